"""The expert daemon (the sonographer's side); ``humantele expert`` runs it.

It runs the 1 kHz servo process (:class:`humantele.haptics.supervisor.SupervisedServo`: its
own OS process, restarted when it dies), and at the link's pose rate:

- reads the servo's latest sample, maps the stylus as the device read it (``T_device_stylus``)
  once through the registration and clutch (:mod:`humantele.expert.mapping`) and publishes the
  virtual transducer pose ``T_patient_probe`` (tip frame) on the ``pose`` channel; the servo
  renders with the same registration (the daemon passes each change on);
- receives the follower's state (probe pose, force) and control messages; each ellipsoid model
  the follower sends is installed in the servo loop (with the registration placing the device
  workspace over it).

The force loop never waits on the network: when the link fails, the servo keeps rendering the
last model, and the daemon keeps running until the follower is back (the link rejoins through
signaling by itself; the follower sends its saved model again on Hello).

Message handling is one method per kind (``on_state``, ``on_control``, ``on_link_state``,
``publish_pose``).

Recording (``--record FILE`` or ``[expert.session] record``): every published pose
(``/expert/pose``, the same ``t`` as the PoseMessage) and the rendered force (``/expert/force``,
patient frame); the figures of :mod:`humantele.expert.figures` and, when it changes, the
clock-sync estimate; scans (:mod:`humantele.expert.scans`); every received video frame
(:mod:`humantele.media.receiver`). ``t`` is this daemon's monotonic clock (s), the one its
ClockSync uses. A path that cannot be recorded to stops the daemon at start (exit code 2); a
failure during the session is reported in the stats and never stops the haptics or the session.

Its configuration is :mod:`humantele.expert.config` (motion scaling has one setting,
``[expert.mapping] scale``), its command line :mod:`humantele.expert.cli`.
"""

from __future__ import annotations

import asyncio
import logging
import math
import sys
import time
from typing import Any

import numpy as np

from humantele.cliargs import EXIT_FAILED
from humantele.daemons.common import Daemon
from humantele.expert.config import ExpertConfig, servo_config_for
from humantele.expert.console.expert_view import PoseHistory, calibration_display
from humantele.expert.console.hook import DaemonConsole
from humantele.expert.figures import ExpertFigures
from humantele.expert.mapping import Registration, StylusMapping, default_registration
from humantele.expert.scans import ScanScript
from humantele.geometry import Pose
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.haptics.servo_config import ServoConfig
from humantele.haptics.servo_layout import ServoError
from humantele.haptics.supervisor import SupervisedServo
from humantele.interop.sessions import ExpertIgtl
from humantele.media.receiver import VideoReceiver
from humantele.transport import PeerLink
from humantele.wire import (
    CalibrationProgress,
    ControlMessage,
    EllipsoidModel,
    PoseMessage,
    StateMessage,
    UsScale,
)

log = logging.getLogger(__name__)


class ExpertDaemon(Daemon):
    """The expert's state and message handlers; :meth:`run` is the daemon."""

    role = "expert"

    def __init__(
        self,
        config: ExpertConfig,
        servo_config: ServoConfig | None = None,
        stats_file: str | None = None,
    ) -> None:
        super().__init__(config, stats_file)
        self.servo_config = servo_config_for(config.mapping, servo_config or ServoConfig())
        self.servo = SupervisedServo(self.servo_config, config.servo_restart_s)
        self.model: Ellipsoid | None = None
        self.mapping = StylusMapping(
            config.mapping, default_registration(config.mapping, (0.0, 0.0, 0.0))
        )
        self.link = PeerLink(
            "expert",
            config.link,
            on_state=self.on_state,
            on_control=self.on_control,
            on_link_state=self.on_link_state,
            media=lambda pc, role: self.video.prepare(pc),
        )
        # The follower's us and pov tracks: the latest decoded frame of each, with its capture
        # time on this clock (self.video.latest("us")), for the console.
        self.video = VideoReceiver(
            config.video,
            self.link.clock,
            self.link.now,
            self.record_any,
            recording=lambda: self.rec is not None,  # then every frame is recorded encoded
        )
        self.pose_seq = 0
        self.figures = ExpertFigures()  # the pose and state streams' counters
        self.last_state: StateMessage | None = None
        self.last_state_t: float | None = None  # its sample time on this clock (s)
        self.last_pose: Pose | None = None
        self.igtl = ExpertIgtl(config.igtl)
        self.models_installed = 0
        self.models_refused = 0
        self.model_refusal = ""  # why the last refused model was refused
        self.calibration_events: list[str] = []
        self.last_sample_t = -math.inf
        self.scans = ScanScript(
            config.scans, lambda msg: self.link.send_control(msg), lambda: self.rec
        )
        self.model_t: float | None = None  # when the first patient model arrived
        # What the console shows (humantele.expert.console): calibration progress, the poses
        # of the last seconds (a captured frame gets its pose), the console's clutch.
        self.calibration_state = "not calibrated"
        self.calibration_landmark: str | None = None
        self.last_state_age: float | None = None  # its one-way age then (s)
        self.probe_history = PoseHistory()
        self.virtual_history = PoseHistory()
        self.console_clutch = False
        receiver = self.video if config.video.enabled else None
        self.console_host = DaemonConsole(config.console, receiver, config.archive)

    # --- incoming messages, one handler per kind ------------------------------------------

    def on_state(self, msg: StateMessage) -> None:
        """The follower's probe (patient frame) and force (tip frame)."""
        self.last_state = msg
        age = self.link.age_of(msg.t_sent)
        now = self.clock()
        self.last_state_age = age if age is not None and math.isfinite(age) else None
        self.figures.state_received(self.last_state_age)
        if isinstance(msg, StateMessage):
            self.probe_history.add(now - max(0.0, self.last_state_age or 0.0), msg.pose)
        ok = age is not None and math.isfinite(age)
        self.last_state_t = time.monotonic() - (max(0.0, age) if ok else 0.0)

    def on_control(self, msg: ControlMessage) -> None:
        if isinstance(msg, EllipsoidModel):
            try:
                model = Ellipsoid.from_dict(msg.model.model_dump())
            except ValueError as exc:
                self.refuse_model(str(exc))
                return
            self.install_model(model)
        elif isinstance(msg, UsScale):
            self.console_host.on_us_scale(msg)
        elif isinstance(msg, CalibrationProgress):
            text = msg.event if not msg.detail else f"{msg.event}: {msg.detail}"
            self.calibration_events.append(text)
            self.on_calibration(msg)
            log.info("follower calibration: %s", text)

    @property
    def console(self) -> Any:
        """The console server while served (None: not served)."""
        return self.console_host.server

    @console.setter
    def console(self, server: Any) -> None:
        self.console_host.server = server

    @property
    def us_scale(self) -> tuple[tuple[float, float], float] | None:
        """The follower's US scale as the console uses it (None: not sent, or configured)."""
        return self.console_host.us_scale

    def apply_us_scale(self, frames: object) -> None:
        self.console_host.apply_us_scale(frames)

    def on_calibration(self, msg: CalibrationProgress) -> None:
        """Calibration progress as the follower reports it: which landmark comes next."""
        self.calibration_state, self.calibration_landmark = calibration_display(
            self.calibration_state, msg, self.model is not None
        )

    def on_link_state(self, state: str) -> None:
        log.info("expert: link %s", state)

    # --- the model and the registration ---------------------------------------------------

    def refuse_model(self, why: str) -> None:
        """A patient model that is not a body: refused, counted, reported; the last good stays."""
        self.models_refused += 1
        self.model_refusal = why
        log.warning(
            "expert: patient model refused (%s); %s", why,
            "keeping the last good one" if self.model is not None else "no model yet",
        )  # fmt: skip

    def install_model(self, model: Ellipsoid) -> None:
        """Render ``model`` (patient frame); a new one moves the workspace over it. A model
        that is not a body (:meth:`Ellipsoid.problem`) is refused and the last good one kept."""
        why = model.problem()
        if why is not None:
            self.refuse_model(why)
            return
        if self.model is not None and model == self.model:
            return  # the same model again (the follower rejoined): nothing changes
        self.model = model
        self.models_installed += 1
        if self.calibration_state != "calibrating":
            self.calibration_state = "calibrated"
        if self.model_t is None:
            self.model_t = self.clock()
        top = np.array(model.center) + [0.0, float(model.semi_axes[1]), 0.0]
        self.mapping.set_registration(default_registration(self.config.mapping, top))
        self.push_registration()
        self.servo.set_model(None if self.mapping.clutched else model)
        log.info("expert: patient model installed: %s", model)

    def push_registration(self) -> None:
        reg: Registration = self.mapping.registration
        self.mapping.take_changed()
        self.servo.set_registration(reg.T_patient_device, reg.scale)

    # --- outgoing -------------------------------------------------------------------------

    def publish_pose(self, t: float) -> None:
        s = self.servo.latest()
        if s is None or s.t <= self.last_sample_t or not self.link.connected:
            return
        self.last_sample_t = s.t
        was_clutched = self.mapping.clutched
        stylus = s.T_device_stylus  # the mapping is applied once, here
        buttons = s.buttons
        if self.console_clutch:  # the console's clutch button holds it as the stylus's does
            buttons |= 1 << self.config.mapping.clutch_button
        pose = self.mapping.update(stylus.position, stylus.quaternion, buttons)
        self.last_pose = pose  # T_patient_stylus as sent (OpenIGTLink serves it)
        if self.mapping.take_changed():
            self.push_registration()
        if self.mapping.clutched != was_clutched and self.model is not None:
            self.servo.set_model(None if self.mapping.clutched else self.model)
        self.virtual_history.add(t, pose)
        self.pose_seq += 1
        msg = PoseMessage.from_pose(
            self.pose_seq, t, pose, s.buttons & 0xFF, clutch=self.mapping.clutched
        )
        self.figures.pose_sent(t, self.link.send_pose(msg))
        if self.rec is not None:  # what was published, at the PoseMessage's t
            self.rec.write(
                "/expert/pose", t, {"position": msg.position, "quaternion": msg.quaternion}
            )
            self.rec.write("/expert/force", t, {"force": s.force, "depth_m": s.depth})

    # --- scans (humantele.expert.scans) and the figures (humantele.expert.figures) -------

    @property
    def scan(self) -> int | None:
        """The scan in progress (None: none)."""
        return self.scans.scan

    @property
    def scans_started(self) -> int:
        return self.scans.started

    @property
    def poses_sent(self) -> int:
        return self.figures.poses_sent

    def start_scan(self, t: float) -> int:
        """Start the next scan (a running one is stopped first); returns its number."""
        return self.scans.start(t)

    def stop_scan(self, t: float) -> None:
        """Stop the scan in progress (nothing if none)."""
        self.scans.stop(t)

    def script_scans(self, t: float) -> None:
        """The scripted scans of ``[expert.scans]``."""
        self.scans.tick(t, self.model_t)

    def record_reports(self, t: float) -> None:
        """Clock sync when it changes; servo statistics and latency about once a second."""
        if self.rec is not None:
            self.clock_log.update(self.rec, self.link.clock)
            self.figures.record(self.rec, t, self.servo)

    def stats(self) -> dict:
        try:
            servo = self.servo.stats().as_dict()
        except ServoError:
            servo = {}
        latest = self.servo.latest() if self.servo.alive else None
        state = self.servo.state(latest)
        # A servo that is down drives no force: 0, and the state says why (never None).
        force = 0.0 if latest is None else round(float(np.linalg.norm(latest.force)), 3)
        return {
            **self.common_stats(self.link),
            "servo_pid": self.servo.pid,
            **self.figures.stats(),
            "models_installed": self.models_installed,
            "has_model": self.model is not None,
            "calibration_events": self.calibration_events[-8:],
            "clutch_reindexes": self.mapping.reindex_count,
            "force_n": force,
            "servo_state": state,
            "servo_fault": state if state.startswith("down") else (latest.fault if latest else ""),
            "models_refused": self.models_refused,
            "model_refusal": self.model_refusal,
            "servo_models_refused": servo.get("models_refused"),
            "servo_tick_errors": servo.get("tick_errors"),
            "servo_rate_hz": servo.get("rate_hz"),
            "servo_overruns": servo.get("overruns"),
            "servo_period_p99_us": servo.get("period_p99_us"),
            "servo_realtime": servo.get("realtime"),
            "servo_restarts": self.servo.restarts,
            "cpu_percent_servo": self.servo.cpu_percent(),
            "scan": self.scan,
            "scans_started": self.scans_started,
            "step_errors": self.step_errors,
            "console": None if self.console is None else self.console.stats(),
            "igtl": self.igtl.stats(),
            "video": self.video.stats() if self.config.video.enabled else None,
        }

    def publish_igtl(self, t: float) -> None:
        """The stylus as sent and the follower's probe as received, to OpenIGTLink clients."""
        us = self.video.latest("us") if self.config.video.enabled else None
        self.igtl.tick(t, self.last_pose, self.last_state, self.last_state_t, us)

    async def run(self, duration_s: float | None = None) -> int:
        if not self.start_run():
            return 2
        try:
            await asyncio.get_running_loop().run_in_executor(None, self.servo.start)
        except ServoError as exc:
            log.error("expert: %s", exc)
            print(f"humantele expert: {exc}", file=sys.stderr)
            self.close_recording()
            return 1
        self.push_registration()
        await self.console_host.start(self)
        await self.igtl.start()
        if self.igtl.banner():
            print(f"humantele expert: {self.igtl.banner()}", flush=True)
        link_task = asyncio.create_task(self.link.run())
        try:
            async for t in self.loop_ticks(self.config.link.pose_rate_hz, duration_s, link_task):
                self.servo.check(t)
                self.publish_pose(t)
                # aiortc sends from a task of its own: let the pose go before the rest of the
                # tick (OpenIGTLink, scans, recording reports) instead of after it.
                await asyncio.sleep(0)
                self.guarded(self.publish_igtl, t)
                self.guarded(self.script_scans, t)
                self.guarded(self.record_reports, t)
        finally:
            self.guarded(self.stop_scan, self.clock())  # the scan ends before the bye
            await self.close_link(self.link, link_task)
            await self.console_host.stop()
            await self.video.close()
            await self.servo.stop()  # a restart in flight stops what it started
            await self.igtl.stop()
            self.finish_run()
        code = self.run_result(link_task)
        # The haptics could not run at the end (not: killed and restarting): not a clean run.
        if code == 0 and self.servo.cannot_run:
            print(f"humantele expert: servo not running: {self.servo.cannot_run}",
                  file=sys.stderr)  # fmt: skip
            return EXIT_FAILED
        return code

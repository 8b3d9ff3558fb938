"""``humantele expert``: the expert daemon (the sonographer's side).

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
patient frame); about once a second the servo statistics, the state stream's one-way latency
and, when it changes, the clock-sync estimate; scan starts and stops; every received video
frame's number and age (``/expert/video_frame``, :mod:`humantele.media.receiver`). ``t`` is this
daemon's monotonic clock (s), the one its ClockSync uses. A path that cannot be recorded to
stops the daemon at start (exit code 2); a failure during the session is reported in the stats
and never stops the haptics or the session.

Scans are started and stopped by the expert (:meth:`ExpertDaemon.start_scan`, ``stop_scan``);
each is announced to the follower with a ``Scan`` control message. ``[expert.scans]`` scripts
them (the demo's: one scan from shortly after the patient model arrives until the daemon
stops).

Motion scaling has one setting, ``[expert.mapping] scale``; the servo gets it from the daemon
(``[servo] motion_scale`` is refused, see :func:`servo_config_for`).
"""

from __future__ import annotations

import argparse
import asyncio
import bisect
import logging
import math
import os
import sys
import time
from collections import deque
from collections.abc import Callable

import numpy as np
from pydantic import Field

from humantele.cliargs import EXIT_FAILED, port
from humantele.config import ConfigError, ConfigModel, load_config, validate_config
from humantele.expert.console import ConsoleConfig
from humantele.expert.console.hook import LANDMARKS, PoseHistory, make_console
from humantele.expert.mapping import (
    MappingConfig,
    Registration,
    StylusMapping,
    default_registration,
)
from humantele.geometry import Pose
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.haptics.servo_config import ServoConfig
from humantele.haptics.servo_layout import ServoError
from humantele.haptics.supervisor import SupervisedServo
from humantele.interop.igtl import IgtlConfig
from humantele.interop.sessions import ExpertIgtl
from humantele.media.config import ExpertVideoConfig
from humantele.media.receiver import VideoReceiver
from humantele.recording import RecorderConfig
from humantele.runtime.daemon import (
    Daemon,
    add_daemon_arguments,
    daemon_overrides,
    run_daemon_process,
    setup_logging,
)
from humantele.runtime.session import SessionConfig, recorder_stats
from humantele.runtime.stats import SortedWindow, percentile_ms
from humantele.transport import LinkConfig, PeerLink
from humantele.wire import (
    CalibrationProgress,
    ControlMessage,
    EllipsoidModel,
    PoseMessage,
    Scan,
    StateMessage,
    UsScale,
)

log = logging.getLogger(__name__)

REPORT_PERIOD_S = 1.0  # servo statistics and latency figures are recorded this often


class ScanScriptConfig(ConfigModel):
    """Scripted scans (``[expert.scans]``): scan 1 starts ``start_after_model_s`` after the
    first patient model arrives and lasts ``length_s`` (None: until the daemon stops); then,
    with ``repeat``, the next one starts ``gap_s`` later. ``enabled = false``: scans only by
    hand (:meth:`ExpertDaemon.start_scan`)."""

    enabled: bool = Field(True, description="script the scans (the demo's)")
    start_after_model_s: float = Field(2.0, ge=0, le=3600, description="first scan after, s")
    length_s: float | None = Field(None, gt=0, le=36000, description="None: until the stop")
    repeat: bool = Field(False, description="start the next scan gap_s after one ends")
    gap_s: float = Field(2.0, ge=0, le=3600, description="between scripted scans, s")


class ExpertConfig(ConfigModel):
    """The expert daemon (``[expert]`` of configs/expert.toml; the servo has ``[servo]``)."""

    servo_restart_s: float = Field(2.0, gt=0, le=60, description="retry a dead servo after")
    # Poses at 100 Hz, as the published system (C&G 2024, Table 1; docs/references.md).
    link: LinkConfig = LinkConfig(pose_rate_hz=100.0)
    mapping: MappingConfig = MappingConfig()
    scans: ScanScriptConfig = ScanScriptConfig()
    video: ExpertVideoConfig = ExpertVideoConfig()
    session: SessionConfig = SessionConfig()
    recording: RecorderConfig = RecorderConfig()
    console: ConsoleConfig = ConsoleConfig()
    igtl: IgtlConfig = IgtlConfig()


def servo_config_for(mapping: MappingConfig, servo: ServoConfig) -> ServoConfig:
    """The servo's configuration with the mapping's motion scale: ``[expert.mapping] scale`` is
    the one setting (the passivity check then sees the scale actually used). A non-default
    ``[servo] motion_scale`` is refused with a ConfigError saying where to set it."""
    default = ServoConfig.model_fields["motion_scale"].default
    if servo.motion_scale not in (default, mapping.scale):
        raise ConfigError(
            f"[servo] motion_scale = {servo.motion_scale:g}: the expert daemon takes the motion "
            f"scale from the mapping; remove it and set [expert.mapping] scale = "
            f"{servo.motion_scale:g} instead"
        )
    data = servo.model_dump()
    data["motion_scale"] = mapping.scale
    return validate_config(ServoConfig, data, "[servo] with [expert.mapping] scale")


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
        self.poses_sent = 0
        self.pose_send_failures = 0
        self.pose_times: deque[float] = deque(maxlen=4000)
        self.last_state: StateMessage | None = None
        self.last_state_t: float | None = None  # its sample time on this clock (s)
        self.last_pose: Pose | None = None
        self.igtl = ExpertIgtl(config.igtl)
        self.states_received = 0
        self.state_ages = SortedWindow(20000)  # s; percentiles without sorting on the loop
        self.models_installed = 0
        self.models_refused = 0
        self.model_refusal = ""  # why the last refused model was refused
        self.calibration_events: list[str] = []
        self.last_sample_t = -math.inf
        # Scans.
        self.scan: int | None = None  # the scan in progress
        self.scans_started = 0
        self.scan_changed_t = -math.inf  # when the last scan started or stopped
        self.model_t: float | None = None  # when the first patient model arrived
        self._late_ticks_reported = 0
        self._states_reported = 0
        self.step_errors = 0
        # What the console shows (humantele.expert.console): calibration progress, the poses
        # of the last seconds (a captured frame gets its pose), the console's clutch.
        self.calibration_state = "not calibrated"
        self.calibration_landmark: str | None = None
        self.last_state_age: float | None = None  # its one-way age then (s)
        self.probe_history = PoseHistory()
        self.virtual_history = PoseHistory()
        self.console_clutch = False
        self.console = None
        self._console_video = None
        self.us_scale: tuple[tuple[float, float], float] | None = None  # the follower's

    # --- incoming messages, one handler per kind ------------------------------------------

    def on_state(self, msg: StateMessage) -> None:
        """The follower's probe (patient frame) and force (tip frame)."""
        self.last_state = msg
        self.states_received += 1
        age = self.link.age_of(msg.t_sent)
        now = self.clock()
        self.last_state_age = age if age is not None and math.isfinite(age) else None
        if self.last_state_age is not None:
            self.state_ages.append(max(0.0, age))
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
            self.on_us_scale(msg)
        elif isinstance(msg, CalibrationProgress):
            text = msg.event if not msg.detail else f"{msg.event}: {msg.detail}"
            self.calibration_events.append(text)
            self.on_calibration(msg)
            log.info("follower calibration: %s", text)

    def on_us_scale(self, msg: UsScale) -> None:
        """The follower's scanner scale: the console's calipers and depth scale take it,
        unless ``[expert.console]`` sets them (the configuration wins, and says so)."""
        frames = getattr(self.console, "frames", None)
        cfg = self.config.console
        if cfg.us_pixel_spacing_mm is not None or cfg.us_depth_origin_row is not None:
            log.info("expert: the follower's US scale %s ignored: [expert.console] sets it",
                     msg.pixel_spacing_mm)  # fmt: skip
            return
        self.us_scale = (msg.pixel_spacing_mm, msg.depth_origin_row)
        self.apply_us_scale(frames)

    def apply_us_scale(self, frames: object) -> None:
        """The follower's scale on the console's received frames (not the sim stand-in)."""
        if self.us_scale is not None and hasattr(frames, "us_spacing_mm"):
            frames.us_spacing_mm, frames.us_depth_origin_row = self.us_scale

    def on_calibration(self, msg: CalibrationProgress) -> None:
        """Calibration progress as the follower reports it: which landmark comes next."""
        nxt = None
        if msg.event == "start":
            self.calibration_state, nxt = "calibrating", 0
        elif msg.event == "point" and msg.index is not None:
            self.calibration_state, nxt = "calibrating", msg.index + 1
        elif msg.event == "error":
            self.calibration_state = "calibrating"
            nxt = msg.index if msg.index is not None else None
        elif msg.event == "done":
            self.calibration_state = "calibrated"
        elif msg.event == "cancel":
            self.calibration_state = "calibrated" if self.model is not None else "not calibrated"
        self.calibration_landmark = (
            LANDMARKS[nxt] if nxt is not None and nxt < len(LANDMARKS) else None
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
        if self.link.send_pose(msg):
            self.poses_sent += 1
            self.pose_times.append(t)
        else:
            self.pose_send_failures += 1
        if self.rec is not None:  # what was published, at the PoseMessage's t
            self.rec.write(
                "/expert/pose", t, {"position": msg.position, "quaternion": msg.quaternion}
            )
            self.rec.write("/expert/force", t, {"force": s.force, "depth_m": s.depth})

    # --- scans ----------------------------------------------------------------------------

    def start_scan(self, t: float) -> int:
        """Start the next scan (a running one is stopped first); returns its number."""
        if self.scan is not None:
            self.stop_scan(t)
        self.scans_started += 1
        self.scan = self.scans_started
        self.scan_changed_t = t
        if self.rec is not None:
            self.rec.scan_start(t, self.scan)
        self.link.send_control(Scan(action="start", scan_id=str(self.scan)))
        log.info("expert: scan %d started", self.scan)
        return self.scan

    def stop_scan(self, t: float) -> None:
        """Stop the scan in progress (nothing if none)."""
        if self.scan is None:
            return
        if self.rec is not None:
            self.rec.scan_stop(t, self.scan)
        self.link.send_control(Scan(action="stop", scan_id=str(self.scan)))
        log.info("expert: scan %d stopped", self.scan)
        self.scan = None
        self.scan_changed_t = t

    def script_scans(self, t: float) -> None:
        """The scripted scans of ``[expert.scans]``."""
        cfg = self.config.scans
        if not cfg.enabled or self.model_t is None:
            return
        if self.scan is None:
            first = self.scans_started == 0
            if first and t - self.model_t >= cfg.start_after_model_s:
                self.start_scan(t)
            elif not first and cfg.repeat and t - self.scan_changed_t >= cfg.gap_s:
                self.start_scan(t)
        elif cfg.length_s is not None and t - self.scan_changed_t >= cfg.length_s:
            self.stop_scan(t)

    # --- recording of the figures ---------------------------------------------------------

    def record_reports(self, t: float) -> None:
        """Clock sync when it changes; servo statistics and latency about once a second."""
        rec = self.rec
        if rec is None:
            return
        self.clock_log.update(rec, self.link.clock)
        if t - self._last_report < REPORT_PERIOD_S:
            return
        self._last_report = t
        if self.servo.alive:
            try:
                st = self.servo.stats()
            except ServoError:
                st = None
            if st is not None and st.ticks > 0:
                latest = self.servo.latest()
                fault = "" if latest is None else latest.fault
                rec.write(
                    "/expert/servo_stats",
                    t,
                    {
                        "rate_hz": st.rate_hz,
                        "period_p99_s": st.period_p99_us * 1e-6,
                        "late_ticks": max(0, st.late_ticks - self._late_ticks_reported),
                        "state": f"fault:{fault}" if fault else "running",
                    },
                )
                self._late_ticks_reported = st.late_ticks
        else:
            rec.write("/expert/servo_stats", t, {"rate_hz": 0.0, "state": "stopped"})
        new = min(len(self.state_ages), self.states_received - self._states_reported)
        self._states_reported = self.states_received
        recent = self.state_ages.last(new)
        if recent:  # the follower's state stream, one way: median since the last report
            rec.write(
                "/expert/latency", t, {"name": "state_one_way", "value_s": float(np.median(recent))}
            )

    def record_any(self, topic: str, t: float, payload: dict) -> None:
        """Record one sample if recording (the recorder only queues)."""
        rec = self.rec
        if rec is not None:
            rec.write(topic, t, payload)

    def pose_rate_hz(self, window_s: float = 1.0) -> float:
        now = time.monotonic()
        recent = len(self.pose_times) - bisect.bisect_left(self.pose_times, now - window_s)
        return round(recent / window_s, 1)

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
            "role": "expert",
            "pid": os.getpid(),
            "servo_pid": self.servo.pid,
            "uptime_s": round(time.monotonic() - self.t_start, 3),
            "link_state": self.link.state,
            "connections": self.link.counters.connections,
            "poses_sent": self.poses_sent,
            "pose_rate_hz": self.pose_rate_hz(),
            "states_received": self.states_received,
            "state_age_p50_ms": percentile_ms(self.state_ages, 50),
            "state_age_p99_ms": percentile_ms(self.state_ages, 99),
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
            "dropped": dict(self.link.counters.dropped),
            "dropped_total": sum(self.link.counters.dropped.values()),
            "cpu_percent": self.cpu.overall(),
            "loop_priority": self.loop_priority,
            "cpu_percent_servo": self.servo.cpu_percent(),
            "scan": self.scan,
            "scans_started": self.scans_started,
            "step_errors": self.step_errors,
            "recording": recorder_stats(self.rec),
            "console": None if self.console is None else self.console.stats(),
            "igtl": self.igtl.stats(),
            "video": self.video.stats() if self.config.video.enabled else None,
        }

    def publish_igtl(self, t: float) -> None:
        """The stylus as sent and the follower's probe as received, to OpenIGTLink clients."""
        us = self.video.latest("us") if self.config.video.enabled else None
        self.igtl.tick(t, self.last_pose, self.last_state, self.last_state_t, us)

    def guarded(self, step: Callable[[float], object], t: float) -> None:
        """Run a step that must never end the daemon (scans, recording); failures counted."""
        try:
            step(t)
        except Exception:
            self.step_errors += 1
            if self.step_errors in (1, 10, 100, 1000):
                log.exception("expert: %s failed (%d so far)", step.__name__, self.step_errors)

    async def start_console(self) -> None:
        """Serve the console page (``[expert.console]``); a port that cannot be had is logged
        and the daemon runs without it (the haptics come first)."""
        if not self.config.console.enabled or self.console is not None:
            return
        self.console, self._console_video = make_console(self)
        self.apply_us_scale(self.console.frames)  # one that came before the console
        try:
            await self.console.start()
        except OSError as exc:
            log.error("expert: console not served: %s", exc)
            print(f"humantele expert: console not served: {exc}", flush=True)
            self.console = None
            return
        print(f"humantele expert: {self.console.banner()}", flush=True)

    async def stop_console(self) -> None:
        if self._console_video is not None:
            await asyncio.to_thread(self._console_video.stop)
            self._console_video = None
        if self.console is not None:
            await self.console.stop()

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
        await self.start_console()
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
            await self.stop_console()
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


# --- command line ---------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_daemon_arguments(parser, "TOML file; [expert] and [servo] sections are used")
    parser.add_argument("--console-port", type=int, help="console page port (0 picks one)")
    parser.add_argument("--no-console", action="store_true", help="do not serve the console page")
    parser.add_argument(
        "--us-pixel-spacing-mm", type=float, nargs=2, metavar=("ROW", "COL"),
        help="mm per pixel of the received ultrasound image, for the console's calipers",
    )  # fmt: skip
    parser.add_argument(
        "--us-depth-origin-row", type=float, metavar="ROW",
        help="row (px) of depth 0 of the received ultrasound image, for the console's depth scale",
    )  # fmt: skip
    parser.add_argument(
        "--igtl-port",
        type=port,
        help="serve OpenIGTLink on this port (0 picks one; 18944 Slicer's)",
    )


def configs_from_args(args: argparse.Namespace) -> tuple[ExpertConfig, ServoConfig]:
    config = load_config(ExpertConfig, args.config, "expert" if args.config else None)
    servo = load_config(ServoConfig, args.config, "servo" if args.config else None)
    data = config.model_dump()
    if getattr(args, "console_port", None) is not None:
        data["console"]["port"] = args.console_port
    if getattr(args, "no_console", False):
        data["console"]["enabled"] = False
    if getattr(args, "us_pixel_spacing_mm", None):
        data["console"]["us_pixel_spacing_mm"] = tuple(args.us_pixel_spacing_mm)
    if getattr(args, "us_depth_origin_row", None) is not None:
        data["console"]["us_depth_origin_row"] = args.us_depth_origin_row
    if getattr(args, "igtl_port", None) is not None:
        data["igtl"].update(enabled=True, port=args.igtl_port)
    daemon_overrides(args, data)
    config = validate_config(ExpertConfig, data, "command line")
    return config, servo_config_for(config.mapping, servo)


def run(args: argparse.Namespace) -> int:
    setup_logging("expert", args.log_level)
    config, servo = configs_from_args(args)
    return run_daemon_process(ExpertDaemon(config, servo, args.stats_file), args.duration)

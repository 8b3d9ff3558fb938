"""``humantele expert``: the expert daemon (the sonographer's side).

It runs the 1 kHz servo process (:class:`humantele.haptics.loop.ServoProcess`, its own OS
process), and at the link's pose rate:

- reads the servo's latest sample (the stylus already mapped into the patient frame by the
  registration the daemon gave it), applies the clutch (:mod:`humantele.expert.mapping`) and
  publishes the virtual transducer pose ``T_patient_probe`` (tip frame) on the ``pose`` channel;
- receives the follower's state (probe pose, force) and control messages; each ellipsoid model
  the follower sends is installed in the servo loop (with the registration placing the device
  workspace over it).

The force loop never waits on the network: when the link fails, the servo keeps rendering the
last model, and the daemon keeps running until the follower is back (the link rejoins through
signaling by itself; the follower sends its saved model again on Hello).

Message handling is one method per kind (``on_state``, ``on_control``, ``on_link_state``,
``publish_pose``), so recording can hook in at those places.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import math
import os
import time
from collections import deque

import numpy as np
from pydantic import Field

from humantele.config import ConfigModel, load_config, validate_config
from humantele.demo import (
    CpuMeter,
    on_stop_signals,
    parent_gone,
    percentile_ms,
    process_cpu_seconds,
    write_stats,
)
from humantele.expert.mapping import (
    MappingConfig,
    Registration,
    StylusMapping,
    default_registration,
)
from humantele.geometry import Pose, quat_conjugate, quat_multiply
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.haptics.loop import ServoConfig, ServoError, ServoProcess
from humantele.transport import LinkConfig, PeerLink
from humantele.wire import (
    Calibration as CalibrationMsg,
)
from humantele.wire import (
    ControlMessage,
    EllipsoidModel,
    PoseMessage,
    StateMessage,
)

log = logging.getLogger(__name__)

REINDEX_SETTLE_S = 0.005  # after a registration change, the servo takes it at its next tick


class ExpertConfig(ConfigModel):
    """The expert daemon (``[expert]`` of configs/expert.toml; the servo has ``[servo]``)."""

    servo_restart_s: float = Field(2.0, gt=0, le=60, description="retry a dead servo after")
    # Poses at 100 Hz, as the published system (ANCHORS); the follower's lag is ~0.35 s.
    link: LinkConfig = LinkConfig(pose_rate_hz=100.0)
    mapping: MappingConfig = MappingConfig()


class ExpertDaemon:
    """The expert's state and message handlers; :meth:`run` is the daemon."""

    def __init__(
        self,
        config: ExpertConfig,
        servo_config: ServoConfig | None = None,
        stats_file: str | None = None,
    ) -> None:
        self.config = config
        self.servo_config = servo_config or ServoConfig()
        self.stats_file = stats_file
        self.servo = ServoProcess(self.servo_config)
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
        )
        self.pose_seq = 0
        self.poses_sent = 0
        self.pose_send_failures = 0
        self.pose_times: deque[float] = deque(maxlen=4000)
        self.last_state: StateMessage | None = None
        self.states_received = 0
        self.state_ages: deque[float] = deque(maxlen=20000)
        self.models_installed = 0
        self.calibration_events: list[str] = []
        self.last_pose: Pose | None = None
        self.last_sample_t = -math.inf
        self.hold_until = -math.inf
        self.clock = time.monotonic  # the loop's clock (s); tests may replace it
        self.servo_restarts = 0
        self.cpu = CpuMeter()
        self.t_start = time.monotonic()
        self._servo_dead_since: float | None = None
        self.servo_started: float | None = None
        self._servo_cpu_last: float | None = None
        self._stop = asyncio.Event()

    # --- incoming messages, one handler per kind ------------------------------------------

    def on_state(self, msg: StateMessage) -> None:
        """The follower's probe (patient frame) and force (tip frame)."""
        self.last_state = msg
        self.states_received += 1
        age = self.link.age_of(msg.t_sent)
        if age is not None and math.isfinite(age):
            self.state_ages.append(max(0.0, age))

    def on_control(self, msg: ControlMessage) -> None:
        if isinstance(msg, EllipsoidModel):
            self.install_model(Ellipsoid.from_dict(msg.model.model_dump()))
        elif isinstance(msg, CalibrationMsg):
            text = msg.event if not msg.detail else f"{msg.event}: {msg.detail}"
            self.calibration_events.append(text)
            log.info("follower calibration: %s", text)

    def on_link_state(self, state: str) -> None:
        log.info("expert: link %s", state)

    # --- the model and the registration ---------------------------------------------------

    def install_model(self, model: Ellipsoid) -> None:
        """Render ``model`` (patient frame); a new one moves the workspace over it."""
        if self.model is not None and model == self.model:
            return  # the same model again (the follower rejoined): nothing changes
        self.model = model
        self.models_installed += 1
        top = np.array(model.center) + [0.0, float(model.semi_axes[1]), 0.0]
        self.mapping.set_registration(default_registration(self.config.mapping, top))
        self.push_registration()
        self.servo.set_model(None if self.mapping.clutched else model)
        log.info("expert: patient model installed: %s", model)

    def push_registration(self) -> None:
        reg: Registration = self.mapping.registration
        self.mapping.take_changed()
        self.servo.set_registration(reg.T_patient_device, reg.scale)
        # Hold the published pose until the servo has taken the new registration.
        self.hold_until = self.clock() + REINDEX_SETTLE_S

    # --- outgoing -------------------------------------------------------------------------

    def stylus_in_device(self, pose_patient: Pose) -> tuple[np.ndarray, np.ndarray]:
        """Undo the registration the servo applied: stylus position and quaternion, device."""
        reg = self.mapping.registration
        p = reg.point_to_device(pose_patient.position)
        q = quat_multiply(quat_conjugate(reg.rotation), pose_patient.quaternion)
        return p, q

    def publish_pose(self, t: float) -> None:
        s = self.servo.latest()
        if s is None or s.t <= self.last_sample_t or not self.link.connected:
            return
        self.last_sample_t = s.t
        if t < self.hold_until and self.last_pose is not None:
            pose = self.last_pose  # the servo has not applied the new registration yet
        else:
            was_clutched = self.mapping.clutched
            p_dev, q_dev = self.stylus_in_device(s.pose)
            pose = self.mapping.update(p_dev, q_dev, s.buttons)
            if self.mapping.take_changed():
                self.push_registration()
            if self.mapping.clutched != was_clutched and self.model is not None:
                self.servo.set_model(None if self.mapping.clutched else self.model)
        self.last_pose = pose
        self.pose_seq += 1
        msg = PoseMessage.from_pose(
            self.pose_seq, t, pose, s.buttons & 0xFF, clutch=self.mapping.clutched
        )
        if self.link.send_pose(msg):
            self.poses_sent += 1
            self.pose_times.append(t)
        else:
            self.pose_send_failures += 1

    def check_servo(self, t: float) -> None:
        """A dead servo process is restarted (the daemon itself keeps running)."""
        if self.servo.alive:
            self._servo_dead_since = None
            return
        if self._servo_dead_since is None:
            self._servo_dead_since = t
            log.error("expert: the servo process died; restarting it")
        if t - self._servo_dead_since < self.config.servo_restart_s:
            return
        self._servo_dead_since = t
        self.servo.stop()
        self.servo = ServoProcess(self.servo_config, self.model)
        try:
            self.servo.start()
        except ServoError as exc:
            log.error("expert: %s", exc)
            return
        self.servo_restarts += 1
        self.servo_started = time.monotonic()
        self.push_registration()

    def servo_cpu_percent(self) -> float | None:
        """CPU use (% of one core) of the servo process since it started."""
        pid = self.servo.pid
        cpu = process_cpu_seconds(pid)
        if cpu is None or self.servo_started is None:
            return self._servo_cpu_last
        wall = time.monotonic() - self.servo_started
        self._servo_cpu_last = round(100.0 * cpu / wall, 1) if wall > 0 else None
        return self._servo_cpu_last

    def pose_rate_hz(self, window_s: float = 1.0) -> float:
        now = time.monotonic()
        return round(sum(1 for t in self.pose_times if now - t <= window_s) / window_s, 1)

    def stats(self) -> dict:
        try:
            servo = self.servo.stats().as_dict()
        except ServoError:
            servo = {}
        latest = self.servo.latest() if self.servo.alive else None
        force = None if latest is None else round(float(np.linalg.norm(latest.force)), 3)
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
            "servo_fault": "" if latest is None else latest.fault,
            "servo_rate_hz": servo.get("rate_hz"),
            "servo_overruns": servo.get("overruns"),
            "servo_period_p99_us": servo.get("period_p99_us"),
            "servo_realtime": servo.get("realtime"),
            "servo_restarts": self.servo_restarts,
            "dropped": dict(self.link.counters.dropped),
            "dropped_total": sum(self.link.counters.dropped.values()),
            "cpu_percent": self.cpu.overall(),
            "cpu_percent_servo": self.servo_cpu_percent(),
        }

    async def run(self, duration_s: float | None = None) -> int:
        loop = asyncio.get_running_loop()
        on_stop_signals(loop, self._stop.set)
        try:
            await loop.run_in_executor(None, self.servo.start)
        except ServoError as exc:
            log.error("expert: %s", exc)
            return 1
        self.servo_started = time.monotonic()
        self.push_registration()
        link_task = asyncio.create_task(self.link.run())
        period = 1.0 / self.config.link.pose_rate_hz
        t_end = None if duration_s is None else time.monotonic() + duration_s
        next_t = time.monotonic()
        last_stats = 0.0
        try:
            while not self._stop.is_set() and not link_task.done():
                t = self.clock()
                self.check_servo(t)
                self.publish_pose(t)
                if t - last_stats > 0.5:
                    last_stats = t
                    write_stats(self.stats_file, self.stats())
                    if parent_gone():
                        log.warning("the demo that started this daemon is gone; stopping")
                        break
                if t_end is not None and t >= t_end:
                    break
                next_t += period
                delay = next_t - time.monotonic()
                if delay < -period:
                    next_t = time.monotonic()
                    delay = 0.0
                await asyncio.sleep(max(0.0, delay))
        finally:
            await self.link.close("expert stopping")
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await asyncio.wait_for(link_task, 5.0)
            self.servo_cpu_percent()
            self.servo.stop()
            write_stats(self.stats_file, self.stats())
        return 0


# --- command line ---------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="TOML file; [expert] and [servo] sections are used")
    parser.add_argument("--signaling-url", help="signaling server, e.g. ws://127.0.0.1:8765/ws")
    parser.add_argument("--room", help="session room name")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument("--stats-file", help="write running figures (JSON) to this file")
    parser.add_argument("--log-level", default="WARNING", help="logging level (default WARNING)")


def configs_from_args(args: argparse.Namespace) -> tuple[ExpertConfig, ServoConfig]:
    config = load_config(ExpertConfig, args.config, "expert" if args.config else None)
    servo = load_config(ServoConfig, args.config, "servo" if args.config else None)
    data = config.model_dump()
    if args.signaling_url:
        data["link"]["signaling_url"] = args.signaling_url
    if args.room:
        data["link"]["room"] = args.room
    return validate_config(ExpertConfig, data, "command line"), servo


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(
        level=getattr(logging, str(args.log_level).upper(), logging.WARNING),
        format="%(asctime)s expert %(name)s: %(message)s",
    )
    logging.getLogger("aioice").setLevel(logging.WARNING)
    config, servo = configs_from_args(args)
    return asyncio.run(ExpertDaemon(config, servo, args.stats_file).run(args.duration))

"""``humantele follower``: the follower daemon (the clinic side).

Every tick (``rate_hz``, asyncio) it:

1. moves the probe: the simulated world (:mod:`humantele.follower.sim_world`: patient,
   person, head) advances; its person follows the virtual probe, or performs the calibration
   presses when calibrating;
2. at the tracker's rate (``sensing_rate_hz``) measures it through the sensing pipeline
   (:mod:`humantele.follower.sensing` when present, else the truth behind the same small
   interface), so what it streams is what a real tracker and force sensor would give. The
   pipeline (~5-7 ms a frame) runs on one worker thread, off the asyncio loop, so the pose
   path is never held up; frames are measured in order and never overlap: a frame due while
   the previous one is still measured is skipped (counted in ``sensing_skipped``);
3. with each measurement: feeds the calibration (:mod:`humantele.follower.calibration`) while
   calibrating, streams the probe pose and force to the expert (``state``, patient frame) and
   records them;
4. publishes the virtual probe to renderers (:mod:`humantele.follower.feed`, world frame;
   ``stale`` when no fresh pose came or the link is down).

Frames: the headset's world frame (y up) here; the patient frame of the calibration on the
wire (``T_world_patient`` from the saved calibration). Poses are of the transducer's tip frame
(origin at the centre of the face, +z along the beam); the tool definition says where the tip
is on the tracked probe body.

Message handling is one method per kind (``on_pose``, ``on_control``, ``on_link_state``) and
one per outgoing stream. The calibration is saved under ``state_dir`` and reused after a
restart; every Hello from the expert gets the model. The expert's ``Scan`` messages say which
scan is in progress (``stats()['scan']``, the feed's ``scan`` object).

Recording (``--record FILE`` or ``[follower.session] record``), ``t`` on this daemon's monotonic
clock (the one its ClockSync uses): every tracker frame once calibrated
(``/follower/probe_pose``, patient frame, ``tracked`` false with a zero pose when the probe was
not found), every force reading (``/follower/force``, tip frame), the fitted model
(``/follower/ellipsoid``, world frame), calibration events, the clock-sync estimate when it
changes and the pose stream's one-way latency about once a second. A path that cannot be
recorded to stops the daemon at start (exit code 2); a failure during the session is reported
in the stats and never stops the session.
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
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from humantele.config import ConfigModel, load_config, validate_config
from humantele.follower.calibration import (
    CALIBRATION_FILE,
    LANDMARKS,
    Calibration,
    CalibrationConfig,
    CalibrationEvent,
    Calibrator,
)
from humantele.follower.feed import FeedConfig, RendererFeed, model_fields
from humantele.follower.sim_human import (
    CalibrationScript,
    SimHeadConfig,
    SimHumanConfig,
    SimPatientConfig,
)
from humantele.follower.sim_world import SimWorld, WorldTruth
from humantele.geometry import Pose, matrix_to_quat
from humantele.recording import RecorderConfig
from humantele.runtime.daemon import (
    Daemon,
    add_daemon_arguments,
    daemon_overrides,
    setup_logging,
)
from humantele.runtime.session import SessionConfig, recorder_stats
from humantele.runtime.stats import percentile_ms
from humantele.transport import LinkConfig, PeerLink
from humantele.wire import (
    Calibration as CalibrationMsg,
)
from humantele.wire import (
    ControlMessage,
    EllipsoidModel,
    EllipsoidParams,
    Hello,
    PoseMessage,
    Scan,
    StateMessage,
    TrackingStatus,
)

log = logging.getLogger(__name__)

DEFAULT_STATE_DIR = "~/.local/state/humantele/follower"
REPORT_PERIOD_S = 1.0  # latency figures are recorded this often
ZERO_POSE = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))  # recorded when the probe is not tracked


class FollowerConfig(ConfigModel):
    """The follower daemon (``[follower]`` of configs/follower.toml)."""

    rate_hz: float = Field(100.0, gt=1, le=1000, description="tick: probe, sensing, state")
    stale_after_s: float = Field(0.3, gt=0, le=10, description="virtual probe stale after")
    alignment_settle_s: float = Field(
        1.0, ge=0, le=30, description="alignment error counted this long after following starts"
    )
    state_dir: str = Field(DEFAULT_STATE_DIR, description="where the calibration is saved")
    auto_calibrate: bool = Field(True, description="sim person presses the landmarks")
    probe_source: Literal["pipeline", "truth"] = Field(
        "pipeline", description="measure through the sensing pipeline ([sensing]), or the truth"
    )
    sensing_rate_hz: float = Field(45.0, gt=1, le=1000, description="tracker frames per second")
    tool: str = Field("probe_default", description="probe tool definition (configs/tools)")
    link: LinkConfig = LinkConfig()
    feed: FeedConfig = FeedConfig()
    calibration: CalibrationConfig = CalibrationConfig()
    sim_patient: SimPatientConfig = SimPatientConfig()
    sim_human: SimHumanConfig = SimHumanConfig()
    sim_head: SimHeadConfig = SimHeadConfig()
    session: SessionConfig = SessionConfig()
    recording: RecorderConfig = RecorderConfig()


@dataclass
class Measurement:
    """What the follower knows of its probe at one tick (world frame, SI); ``force_tip`` is
    the same force in the probe's tip frame (None when unknown)."""

    status: TrackingStatus
    T_world_tip: Pose | None
    force_world: NDArray[np.float64]
    contact: bool
    force_tip: NDArray[np.float64] | None = None


@dataclass
class TrackerImage:
    """One tracker image to measure: the simulated world at its time (what the sim sensors
    see; ``truth.t`` is the tick time, s), and the virtual probe and target the tick had
    (world frame, for the alignment figure)."""

    truth: WorldTruth
    virtual: Pose | None
    target: Pose | None

    @property
    def t(self) -> float:
        return self.truth.t


def _tip_transform(tool_name: str) -> Pose:
    """``T_probe_tip``: the tip frame on the tracked probe body (from the tool definition)."""
    try:
        from humantele.tracking.tool import load_tool

        tool = load_tool(tool_name)
        tip, z = np.asarray(tool.tip, dtype=float), np.asarray(tool.face_direction, dtype=float)
    except (ImportError, AttributeError):  # no tracking package: the default tool's figures
        tip, z = np.array([0.0, 0.0, -0.15]), np.array([0.0, 0.0, -1.0])
    z = z / np.linalg.norm(z)
    x = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = x - z * float(x @ z)
    x /= np.linalg.norm(x)
    return Pose(tip, matrix_to_quat(np.column_stack([x, np.cross(z, x), z])))


class Sensing:
    """Measure the probe: the sensing pipeline (sim IR tracker and force sensor) by default,
    else the truth. ``measure(truth)`` (the simulated world at a tracker image) gives a
    :class:`Measurement`; a pipeline error gives a LOST measurement (counted), never a crash.
    """

    def __init__(self, config: FollowerConfig, sensing_config: object | None = None) -> None:
        self.T_probe_tip = _tip_transform(config.tool)
        self.T_tip_probe = self.T_probe_tip.inverse()
        self.pipeline = None
        self.errors = 0
        self.contact_n = config.calibration.force_off_n
        if config.probe_source == "pipeline":
            try:
                from humantele.follower.sensing import ProbeSensing
            except ImportError:
                log.warning("follower: no sensing pipeline here; streaming the simulated truth")
            else:
                self.pipeline = ProbeSensing(sensing_config)

    def measure(self, truth: WorldTruth) -> Measurement:
        t, T_world_tip, force_world = truth.t, truth.T_world_tip, truth.force_world
        T_world_camera = truth.T_world_camera
        lost = Measurement(TrackingStatus.LOST, None, np.zeros(3), False)
        if T_world_tip is None:
            return lost
        if self.pipeline is None:
            contact = float(np.linalg.norm(force_world)) > self.contact_n
            force_tip = T_world_tip.inverse().rotate(force_world)
            return Measurement(TrackingStatus.TRACKED, T_world_tip, force_world, contact, force_tip)
        try:
            m = self.pipeline.measure(
                t, T_world_tip @ self.T_tip_probe, force_world, T_world_camera
            )
        except Exception:  # a sensing fault must not stop the daemon
            self.errors += 1
            if self.errors == 1:
                log.exception("follower: sensing failed (counted, reported as lost)")
            return lost
        force = np.asarray(m.force_world, dtype=float)
        force_tip = self.T_tip_probe.rotate(np.asarray(m.force_probe, dtype=float))
        if not (np.all(np.isfinite(force)) and np.all(np.isfinite(force_tip))):
            force, force_tip = np.zeros(3), None
        if m.status != "tracked" or m.T_world_probe is None:
            return Measurement(TrackingStatus.LOST, None, force, bool(m.contact), force_tip)
        tip = m.T_world_probe @ self.T_probe_tip
        return Measurement(TrackingStatus.TRACKED, tip, force, bool(m.contact), force_tip)

    def close(self) -> None:
        if self.pipeline is not None:
            with contextlib.suppress(Exception):
                self.pipeline.close()


class FollowerDaemon(Daemon):
    """The follower's state and its message handlers; :meth:`run` is the daemon."""

    role = "follower"

    def __init__(
        self,
        config: FollowerConfig,
        stats_file: str | None = None,
        sensing_config: object | None = None,
    ) -> None:
        super().__init__(config, stats_file)
        self.state_dir = Path(config.state_dir).expanduser()
        self.calibration_path = self.state_dir / CALIBRATION_FILE
        self.calibration: Calibration | None = Calibration.load(self.calibration_path)
        self.calibrator = Calibrator(config.calibration)
        self.world = SimWorld(config.sim_patient, config.sim_human, config.sim_head)
        self.sensing = Sensing(config, sensing_config)
        self.measurement = Measurement(TrackingStatus.LOST, None, np.zeros(3), False)
        self.last_measure_t = -math.inf
        self.measurements = 0
        self.feed = RendererFeed(config.feed, self.state_dir)
        self.link = PeerLink(
            "follower",
            config.link,
            on_pose=self.on_pose,
            on_control=self.on_control,
            on_link_state=self.on_link_state,
        )
        self.calibrating = False
        self.following_since: float | None = None
        self.last_force_n = 0.0
        self.script: CalibrationScript | None = None
        self.script_t0 = 0.0
        self.last_pose: PoseMessage | None = None
        self.last_pose_rx = -math.inf
        self.pose_ages: deque[float] = deque(maxlen=20000)
        self.align_pos: deque[float] = deque(maxlen=20000)
        self.align_ang: deque[float] = deque(maxlen=20000)
        self.poses_received = 0
        self.pose_times: deque[float] = deque(maxlen=2000)
        self.state_seq = 0
        self.ticks = 0
        self.tick_errors = 0
        self.tracking_lost = 0
        self.late_ticks = 0
        self.last_event: CalibrationEvent | None = None
        self.loaded_calibration = self.calibration is not None
        # The sensing worker (run() starts it; without it, tick() measures in line).
        self.executor: ThreadPoolExecutor | None = None
        self._sensing: Future | None = None
        self.sensing_skipped = 0
        self.sensing_times: deque[float] = deque(maxlen=2000)  # s per measurement, worker
        # Scans (from the expert) and what has been recorded.
        self.scan: int | None = None
        self.scans_seen = 0
        self._poses_reported = 0
        self._model_recorded: Calibration | None = None

    # --- incoming messages, one handler per kind ------------------------------------------

    def on_pose(self, msg: PoseMessage) -> None:
        """A virtual probe pose from the expert (``T_patient_probe``)."""
        self.last_pose = msg
        self.last_pose_rx = time.monotonic()
        self.poses_received += 1
        self.pose_times.append(self.last_pose_rx)
        age = self.link.age_of(msg.t_sent)
        if age is not None and math.isfinite(age):
            self.pose_ages.append(max(0.0, age))

    def on_control(self, msg: ControlMessage) -> None:
        if isinstance(msg, Hello):
            self.send_model()  # the expert (re)joined: give it the model we have
        elif isinstance(msg, CalibrationMsg) and msg.event == "start":
            self.start_calibration()
        elif isinstance(msg, Scan):
            self.on_scan(msg)

    def on_scan(self, msg: Scan) -> None:
        """The expert started or stopped a scan (its number is ``scan_id``)."""
        number = int(msg.scan_id) if msg.scan_id.isdigit() else None
        if msg.action == "start":
            self.scan = number
            self.scans_seen += 1
        elif self.scan == number or number is None:
            self.scan = None
        log.info("follower: scan %s %s", msg.scan_id, msg.action)
        if number is not None:  # the analysis takes scans from /expert/scan; this is the echo
            self.record("/follower/scan", None, {"event": msg.action, "scan": number})
        self.feed.publish("scan", {"scan": self.scan, "action": msg.action})

    def on_link_state(self, state: str) -> None:
        self.feed.publish("link", {"state": state})

    # --- outgoing -------------------------------------------------------------------------

    def send_control(self, msg: ControlMessage) -> bool:
        """Control messages only while connected (the expert learns the rest on Hello)."""
        return self.link.connected and self.link.send_control(msg)

    def send_model(self) -> bool:
        if self.calibration is None:
            return False
        params = EllipsoidParams(**self.calibration.model_patient().to_dict())
        return self.send_control(EllipsoidModel(model=params))

    def send_state(self, t: float, m: Measurement) -> None:
        """The measured probe (patient frame) and force (probe tip frame) to the expert."""
        if self.calibration is None or m.T_world_tip is None or not self.link.connected:
            return
        T_patient_tip = self.calibration.T_world_patient.inverse() @ m.T_world_tip
        force_tip = m.T_world_tip.inverse().rotate(m.force_world)
        self.state_seq += 1
        self.link.send_state(
            StateMessage(
                self.state_seq,
                t,
                tuple(T_patient_tip.position),
                tuple(T_patient_tip.quaternion),
                m.status,
                tuple(float(v) for v in force_tip),
                m.contact,
            )
        )

    def publish_feed(self, t: float, virtual: Pose | None, m: Measurement) -> None:
        age = None if self.last_pose is None else self.link.age_of(self.last_pose.t_sent)
        if virtual is not None:
            self.feed.publish(
                "virtual_probe",
                {
                    "position": virtual.position,
                    "quaternion": virtual.quaternion,
                    "age_ms": None if age is None else age * 1000.0,
                    "stale": self.virtual_stale(t),
                    "clutch": bool(self.last_pose.clutch) if self.last_pose else False,
                },
                t_origin=self.last_pose_rx,
            )
        if m.T_world_tip is not None:
            self.feed.publish(
                "probe",
                {
                    "position": m.T_world_tip.position,
                    "quaternion": m.T_world_tip.quaternion,
                    "force": m.force_world,
                    "contact": m.contact,
                    "tracking": m.status.name.lower(),
                },
            )

    def publish_model(self) -> None:
        """The fitted ellipsoid (world frame) for the page's outline, if calibrated."""
        if self.calibration is not None:
            self.feed.publish("model", model_fields(self.calibration.ellipsoid))

    def publish_calibration(self, event: CalibrationEvent | None = None) -> None:
        step = self.calibrator.step if self.calibrating else None
        self.feed.publish(
            "calibration",
            {
                "calibrated": self.calibration is not None,
                "calibrating": self.calibrating,
                "step": step,
                "prompt": self.calibrator.prompt() if self.calibrating else "",
                "event": None if event is None else event.kind,
                "landmark": None if event is None else event.landmark,
                "message": "" if event is None else event.message,
            },
        )

    # --- calibration ----------------------------------------------------------------------

    def start_calibration(self) -> None:
        self.calibrating = True
        self.calibrator.reset()
        self.record("/follower/calibration", time.monotonic(), {"event": "reset"})
        self.script = self.world.calibration_script() if self.config.auto_calibrate else None
        self.script_t0 = time.monotonic()
        self.send_control(CalibrationMsg(event="start"))
        self.publish_calibration()

    def on_calibration_event(self, ev: CalibrationEvent, t: float | None = None) -> None:
        self.last_event = ev
        log.info("calibration: %s", ev.message)
        index = LANDMARKS.index(ev.landmark)
        point = tuple(float(v) for v in ev.point)
        self.record_calibration_event(t, ev)
        if ev.kind == "refused":
            self.send_control(
                CalibrationMsg(event="error", index=index, point=point, detail=ev.message[:200])
            )
        else:
            self.send_control(CalibrationMsg(event="point", index=index, point=point))
        if ev.kind == "done" and self.calibrator.result is not None:
            self.calibration = self.calibrator.result
            self.calibration.save(self.calibration_path)
            self.calibrating = False
            self.script = None
            self.send_control(CalibrationMsg(event="done"))
            self.send_model()
            self.record_model(t)
            self.publish_model()
        self.publish_calibration(ev)

    # --- the tick -------------------------------------------------------------------------

    def virtual_stale(self, t: float) -> bool:
        return not self.link.connected or t - self.last_pose_rx > self.config.stale_after_s

    def virtual_world(self) -> Pose | None:
        """The virtual probe's tip pose in the world, or None without a pose or calibration."""
        if self.last_pose is None or self.calibration is None:
            return None
        return self.calibration.T_world_patient @ self.last_pose.pose

    def tick(self, t: float) -> None:
        virtual = self.virtual_world()
        if self.script is not None and self.calibrator.step is not None:
            # The scripted technician presses the landmark asked for (again if refused).
            target = self.script.target(self.calibrator.step, t - self.script_t0)
            if target is None:
                self.script_t0 = t
                target = self.script.target(self.calibrator.step, 0.0)
        else:
            fresh = virtual is not None and not self.virtual_stale(t)
            target = virtual if fresh else None
            if target is not None and self.last_pose.clutch:
                target = None  # the expert is re-indexing: hold still
        self.world.step(t, target)
        if self.calibrating or target is None:
            self.following_since = None
        elif self.following_since is None:
            self.following_since = t
        frame_period = 1.0 / self.config.sensing_rate_hz
        if t - self.last_measure_t >= frame_period:  # a tracker frame and a force reading
            # On the frame clock, so the rate is sensing_rate_hz even when it is not a whole
            # fraction of the tick rate (45 Hz from 100 Hz ticks, not 33); no catching up.
            late = t - self.last_measure_t >= 2.0 * frame_period
            self.last_measure_t = t if late else self.last_measure_t + frame_period
            self.start_measurement(TrackerImage(self.world.truth(t), virtual, target))
        # Video frame timestamps (/follower/video_frame: stream 'pov' or 'us', seq, event) are
        # recorded here once the follower has its POV and ultrasound tracks; there is no video
        # yet, so nothing is recorded for it.
        self.publish_feed(t, virtual, self.measurement)

    # --- measurements (sensing worker thread -> loop) -------------------------------------

    def start_measurement(self, frame: TrackerImage) -> None:
        """Measure one tracker image: on the sensing worker when the daemon runs (the result
        is taken on the loop), else in line. Never two at once: an image due while the
        previous one is measured is skipped and counted."""
        if self.executor is None:
            self.take_measurement(frame, self.sensing.measure(frame.truth))
            return
        if self._sensing is not None:
            self.sensing_skipped += 1
            return
        fut = asyncio.get_running_loop().run_in_executor(self.executor, self._measure, frame)
        self._sensing = fut
        fut.add_done_callback(lambda f: self._measured(frame, f))

    def _measure(self, frame: TrackerImage) -> Measurement:
        """On the sensing worker: measure, and time it."""
        t0 = time.perf_counter()
        m = self.sensing.measure(frame.truth)
        self.sensing_times.append(time.perf_counter() - t0)
        return m

    def _measured(self, frame: TrackerImage, fut: Future) -> None:
        self._sensing = None
        if fut.cancelled():
            return
        try:
            exc = fut.exception()
            if exc is not None:  # Sensing.measure catches the pipeline's; this is the worker's
                raise exc
            self.take_measurement(frame, fut.result())
        except Exception:
            self.tick_errors += 1
            if self.tick_errors in (1, 10, 100, 1000):
                log.exception("follower: measurement failed (%d so far)", self.tick_errors)

    def take_measurement(self, frame: TrackerImage, m: Measurement) -> None:
        """One tracker frame measured: calibration, alignment, the state stream, recording."""
        self.measurement = m
        self.measurements += 1
        self.tracking_lost += m.T_world_tip is None
        self.last_force_n = float(np.linalg.norm(m.force_world))
        if self.calibrating:  # an untracked press still counts for the hysteresis
            tip = None if m.T_world_tip is None else m.T_world_tip.position
            ev = self.calibrator.update(tip, self.last_force_n)
            if ev is not None:
                self.on_calibration_event(ev, frame.t)
        elif frame.target is not None and self.following_since is not None:
            settled = frame.t - self.following_since >= self.config.alignment_settle_s
            if settled and m.T_world_tip is not None:
                dp, da = m.T_world_tip.distance_to(frame.virtual)
                self.align_pos.append(dp)
                self.align_ang.append(da)
        self.send_state(frame.t, m)
        self.record_measurement(frame.t, m)

    # --- recording ------------------------------------------------------------------------

    def record(self, topic: str, t: float | None, payload: dict) -> None:
        """One sample (``t``: this daemon's monotonic clock, s; None: now), if recording."""
        if self.rec is not None:
            self.rec.write(topic, time.monotonic() if t is None else t, payload)

    def record_measurement(self, t: float, m: Measurement) -> None:
        """The force (tip frame) and, once calibrated, the probe pose (patient frame)."""
        if self.rec is None:
            return
        if m.force_tip is not None:
            self.rec.write("/follower/force", t, {"force": m.force_tip})
        if self.calibration is None:
            return
        if m.status == TrackingStatus.TRACKED and m.T_world_tip is not None:
            T = self.calibration.T_world_patient.inverse() @ m.T_world_tip
            pose = {"position": T.position, "quaternion": T.quaternion, "tracked": True}
        else:
            pose = {"position": ZERO_POSE[0], "quaternion": ZERO_POSE[1], "tracked": False}
        self.rec.write("/follower/probe_pose", t, pose)

    def record_calibration_event(self, t: float | None, ev: CalibrationEvent) -> None:
        point = {"landmark": ev.landmark, "position": [float(v) for v in ev.point]}
        if ev.kind == "refused":
            self.record("/follower/calibration", t, {"event": "error", **point,
                                                      "message": ev.message[:200]})  # fmt: skip
            return
        self.record("/follower/calibration", t, {"event": "point", **point})
        if ev.kind == "done":
            self.record("/follower/calibration", t, {"event": "fit"})

    def record_model(self, t: float | None = None) -> None:
        """The fitted model (world frame, as ``Ellipsoid.to_dict``), once per calibration."""
        if self.calibration is None or self._model_recorded is self.calibration:
            return
        self._model_recorded = self.calibration
        self.record("/follower/ellipsoid", t, self.calibration.ellipsoid.to_dict())

    def record_reports(self, t: float) -> None:
        """The clock-sync estimate when it changes; the pose stream's one-way latency (median
        since the last report) about once a second."""
        if self.rec is None:
            return
        self.clock_log.update(self.rec, self.link.clock)
        if t - self._last_report < REPORT_PERIOD_S:
            return
        self._last_report = t
        new = min(len(self.pose_ages), self.poses_received - self._poses_reported)
        self._poses_reported = self.poses_received
        if new > 0:
            value = float(np.median(list(self.pose_ages)[-new:]))
            self.rec.write("/follower/latency", t, {"name": "pose_one_way", "value_s": value})

    def pose_rate_hz(self, window_s: float = 1.0) -> float:
        """Poses received per second over the last ``window_s``."""
        now = time.monotonic()
        return round(sum(1 for t in self.pose_times if now - t <= window_s) / window_s, 1)

    def stats(self) -> dict:
        ap, aa = list(self.align_pos)[-3000:], list(self.align_ang)[-3000:]
        wall = time.monotonic() - self.t_start
        return {
            "role": "follower",
            "pid": os.getpid(),
            "uptime_s": round(wall, 3),
            "link_state": self.link.state,
            "connections": self.link.counters.connections,
            "poses_received": self.poses_received,
            "pose_rate_hz": self.pose_rate_hz(),
            "pose_age_p50_ms": percentile_ms(self.pose_ages, 50),
            "pose_age_p99_ms": percentile_ms(self.pose_ages, 99),
            "pose_age_last_ms": percentile_ms(list(self.pose_ages)[-1:], 50),
            "states_sent": self.link.counters.sent.get("state", 0),
            "calibrated": self.calibration is not None,
            "calibration_reused": self.loaded_calibration,
            "calibration_refusals": self.calibrator.refusals,
            "calibration_step": self.calibrator.step if self.calibrating else None,
            "force_n": round(self.last_force_n, 3),
            "alignment_mm_rms": _rms_scaled(ap, 1000.0),
            "alignment_deg_rms": _rms_scaled(aa, 180.0 / math.pi),
            "dropped": dict(self.link.counters.dropped),
            "dropped_total": sum(self.link.counters.dropped.values()),
            "feed_clients": len(self.feed.clients),
            "feed_url": self.feed.url if self.feed.port else None,
            "feed": self.feed.stats(),
            "ticks": self.ticks,
            "measurements": self.measurements,
            "tracking_lost": self.tracking_lost,
            "sensing_errors": self.sensing.errors,
            "sensing_skipped": self.sensing_skipped,
            "sensing_p50_ms": percentile_ms(self.sensing_times, 50),
            "sensing_p99_ms": percentile_ms(self.sensing_times, 99),
            "scan": self.scan,
            "scans_seen": self.scans_seen,
            "recording": recorder_stats(self.rec),
            "tick_errors": self.tick_errors,
            "late_ticks": self.late_ticks,
            "cpu_percent": self.cpu.overall(),
        }

    def _count_late_tick(self) -> None:
        self.late_ticks += 1

    async def run(self, duration_s: float | None = None) -> int:
        if not self.start_run():
            return 2
        self.record_model()  # a saved calibration's model
        self.executor = ThreadPoolExecutor(1, thread_name_prefix="humantele-sensing")
        if self.config.feed.enabled:
            try:
                await self.feed.start()
            except BaseException:  # e.g. the port is taken: the recording is still closed
                self.close_recording()
                raise
            print(f"humantele follower: {self.feed.banner()}", flush=True)
        link_task = asyncio.create_task(self.link.run())
        if self.calibration is None:
            self.start_calibration()
        else:
            log.info("follower: reusing the saved calibration %s", self.calibration_path)
        self.publish_calibration()
        self.publish_model()
        try:
            async for t in self.loop_ticks(
                self.config.rate_hz, duration_s, link_task, on_late=self._count_late_tick
            ):
                self.ticks += 1
                try:
                    self.tick(t)
                    self.record_reports(t)
                except Exception:  # never let one bad tick end the daemon
                    self.tick_errors += 1
                    if self.tick_errors in (1, 10, 100, 1000):
                        log.exception("follower: tick failed (%d so far)", self.tick_errors)
        finally:
            await self.close_link(self.link, link_task)
            await self.feed.stop()
            self.executor.shutdown(wait=True)  # the frame being measured ends first
            self.executor = None
            self.sensing.close()
            self.finish_run()
        return 0


def _rms_scaled(values: list[float], scale: float) -> float | None:
    if not values:
        return None
    return round(math.sqrt(sum(v * v for v in values) / len(values)) * scale, 3)


# --- command line ---------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_daemon_arguments(parser, "TOML file; the [follower] section is used")
    parser.add_argument("--state-dir", help="where the calibration is saved")
    parser.add_argument("--feed-port", type=int, help="renderer feed port (0 picks one)")
    parser.add_argument("--recalibrate", action="store_true", help="ignore a saved calibration")


def config_from_args(args: argparse.Namespace) -> FollowerConfig:
    config = load_config(FollowerConfig, args.config, "follower" if args.config else None)
    data = config.model_dump()
    daemon_overrides(args, data)
    if args.state_dir:
        data["state_dir"] = args.state_dir
    if args.feed_port is not None:
        data["feed"]["port"] = args.feed_port
    return validate_config(FollowerConfig, data, "command line")


def sensing_config_from_args(args: argparse.Namespace) -> object | None:
    """The ``[sensing]`` section of the follower's file (the sensing pipeline's own)."""
    try:
        from humantele.follower.sensing import SensingConfig
    except ImportError:
        return None
    return load_config(SensingConfig, args.config, "sensing" if args.config else None)


def run(args: argparse.Namespace) -> int:
    setup_logging("follower", args.log_level)
    config = config_from_args(args)
    daemon = FollowerDaemon(config, args.stats_file, sensing_config_from_args(args))
    if args.recalibrate:
        daemon.calibration = None
        daemon.loaded_calibration = False
    return asyncio.run(daemon.run(args.duration))

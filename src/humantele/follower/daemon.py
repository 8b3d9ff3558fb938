"""``humantele follower``: the follower daemon (the clinic side).

Every tick (``rate_hz``, asyncio) it:

1. moves the probe: the simulated world (:mod:`humantele.follower.sim_world`: patient,
   person, head) advances; its person follows the virtual probe, or performs the calibration
   presses when calibrating;
2. at the tracker's rate (``sensing_rate_hz``) measures it through the sensing pipeline
   (:mod:`humantele.follower.sensing`; ``probe_source = "truth"``: the simulated truth behind
   the same small interface), so what it streams is what a real tracker and force sensor
   would give. The pipeline (~5-7 ms a frame) runs in a child process
   (``sensing_worker = "process"``, :mod:`humantele.follower.sensing_process`; ``"thread"``:
   a worker thread), off the asyncio loop and off its GIL, so the pose path is never held
   up; frames are measured in order and never overlap: a frame due while the previous one is
   still measured is skipped (counted in ``sensing_skipped``; those due while the child
   starts, in ``sensing_starting``);
3. with each measurement: feeds the calibration (:mod:`humantele.follower.calibration`) while
   calibrating, streams the probe pose and force to the expert (``state``, patient frame) and
   records them;
4. publishes the measured probe to renderers (:mod:`humantele.follower.feed`, world frame),
   and the virtual probe while it is ``stale`` (no fresh pose came or the link is down); a
   fresh virtual probe is published as its pose arrives, not at the next tick.
5. publishes the sim world's snapshot to the video sources, which render and send the ``us``
   and ``pov`` tracks from their own process (:mod:`humantele.media.sender`, docs/video.md);
   once a second the degradation policy may lower the POV (never the US).

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
import bisect
import contextlib
import logging
import math
import os
import sys
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from humantele.cliargs import EXIT_FAILED, port, socket_error
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
from humantele.follower.sensing import ProbeSensing, SensingConfig
from humantele.follower.sensing_process import SensingProcess
from humantele.follower.sim_human import (
    CalibrationScript,
    SimHeadConfig,
    SimHumanConfig,
    SimPatientConfig,
)
from humantele.follower.sim_world import SimWorld, WorldTruth
from humantele.geometry import Pose, matrix_to_quat
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.interop.igtl import IgtlConfig
from humantele.interop.sessions import FollowerIgtl
from humantele.media.config import FollowerVideoConfig
from humantele.media.sender import VideoSender
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
from humantele.tracking.tool import load_tool
from humantele.transport import LinkConfig, PeerLink
from humantele.video.base import VideoSourceUnavailable
from humantele.video.scene import SceneSnapshot
from humantele.wire import (
    CalibrationProgress,
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
ALIGN_KEPT = 3000  # alignment errors the RMS is over (the last ~65 s of 45 Hz frames)
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
    sensing_worker: Literal["process", "thread"] = Field(
        "process",
        description="where frames are measured while the daemon runs: a child process (its "
        "GIL apart from the loop's) or a thread",
    )
    sensing_nice: int = Field(
        10, ge=0, le=19, description="the sensing process's nice: the daemon's loop wakes first"
    )
    tool: str = Field(
        "probe_default", description="the probe's tool definition: tracked, drawn, tip (one)"
    )
    link: LinkConfig = LinkConfig()
    feed: FeedConfig = FeedConfig()
    calibration: CalibrationConfig = CalibrationConfig()
    sim_patient: SimPatientConfig = SimPatientConfig()
    sim_human: SimHumanConfig = SimHumanConfig()
    sim_head: SimHeadConfig = SimHeadConfig()
    video: FollowerVideoConfig = FollowerVideoConfig()
    session: SessionConfig = SessionConfig()
    recording: RecorderConfig = RecorderConfig()
    igtl: IgtlConfig = IgtlConfig()


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
    tool = load_tool(tool_name)
    tip, z = np.asarray(tool.tip, dtype=float), np.asarray(tool.face_direction, dtype=float)
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

    def __init__(
        self,
        config: FollowerConfig,
        sensing_config: SensingConfig | None = None,
        build: bool = True,
    ) -> None:
        """``build=False``: build the pipeline at the first :meth:`measure` (the daemon's own
        copy when a :class:`~humantele.follower.sensing_process.SensingProcess` measures)."""
        self.T_probe_tip = _tip_transform(config.tool)
        self.T_tip_probe = self.T_probe_tip.inverse()
        self.pipeline = None
        self.errors = 0
        self.contact_n = config.calibration.force_off_n
        self.sensing_config = sensing_config
        self.tool = config.tool
        self.unbuilt = config.probe_source == "pipeline"  # the pipeline is still to be built
        if build:
            self.build()

    def build(self) -> None:
        """Build the sensing pipeline (once; nothing in ``truth`` mode)."""
        if not self.unbuilt:
            return
        self.unbuilt = False
        if self.pipeline is not None:  # given by the caller
            return
        self.pipeline = ProbeSensing(self.sensing_config, self.tool)

    def measure(self, truth: WorldTruth) -> Measurement:
        if self.unbuilt:
            self.build()
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
            status = TrackingStatus(m.status)
        except Exception:  # a sensing fault must not stop the daemon
            self.errors += 1
            if self.errors == 1:
                log.exception("follower: sensing failed (counted, reported as lost)")
            return lost
        force = np.asarray(m.force_world, dtype=float)
        force_tip = self.T_tip_probe.rotate(np.asarray(m.force_probe, dtype=float))
        if not (np.all(np.isfinite(force)) and np.all(np.isfinite(force_tip))):
            force, force_tip = np.zeros(3), None
        if not status.has_pose or m.T_world_probe is None:
            status = TrackingStatus.LOST if status.has_pose else status  # lost or ambiguous
            return Measurement(status, None, force, bool(m.contact), force_tip)
        tip = m.T_world_probe @ self.T_probe_tip
        return Measurement(status, tip, force, bool(m.contact), force_tip)

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
        sensing_config: SensingConfig | None = None,
    ) -> None:
        super().__init__(config, stats_file)
        self.state_dir = Path(config.state_dir).expanduser()
        self.calibration_path = self.state_dir / CALIBRATION_FILE
        self.calibration: Calibration | None = Calibration.load(self.calibration_path)
        self.calibrator = Calibrator(config.calibration)
        self.world = SimWorld(config.sim_patient, config.sim_human, config.sim_head)
        patient = self.world.patient
        self.patient_ellipsoid = Ellipsoid(
            tuple(patient.T_world_body.position),
            tuple(float(v) for v in patient.semi_axes),
            math.radians(config.sim_patient.yaw_deg),
        )
        # with a sensing process, the daemon's own pipeline is built only if ever used
        self.sensing = Sensing(config, sensing_config, build=config.sensing_worker == "thread")
        self.sensing_proc: SensingProcess | None = None  # run() starts it
        self._proc_frame: tuple[int, TrackerImage] | None = None  # (job, image) in flight
        self._jobs = 0
        self.sensing_failure: str | None = None
        self.sensing_starting = 0  # tracker images due before the sensing process was ready
        self.measurement = Measurement(TrackingStatus.LOST, None, np.zeros(3), False)
        self.last_measure_t = -math.inf
        self.measurements = 0
        self.feed = RendererFeed(config.feed, self.state_dir)
        # Video: the us and pov tracks (humantele.media.sender), fed by the sim world's latest
        # snapshot (self.scene_snapshot, updated each tick) for the sim sources.
        self._scene: SceneSnapshot | None = None
        self._head: Pose | None = None
        self.video = (
            VideoSender(config.video, self.scene_snapshot, self.record_any, self.patient_ellipsoid)
            if config.video.enabled
            else None
        )
        self._video_check_t = -math.inf
        self.video_error = ""
        self._video_late_ticks = 0
        us = (self.video.captures["us"].slot, config.video.us) if self.video else None
        self.igtl = FollowerIgtl(config.igtl, self.world.patient.ellipsoid(), us)
        self.link = PeerLink(
            "follower",
            config.link,
            on_pose=self.on_pose,
            on_control=self.on_control,
            on_link_state=self.on_link_state,
            media=None if self.video is None else (lambda pc, role: self.video.attach(pc)),
        )
        self.calibrating = False
        self.following_since: float | None = None
        self.last_force_n = 0.0
        self.script: CalibrationScript | None = None
        self.script_t0 = 0.0
        self.last_pose: PoseMessage | None = None
        self.last_pose_rx = -math.inf
        self.pose_ages = SortedWindow(20000)  # s; percentiles without sorting on the loop
        self.align_pos: deque[float] = deque(maxlen=ALIGN_KEPT)
        self.align_ang: deque[float] = deque(maxlen=ALIGN_KEPT)
        self.poses_received = 0
        self.pose_times: deque[float] = deque(maxlen=2000)
        self.state_seq = 0
        self.ticks = 0
        self.tick_errors = 0
        self.tracking_lost = 0
        self.late_ticks = 0
        self.last_event: CalibrationEvent | None = None
        self.loaded_calibration = self.calibration is not None
        self.calibration_save_error = ""  # why the last calibration could not be saved
        # The sensing worker (run() starts it; without it, tick() measures in line).
        self.executor: ThreadPoolExecutor | None = None
        self._sensing: Future | None = None
        self.sensing_skipped = 0
        self.sensing_times = SortedWindow(2000)  # s per measurement (worker or child)
        self.tick_late = SortedWindow(20000)  # s each tick came after its period
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
        self.publish_virtual(self.last_pose_rx)

    def on_control(self, msg: ControlMessage) -> None:
        if isinstance(msg, Hello):
            self.send_model()  # the expert (re)joined: give it the model we have
        elif isinstance(msg, CalibrationProgress) and msg.event == "start":
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

    def publish_virtual(self, t: float) -> None:
        """The virtual probe (world frame) to renderers, once calibrated: as each pose arrives
        (from :meth:`on_pose`, so the page sees it at once), and at each tick while it is
        stale (``t``: the time it is judged at, s)."""
        virtual = self.virtual_world()
        if virtual is None or self.last_pose is None:
            return
        age = self.link.age_of(self.last_pose.t_sent)
        self.feed.publish(
            "virtual_probe",
            {
                "position": virtual.position,
                "quaternion": virtual.quaternion,
                "age_ms": None if age is None else age * 1000.0,
                "stale": self.virtual_stale(t),
                "clutch": bool(self.last_pose.clutch),
            },
            t_origin=self.last_pose_rx,
        )

    def publish_feed(self, t: float, m: Measurement) -> None:
        """At each tick: the virtual probe if it went stale, and the measured probe."""
        if self.virtual_stale(t):
            self.publish_virtual(t)
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
        self.send_control(CalibrationProgress(event="start"))
        self.publish_calibration()

    def save_calibration(self) -> bool:
        """Save the calibration for the next start; a failure (read-only or full state dir) is
        reported (log, stats ``calibration_save_error``) and the session goes on without it."""
        try:
            self.calibration.save(self.calibration_path)
        except OSError as exc:
            self.calibration_save_error = f"{exc.strerror or exc}: {exc.filename or ''}".strip()
            log.error(
                "follower: calibration not saved (%s); it is used now but will be asked for "
                "again at the next start", self.calibration_save_error,
            )  # fmt: skip
            return False
        self.calibration_save_error = ""
        return True

    def on_calibration_event(self, ev: CalibrationEvent, t: float | None = None) -> None:
        self.last_event = ev
        log.info("calibration: %s", ev.message)
        index = LANDMARKS.index(ev.landmark)
        point = tuple(float(v) for v in ev.point)
        self.record_calibration_event(t, ev)
        if ev.kind == "refused":
            self.send_control(
                CalibrationProgress(
                    event="error", index=index, point=point, detail=ev.message[:200]
                )
            )
        else:
            self.send_control(CalibrationProgress(event="point", index=index, point=point))
        if ev.kind == "done" and self.calibrator.result is not None:
            self.calibration = self.calibrator.result
            self.save_calibration()  # best-effort: the model goes to the expert regardless
            self.calibrating = False
            self.script = None
            self.send_control(CalibrationProgress(event="done"))
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
            # The scripted technician presses the landmark asked for (again if refused), once
            # the follower measures: a press while the sensing process starts is not seen.
            if not self.measuring():
                self.script_t0 = t
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
            truth = self.world.truth(t)
            self._head = truth.T_world_camera
            self.start_measurement(TrackerImage(truth, virtual, target))
        # The sim video sources render this snapshot (in the video process); video frame
        # timestamps (/follower/video_frame) are recorded as each frame is captured and sent.
        self.publish_scene(t, self.world.T_world_tip, self.world.force_world, virtual)
        self.publish_feed(t, self.measurement)
        v_patient = None if self.last_pose is None else self.last_pose.pose
        force_n = float(np.linalg.norm(self.world.force_world))
        self.igtl.tick(t, self.calibration, v_patient, self.world.T_world_tip, force_n)

    def publish_scene(
        self, t: float, true_tip: Pose | None, force: NDArray, virtual: Pose | None
    ) -> None:
        """The sim world now, for the sim video sources (an immutable snapshot)."""
        if self.video is None:
            return
        force_n = 0.0
        if true_tip is not None:
            beam = true_tip.rotate((0.0, 0.0, 1.0))
            force_n = max(0.0, -float(np.dot(force, beam)))
        self._scene = SceneSnapshot(t, self.patient_ellipsoid, true_tip, force_n, self._head,
                                    virtual)  # fmt: skip
        self.video.publish_scene(self._scene)

    def scene_snapshot(self) -> SceneSnapshot:
        """The latest snapshot (called from the video threads)."""
        s = self._scene
        return s if s is not None else SceneSnapshot(0.0, self.patient_ellipsoid, None, 0.0, None)

    def record_any(self, topic: str, t: float, payload: dict) -> None:
        """Record from any thread (the recorder only queues)."""
        rec = self.rec
        if rec is not None:
            rec.write(topic, t, payload)

    # --- measurements (sensing worker thread -> loop) -------------------------------------

    def measuring(self) -> bool:
        """False while the sensing process starts (its tracker images are skipped)."""
        proc = self.sensing_proc
        return proc is None or not proc.running or proc.ready

    def start_measurement(self, frame: TrackerImage) -> None:
        """Measure one tracker image: on the sensing worker when the daemon runs (the result
        is taken on the loop), else in line. Never two at once: an image due while the
        previous one is measured is skipped and counted."""
        proc = self.sensing_proc
        if proc is not None and proc.running:
            if not proc.ready:  # still starting (importing, calibrating the sim force sensor)
                self.sensing_starting += 1
                return
            if proc.busy:
                self.sensing_skipped += 1
                return
            self._jobs += 1
            if proc.submit(self._jobs, frame.truth):
                self._proc_frame = (self._jobs, frame)
            else:
                self.sensing_skipped += 1
            return
        if self.executor is None:
            self.take_measurement(frame, self.sensing.measure(frame.truth))
            return
        if self._sensing is not None:
            self.sensing_skipped += 1
            return
        fut = asyncio.get_running_loop().run_in_executor(self.executor, self._measure, frame)
        self._sensing = fut
        fut.add_done_callback(lambda f: self._measured(frame, f))

    def _measured_in_process(self, job: int, m: Measurement, seconds: float) -> None:
        """A measurement from the sensing process (on the loop)."""
        pending, self._proc_frame = self._proc_frame, None
        self.sensing_times.append(seconds)
        if pending is None or pending[0] != job:
            return  # a frame submitted to a child that has since been replaced
        try:
            self.take_measurement(pending[1], m)
        except Exception:
            self.tick_errors += 1
            if self.tick_errors in (1, 10, 100, 1000):
                log.exception("follower: measurement failed (%d so far)", self.tick_errors)

    def _sensing_cannot_start(self, reason: str) -> None:
        """The sensing process refused its config: the daemon stops (exit code 2)."""
        self.sensing_failure = reason
        self.stop()

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
        self.igtl.on_measurement(frame.t, self.calibration, m)

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
            value = float(np.median(self.pose_ages.last(new)))
            self.rec.write("/follower/latency", t, {"name": "pose_one_way", "value_s": value})

    def pose_rate_hz(self, window_s: float = 1.0) -> float:
        """Poses received per second over the last ``window_s``."""
        now = time.monotonic()
        recent = len(self.pose_times) - bisect.bisect_left(self.pose_times, now - window_s)
        return round(recent / window_s, 1)

    def stats(self) -> dict:
        ap, aa = self.align_pos, self.align_ang
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
            "pose_age_last_ms": percentile_ms(self.pose_ages.last(1), 50),
            "states_sent": self.link.counters.sent.get("state", 0),
            "calibrated": self.calibration is not None,
            "calibration_reused": self.loaded_calibration,
            "calibration_save_error": self.calibration_save_error,
            "calibration_refusals": self.calibrator.refusals,
            "calibration_step": self.calibrator.step if self.calibrating else None,
            "force_n": round(self.last_force_n, 3),
            "alignment_mm_rms": _rms_scaled(ap, 1000.0),
            "alignment_deg_rms": _rms_scaled(aa, 180.0 / math.pi),
            "dropped": dict(self.link.counters.dropped),
            "dropped_total": sum(self.link.counters.dropped.values()),
            "feed_clients": len(self.feed.clients),
            "feed_url": self.feed.address if self.feed.port else None,
            "feed": self.feed.stats(),
            "ticks": self.ticks,
            "measurements": self.measurements,
            "tracking_lost": self.tracking_lost,
            "sensing_errors": self.sensing.errors
            + (0 if self.sensing_proc is None else self.sensing_proc.child_errors),
            "sensing_skipped": self.sensing_skipped,
            "sensing_starting": self.sensing_starting,
            "sensing_worker": (
                "process"
                if self.sensing_proc is not None and self.sensing_proc.running
                else "thread"
            ),
            "sensing_restarts": 0 if self.sensing_proc is None else self.sensing_proc.restarts,
            "sensing_p50_ms": percentile_ms(self.sensing_times, 50),
            "sensing_p99_ms": percentile_ms(self.sensing_times, 99),
            "scan": self.scan,
            "scans_seen": self.scans_seen,
            "recording": recorder_stats(self.rec),
            "tick_errors": self.tick_errors,
            "late_ticks": self.late_ticks,
            "tick_late_p99_ms": percentile_ms(self.tick_late, 99),
            "tick_late_max_ms": percentile_ms(self.tick_late, 100),
            "cpu_percent_sensing": (
                None if self.sensing_proc is None else self.sensing_proc.cpu_percent()
            ),
            "cpu_percent": self.cpu.overall(),
            "loop_priority": self.loop_priority,
            "igtl": self.igtl.stats(),
            "video": None if self.video is None else self.video.stats(),
        }

    def feed_error(self, exc: OSError) -> str:
        """One line for a renderer feed that cannot start."""
        cfg = self.config.feed
        if exc.filename is not None:  # the TLS certificate in the state directory
            return (
                f"humantele follower: renderer feed: cannot write {exc.filename}: "
                f"{exc.strerror or exc} (check --state-dir {self.state_dir})"
            )
        return socket_error("humantele follower: renderer feed", cfg.host, cfg.port, exc)

    def check_video(self, t: float) -> None:
        """Once a second, the video's degradation policy (POV first), in a task."""
        if self.video is None or t - self._video_check_t < 1.0:
            return
        dt = 1.0 if self._video_check_t == -math.inf else t - self._video_check_t
        self._video_check_t = t
        late = (self.late_ticks - self._video_late_ticks) / dt
        self._video_late_ticks = self.late_ticks
        task = asyncio.ensure_future(self.video.check(t, late))
        task.add_done_callback(_log_task_error)

    def _count_late_tick(self) -> None:
        self.late_ticks += 1

    async def run(self, duration_s: float | None = None) -> int:
        if not self.start_run():
            return 2
        self.record_model()  # a saved calibration's model
        # The video sources open beside the session (the video process takes a few seconds
        # to start); one that cannot open stops the daemon with a clear message, exit code 2.
        video_task = None if self.video is None else asyncio.create_task(self.start_video())
        self.executor = ThreadPoolExecutor(1, thread_name_prefix="humantele-sensing")
        if self.config.sensing_worker == "process" and self.sensing.unbuilt:
            self.sensing_proc = SensingProcess(
                self.config,
                self.sensing.sensing_config,
                self._measured_in_process,
                self._sensing_cannot_start,
                nice=self.config.sensing_nice,
            )
            self.sensing_proc.start()  # it starts while the link connects
        if self.config.feed.enabled:
            try:
                await self.feed.start()
            except OSError as exc:  # port taken, unknown host, unwritable state dir
                self.close_recording()
                print(self.feed_error(exc), file=sys.stderr)
                return EXIT_FAILED
            except BaseException:  # the recording is still closed
                self.close_recording()
                raise
            print(f"humantele follower: {self.feed.banner()}", flush=True)
        await self.igtl.start()
        if self.igtl.banner():
            print(f"humantele follower: {self.igtl.banner()}", flush=True)
        link_task = asyncio.create_task(self.link.run())
        prev_t, period = None, 1.0 / self.config.rate_hz
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
                if prev_t is not None:  # how late this tick came after the previous one
                    self.tick_late.append(max(0.0, t - prev_t - period))
                prev_t = t
                try:
                    self.tick(t)
                    self.record_reports(t)
                    self.check_video(t)
                except Exception:  # never let one bad tick end the daemon
                    self.tick_errors += 1
                    if self.tick_errors in (1, 10, 100, 1000):
                        log.exception("follower: tick failed (%d so far)", self.tick_errors)
        finally:
            await self.close_link(self.link, link_task)
            await self.feed.stop()
            if video_task is not None:  # close first: an open still waiting then returns
                await asyncio.to_thread(self.video.close)
                with contextlib.suppress(BaseException):
                    await asyncio.wait_for(video_task, 5.0)
            await self.igtl.stop()
            self.executor.shutdown(wait=True)  # the frame being measured ends first
            self.executor = None
            if self.sensing_proc is not None:
                self.sensing_proc.close()
            self.sensing.close()
            self.finish_run()
        if self.sensing_failure is not None:
            print(f"humantele follower: sensing cannot start: {self.sensing_failure}", flush=True)
            return 2
        if self.video_error:
            return 2
        return self.run_result(link_task)

    async def start_video(self) -> None:
        """Open the video sources (in a thread: it blocks) and start them; a source that
        cannot open is reported on stderr and stops the daemon (exit code 2)."""
        assert self.video is not None
        try:
            await asyncio.to_thread(self.video.open)
        except VideoSourceUnavailable as exc:
            self.video_error = str(exc)
            print(f"humantele follower: {exc}", file=sys.stderr, flush=True)
            self._stop.set()
            return
        self.video.start(asyncio.get_running_loop())


def _log_task_error(task: asyncio.Future) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.error("follower: video check failed: %s", task.exception())


def _rms_scaled(values: deque[float], scale: float) -> float | None:
    if not values:
        return None
    a = np.fromiter(values, dtype=float, count=len(values))
    return round(float(np.sqrt(np.mean(a * a))) * scale, 3)


# --- command line ---------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_daemon_arguments(parser, "TOML file; the [follower] section is used")
    parser.add_argument("--state-dir", help="where the calibration is saved")
    parser.add_argument("--feed-port", type=port, help="renderer feed port (0 picks one)")
    parser.add_argument(
        "--igtl-port",
        type=port,
        help="serve OpenIGTLink on this port (0 picks one; 18944 Slicer's)",
    )
    parser.add_argument("--recalibrate", action="store_true", help="ignore a saved calibration")


def config_from_args(args: argparse.Namespace) -> FollowerConfig:
    config = load_config(FollowerConfig, args.config, "follower" if args.config else None)
    data = config.model_dump()
    daemon_overrides(args, data)
    if args.state_dir:
        data["state_dir"] = args.state_dir
    if args.feed_port is not None:
        data["feed"]["port"] = args.feed_port
    if getattr(args, "igtl_port", None) is not None:
        data["igtl"].update(enabled=True, port=args.igtl_port)
    return validate_config(FollowerConfig, data, "command line")


def sensing_config_from_args(args: argparse.Namespace) -> SensingConfig:
    """The ``[sensing]`` section of the follower's file (the sensing pipeline's own)."""
    return load_config(SensingConfig, args.config, "sensing" if args.config else None)


def run(args: argparse.Namespace) -> int:
    setup_logging("follower", args.log_level)
    config = config_from_args(args)
    daemon = FollowerDaemon(config, args.stats_file, sensing_config_from_args(args))
    if args.recalibrate:
        daemon.calibration = None
        daemon.loaded_calibration = False
    return run_daemon_process(daemon, args.duration)

"""What the follower calls to know where the real probe is and how hard it presses.

:class:`ProbeSensing` runs the pipeline on the clinic's devices: the IR/depth tracker on the
camera's frames, placed in the tracker's world by the camera pose each frame carries (hl2ss:
the headset's rig pose times the AHAT extrinsics; a fixed camera: its configured pose), and
the calibrated magnetic force sensor with its contact detector. The devices come from the
clinic (:func:`humantele.follower.clinics.make_sensing_devices`): real backends, or the sim
clinic's, which observe its simulated world; this module never looks behind them. Its
configuration, the devices and the pipeline's measurement are in
:mod:`humantele.follower.sensing_devices` (which the sim clinic imports without this module).

:class:`Sensing` is the follower's view of it (tip frame, :class:`Measurement`), run in the
sensing child (:mod:`humantele.follower.sensing_process`) or a thread.

Frames: world (the tracker's, y up), camera (OpenCV: x right, y down, z forward), probe
(see humantele/defaults/tools), tip (origin at the face centre, +z along the beam). Units: m,
N, s.

Cost per ``measure`` call with the sim devices, one core: about 2-5 ms (frame rendering about
half, the pipeline the rest; see ``humantele bench tracking``).
"""

from __future__ import annotations

import contextlib
import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from humantele.follower.clinic import ClinicConfig, DeviceClinicConfig, SimClinicConfig
from humantele.follower.clinics import make_sensing_devices
from humantele.follower.sensing_devices import (
    ProbeMeasurement,
    SensingConfig,
    SensingDevices,
    tip_transform,
)
from humantele.forcesense.reader import ForceReader
from humantele.geometry import Pose, matrix_to_quat
from humantele.tracking.pipeline import Tracker
from humantele.tracking.sim_config import SimFrameConfig
from humantele.tracking.status import TrackingStatus
from humantele.tracking.tool import DEFAULT_TOOL, ToolDefinition, load_tool

log = logging.getLogger(__name__)

# Camera looking straight down (world -y), image x along world x, image y along world z.
_R_WORLD_CAMERA_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]).T


class ProbeSensing:
    """Tracker + force sensor + contact detector, from one :class:`SensingConfig`, for the
    probe ``tool`` (a :class:`ToolDefinition`, or its name or path for :func:`load_tool`), on
    ``devices`` (default: the clinic's for this config: the sim clinic's when the camera is
    ``sim``, else the real backends)."""

    def __init__(
        self,
        config: SensingConfig | None = None,
        tool: ToolDefinition | str = DEFAULT_TOOL,
        devices: SensingDevices | None = None,
    ):
        self.config = c = config or SensingConfig()
        self.tool = tool if isinstance(tool, ToolDefinition) else load_tool(tool)
        if devices is None:
            sim = isinstance(c.camera, SimFrameConfig)
            clinic = SimClinicConfig() if sim else DeviceClinicConfig()
            devices = make_sensing_devices(clinic, c, self.tool)
        self.devices = devices
        self.source, self.sensor = devices.source, devices.sensor
        self.calibration = devices.calibration
        self.tracker = Tracker(self.tool, c.pipeline, c.filter)
        # A real board is read at its own rate (a thread, started at the first measure: after
        # the sensing process set its priority, which the thread inherits); the sim clinic's
        # board shows the force of each frame's simulated world: read once per frame.
        self.force = ForceReader(self.sensor, self.calibration, c.force.contact,
                                 c.force.read_rate_hz, c.force.stale_s)  # fmt: skip
        self.contact = self.force.contact
        self.force_threaded = devices.observe is None
        self.T_world_camera: Pose | None = None  # the last frame's camera
        self.fixed_camera: Pose | None = None
        if c.camera_anchor == "fixed":
            self.fixed_camera = Pose(c.camera_position_m, matrix_to_quat(_R_WORLD_CAMERA_DOWN))
        self._R_world_probe = np.eye(3)
        self.no_camera_pose = 0  # frames the device gave without the camera's pose
        self.no_frame = 0  # reads that gave no frame (counted by the source, by reason)
        self.frames_tracked = 0  # frames the tracker measured (with a camera pose)
        self.force_stale = 0  # measurements whose force was stale
        try:  # the devices last: a bad setting above fails before any hardware is touched
            self.source.open()
            self.sensor.open()
        except Exception:
            self.close()
            raise

    def measure(self, t: float, world: Any = None) -> ProbeMeasurement:
        """Measure the probe at time ``t`` (s). ``world``: what the sim clinic's devices
        observe at this frame (ignored by real devices)."""
        if world is not None and self.devices.observe is not None:
            self.devices.observe(world)
        if self.force_threaded and not self.force.running:
            self.force.poll()  # the first reading in line, then the board's own rate
            self.force.start()
        frame = self.source.read(t)
        if frame is None:
            self.no_frame += 1
        status = TrackingStatus.LOST
        pose_w = tip_w = rig = device_t = None
        residual = math.nan
        if frame is not None:
            rig, device_t = frame.T_world_rig, frame.device_time_s
            camera = self.fixed_camera or frame.T_world_camera
            if camera is None:
                self.no_camera_pose += 1
            else:
                self.T_world_camera = camera
                self.frames_tracked += 1
                res = self.tracker.process(frame)
                status, residual = res.status, res.residual_m
                if res.T_camera_probe is not None:
                    pose_w = camera @ res.T_camera_probe
                    tip_w = pose_w.apply(self.tool.tip)
                    self._R_world_probe = pose_w.rotation_matrix
        if not self.force_threaded:
            self.force.poll(t)
        force = self.force.sample()
        self.force_stale += force.stale
        force_world = self._R_world_probe @ force.force_probe
        return ProbeMeasurement(
            t=t,
            status=status,
            T_world_probe=pose_w,
            tip_world=tip_w,
            force_world=force_world,
            force_probe=force.force_probe,
            contact=force.contact,
            residual_m=residual,
            contact_event=force.event,
            T_world_rig=rig,
            device_time_s=device_t,
            force_stale=force.stale,
            camera_stalled=bool(getattr(self.source, "stalled", False)),
        )

    @property
    def bad_force(self) -> int:
        """Force readings the calibration made non-finite (dropped)."""
        return self.force.bad_force

    def device_stats(self) -> dict:
        """The devices' counters for the follower's stats (:func:`unmeasured` sums them)."""
        cam = getattr(self.source, "stats", None)
        camera = cam() if callable(cam) else {"dropped": dict(getattr(self.source, "dropped",
                                                                        {}))}  # fmt: skip
        camera["stalled"] = bool(getattr(self.source, "stalled", False))
        return {"camera": camera, "no_frame": self.no_frame, "frames": self.frames_tracked,
                "no_camera_pose": self.no_camera_pose, "force_stale": self.force_stale,
                "force": self.force.stats()}  # fmt: skip

    def close(self) -> None:
        self.force.stop()  # before the board is closed under it
        self.source.close()
        self.sensor.close()


# --- the follower's view: tip frame, one measurement per tracker frame -----------------------


@dataclass
class Measurement:
    """What the follower knows of its probe at one tracker frame (world frame, SI):
    ``force_tip`` is the force in the probe's tip frame (None when unknown); ``contact``
    comes from the force sensor; ``T_world_rig`` is the headset's pose, when the device
    gave one. ``force_stale``: the board gave no good reading for ``stale_s`` (unplugged):
    no force (zero, ``force_tip`` None) and no contact; ``camera_stalled``: the headset's
    stream is stalled (no frame for its ``stall_s``)."""

    status: TrackingStatus
    T_world_tip: Pose | None
    force_world: NDArray[np.float64]
    contact: bool
    force_tip: NDArray[np.float64] | None = None
    T_world_rig: Pose | None = None
    device_time_s: float | None = None  # the tracker frame's time on the device's clock
    force_stale: bool = False
    camera_stalled: bool = False


LOST = Measurement(TrackingStatus.LOST, None, np.zeros(3), False)


@dataclass
class TrackerImage:
    """One tracker frame to measure at ``t`` (s, the daemon's clock): ``world`` is what the
    sim clinic's devices observe then (None with real devices; the daemon never reads it),
    ``virtual`` and ``target`` the virtual probe and the live guide the tick had (world
    frame, for the alignment figure)."""

    t: float
    world: Any
    virtual: Pose | None
    target: Pose | None


@dataclass(frozen=True)
class SensingSetup:
    """What the sensing needs of the follower's config: the probe's ``tool``, the ``clinic``,
    the ``probe_source`` and the contact force that ends a press (N). The sensing child is
    sent this, not the whole config: unpickling the follower's config imports its pages, its
    WebRTC link and its video (0.75 CPU-s a start, more than the sensing's own imports)."""

    tool: str
    clinic: ClinicConfig
    probe_source: str
    force_off_n: float

    @classmethod
    def of(cls, config: Any) -> SensingSetup:
        """From the follower's config (a :class:`SensingSetup` stays as it is)."""
        if isinstance(config, SensingSetup):
            return config
        return cls(config.tool, config.clinic, config.probe_source,
                   config.calibration.force_off_n)  # fmt: skip


class Sensing:
    """The follower's probe sensing: ``measure(t, world)`` gives a :class:`Measurement`; a
    pipeline error gives a LOST measurement (counted), never a crash. ``config``: the
    follower's, or its :class:`SensingSetup`."""

    def __init__(
        self, config: Any, sensing_config: SensingConfig | None = None, build: bool = True
    ) -> None:
        """``build=False``: build the pipeline at the first :meth:`measure` (the daemon's own
        copy when a :class:`~humantele.follower.sensing_process.SensingProcess` measures)."""
        self.config = config = SensingSetup.of(config)
        self.T_probe_tip = tip_transform(config.tool)
        self.T_tip_probe = self.T_probe_tip.inverse()
        self.pipeline: Any = None
        self.errors = 0
        self.sensing_config = sensing_config or SensingConfig()
        self.unbuilt = True
        if build:
            self.build()

    def build(self) -> None:
        """Build the pipeline on the clinic's devices (once): the sensing pipeline, or with
        ``probe_source = "truth"`` the sim clinic's ideal sensor."""
        if not self.unbuilt:
            return
        self.unbuilt = False
        if self.pipeline is not None:  # given by the caller
            return
        c = self.config
        if c.probe_source == "truth":
            from humantele.follower.sim_clinic import IdealSensing

            self.pipeline = IdealSensing(self.T_probe_tip, c.force_off_n)
            return
        tool = load_tool(c.tool)
        devices = make_sensing_devices(c.clinic, self.sensing_config, tool)
        self.pipeline = ProbeSensing(self.sensing_config, tool, devices)

    def measure(self, t: float, world: Any = None) -> Measurement:
        if self.unbuilt:
            self.build()
        try:
            m = self.pipeline.measure(t, world)
            status = TrackingStatus(m.status)
        except Exception:  # a sensing fault must not stop the daemon
            self.errors += 1
            if self.errors == 1:
                log.exception("follower: sensing failed (counted, reported as lost)")
            return LOST
        force = np.asarray(m.force_world, dtype=float)
        force_tip = self.T_tip_probe.rotate(np.asarray(m.force_probe, dtype=float))
        stale = bool(getattr(m, "force_stale", False))
        contact = bool(m.contact) and not stale
        if stale or not (np.all(np.isfinite(force)) and np.all(np.isfinite(force_tip))):
            force, force_tip = np.zeros(3), None
        rig, device_t = getattr(m, "T_world_rig", None), getattr(m, "device_time_s", None)
        stalled = bool(getattr(m, "camera_stalled", False))
        tip = None
        if not status.has_pose or m.T_world_probe is None:
            status = TrackingStatus.LOST if status.has_pose else status  # lost or ambiguous
        else:
            tip = m.T_world_probe @ self.T_probe_tip
        return Measurement(status, tip, force, contact, force_tip, rig, device_t, stale, stalled)

    def device_stats(self) -> dict | None:
        """The devices' counters (:meth:`ProbeSensing.device_stats`; None: not built, or a
        pipeline without devices)."""
        get = getattr(self.pipeline, "device_stats", None)
        if not callable(get):
            return None
        try:
            return get()
        except Exception:  # noqa: BLE001 - stats must never stop the sensing
            return None

    def close(self) -> None:
        if self.pipeline is not None:
            with contextlib.suppress(Exception):
                self.pipeline.close()

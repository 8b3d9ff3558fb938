"""What the follower daemon calls to know where the real probe is and how hard it presses.

:class:`ProbeSensing` runs the real pipeline: the IR/depth tracker on camera frames and the
calibrated magnetic force sensor. With the default ``sim`` backends it renders frames and
readings of the simulated follower's probe from the true pose and force it is given, so what
it returns is measured (noise, occlusion, lost frames), not the truth.

Frames: world (the headset's, y up), camera (OpenCV: x right, y down, z forward), probe
(see humantele/defaults/tools). Units: m, N, s.

Cost per ``measure`` call with the sim backends, one core: about 2-5 ms (frame rendering about
half, the pipeline the rest; see ``humantele bench tracking``), so 45 Hz takes < 25 % of a
core. Run it in a thread executor if the loop must stay below a millisecond per step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from humantele.config import ConfigModel
from humantele.forcesense.calibration import ForceCalibration, calibrate_sim
from humantele.forcesense.contact import ContactDetector, ContactEvent
from humantele.forcesense.sensors import ForceSensorConfig, calibration_path, make_force_sensor
from humantele.forcesense.sim import SimForceConfig, SimForceSensor
from humantele.geometry import Pose, matrix_to_quat
from humantele.tracking.filter import FilterConfig
from humantele.tracking.pipeline import PipelineConfig, Tracker
from humantele.tracking.sim import SimFrameConfig, SimFrameSource
from humantele.tracking.sources import FrameSourceConfig, make_frame_source
from humantele.tracking.status import TrackingStatus
from humantele.tracking.tool import DEFAULT_TOOL, ToolDefinition, load_tool

# Camera looking straight down (world -y), image x along world x, image y along world z.
_R_WORLD_CAMERA_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]).T


class SensingConfig(ConfigModel):
    """Tracker (camera backend, pipeline, filter), force sensor, and where the camera is. The
    tool (the probe's marker tree) is not here: it is the follower's one ``tool`` setting,
    given to :class:`ProbeSensing`.

    ``camera_anchor = "above_probe"``: the headset camera is placed ``camera_height_m`` above
    the probe's first true position, looking down (the follower's head, held steady).
    ``"fixed"``: at ``camera_position_m`` looking down. A ``T_world_camera`` passed to
    :meth:`ProbeSensing.measure` (the headset's own pose) overrides both.
    """

    moved_fields = {"tool": "the probe's tool is set once, in [follower] tool"}

    camera: FrameSourceConfig = Field(default_factory=SimFrameConfig)
    pipeline: PipelineConfig = Field(default_factory=PipelineConfig)
    filter: FilterConfig = Field(default_factory=FilterConfig)
    force: ForceSensorConfig = Field(default_factory=ForceSensorConfig)
    camera_anchor: Literal["above_probe", "fixed"] = "above_probe"
    camera_height_m: float = Field(0.42, gt=0.1, le=1.0)
    camera_position_m: list[float] = Field(default_factory=lambda: [0.0, 0.55, 0.0])


@dataclass(frozen=True)
class ProbeMeasurement:
    """One measurement. ``T_world_probe``/``tip_world`` only when tracked; ``force_world``
    (3,) N is the calibrated sensor force turned into the world frame with the last tracked
    orientation (identity before the first); ``force_probe`` the same in the probe frame;
    ``contact`` the detector state and ``contact_event`` "press"/"release" on this call."""

    t: float
    status: TrackingStatus
    T_world_probe: Pose | None
    tip_world: NDArray[np.float64] | None
    force_world: NDArray[np.float64]
    force_probe: NDArray[np.float64]
    contact: bool
    residual_m: float
    contact_event: ContactEvent | None = None


class ProbeSensing:
    """Tracker + force sensor + contact detector, from one :class:`SensingConfig`, for the
    probe ``tool`` (a :class:`ToolDefinition`, or its name or path for :func:`load_tool`)."""

    def __init__(
        self, config: SensingConfig | None = None, tool: ToolDefinition | str = DEFAULT_TOOL
    ):
        self.config = c = config or SensingConfig()
        self.tool = tool if isinstance(tool, ToolDefinition) else load_tool(tool)
        self.source = make_frame_source(c.camera, self.tool)
        self.tracker = Tracker(self.tool, c.pipeline, c.filter)
        self.sensor = make_force_sensor(c.force.sensor)
        path = calibration_path(c.force)
        if path is not None:
            self.calibration = ForceCalibration.load(path)
        elif isinstance(self.sensor, SimForceSensor):
            # calibrate a twin of the sim board (same seed: the same physical board)
            twin = SimForceSensor(
                c.force.sensor if isinstance(c.force.sensor, SimForceConfig) else None
            )
            self.calibration = calibrate_sim(twin)
        else:
            raise ValueError("the hid force sensor needs force.calibration_file")
        self.contact = ContactDetector(c.force.contact)
        self.T_world_camera: Pose | None = None
        if c.camera_anchor == "fixed":
            self.T_world_camera = Pose(c.camera_position_m, matrix_to_quat(_R_WORLD_CAMERA_DOWN))
        self._R_world_probe = np.eye(3)
        self._force_probe = np.zeros(3)
        self.bad_force = 0
        try:  # the devices last: a bad setting above fails before any hardware is touched
            self.source.open()
            self.sensor.open()
        except Exception:
            self.close()
            raise

    def measure(
        self,
        t: float,
        T_world_probe_true: Pose | None = None,
        force_true_world: ArrayLike | None = None,
        T_world_camera: Pose | None = None,
    ) -> ProbeMeasurement:
        """Measure the probe at time ``t`` (s). The truths drive the sim backends only."""
        if T_world_camera is not None:
            self.T_world_camera = T_world_camera
        if self.T_world_camera is None:
            p = np.zeros(3) if T_world_probe_true is None else T_world_probe_true.position
            self.T_world_camera = Pose(
                p + [0.0, self.config.camera_height_m, 0.0],
                matrix_to_quat(_R_WORLD_CAMERA_DOWN),
            )
        T_world_camera = self.T_world_camera
        # --- pose ---
        if isinstance(self.source, SimFrameSource):
            if T_world_probe_true is None:
                raise ValueError("the sim tracker needs T_world_probe_true")
            frame = self.source.render(T_world_camera.inverse() @ T_world_probe_true, t)
        else:
            frame = self.source.read(t)
        status = TrackingStatus.LOST
        pose_w = tip_w = None
        residual = math.nan
        if frame is not None:
            res = self.tracker.process(frame)
            status, residual = res.status, res.residual_m
            if res.T_camera_probe is not None:
                pose_w = T_world_camera @ res.T_camera_probe
                tip_w = pose_w.apply(self.tool.tip)
                self._R_world_probe = pose_w.rotation_matrix
        # --- force ---
        if isinstance(self.sensor, SimForceSensor):
            f_true = np.zeros(3) if force_true_world is None else np.asarray(force_true_world)
            R_true = np.eye(3) if T_world_probe_true is None else T_world_probe_true.rotation_matrix
            self.sensor.set_force(R_true.T @ f_true)
        reading = self.sensor.read(t)
        if reading is not None:
            f = self.calibration.force(reading)
            if np.all(np.isfinite(f)):
                self._force_probe = f
            else:
                self.bad_force += 1
        force_world = self._R_world_probe @ self._force_probe
        event = self.contact.update(t, self._force_probe)
        return ProbeMeasurement(
            t=t,
            status=status,
            T_world_probe=pose_w,
            tip_world=tip_w,
            force_world=force_world,
            force_probe=self._force_probe.copy(),
            contact=self.contact.in_contact,
            residual_m=residual,
            contact_event=event,
        )

    def close(self) -> None:
        self.source.close()
        self.sensor.close()

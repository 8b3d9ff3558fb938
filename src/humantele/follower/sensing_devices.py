"""The follower's sensing devices and what its pipeline measures, apart from the pipeline
(:mod:`humantele.follower.sensing`) so that the clinics that provide the devices
(:mod:`humantele.follower.clinics`, :mod:`humantele.follower.sim_clinic`) need not import it:
:class:`SensingConfig` (``[sensing]``), :class:`SensingDevices`, the configured real backends
(:func:`real_sensing_devices`), one :class:`ProbeMeasurement`, and the tip frame on the tracked
probe (:func:`tip_transform`). Frames and units as in :mod:`humantele.follower.sensing`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from humantele.config import ConfigModel
from humantele.forcesense.base import ForceSensor
from humantele.forcesense.calibration import ForceCalibration
from humantele.forcesense.contact import ContactEvent
from humantele.forcesense.sensors import ForceSensorConfig, calibration_path, make_force_sensor
from humantele.forcesense.sim_config import SimForceConfig
from humantele.geometry import Pose, matrix_to_quat
from humantele.tracking.filter import FilterConfig
from humantele.tracking.frames import FrameSource
from humantele.tracking.pipeline import PipelineConfig
from humantele.tracking.sim_config import SimFrameConfig
from humantele.tracking.sources import FrameSourceConfig, make_frame_source
from humantele.tracking.status import TrackingStatus
from humantele.tracking.tool import ToolDefinition, load_tool


class SensingConfig(ConfigModel):
    """Tracker (camera backend, pipeline, filter), force sensor, and where the camera is. The
    tool (the probe's marker tree) is not here: it is the follower's one ``tool`` setting.

    ``camera_anchor = "device"``: each frame carries the camera's pose in the tracker's world
    from the device (the headset's rig pose with hl2ss; the simulated head in the sim
    clinic); a frame without one cannot place the probe and is counted. ``"fixed"``: a
    camera that does not move, at ``camera_position_m`` looking down (an OpenCV camera on a
    stand); its frames' own pose, if any, is ignored.
    """

    moved_fields = {
        "tool": "the probe's tool is set once, in [follower] tool",
        "camera_height_m": "the simulated headset is [follower.clinic.head] height_m",
    }

    camera: FrameSourceConfig = Field(default_factory=SimFrameConfig)
    pipeline: PipelineConfig = Field(default_factory=PipelineConfig)
    filter: FilterConfig = Field(default_factory=FilterConfig)
    force: ForceSensorConfig = Field(default_factory=ForceSensorConfig)
    camera_anchor: Literal["device", "fixed"] = "device"
    camera_position_m: list[float] = Field(default_factory=lambda: [0.0, 0.55, 0.0])


@dataclass
class SensingDevices:
    """The tracker camera and the force sensor (not yet opened), the sensor's calibration,
    and ``observe(world)``: how the sim clinic's devices are shown its world at a frame
    (None for real devices, which observe the room)."""

    source: FrameSource
    sensor: ForceSensor
    calibration: ForceCalibration
    observe: Callable[[Any], None] | None = None


def real_sensing_devices(config: SensingConfig, tool: ToolDefinition) -> SensingDevices:
    """The configured real backends; a ``sim`` backend here is refused (in a real clinic
    nothing would move it), and so is a force sensor without its calibration file."""
    if isinstance(config.camera, SimFrameConfig) or isinstance(config.force.sensor, SimForceConfig):
        raise ValueError(
            "a sim tracker camera or force sensor needs the simulated clinic "
            '([follower.clinic] backend = "sim"); set [sensing.camera] and '
            "[sensing.force.sensor] to real backends"
        )
    path = calibration_path(config.force)
    if path is not None:
        calibration = ForceCalibration.load(path)
    elif config.force.sensor.backend == "replay":  # the one the recording kept
        calibration = _recorded_force_calibration(config.force.sensor.file)
    else:
        raise ValueError("the force sensor needs [sensing.force] calibration_file")
    return SensingDevices(make_frame_source(config.camera, tool),
                          make_force_sensor(config.force.sensor), calibration)  # fmt: skip


def _recorded_force_calibration(recording: str) -> ForceCalibration:
    """The board's calibration a device recording kept (``humantele devices record``)."""
    from humantele.recording.device_file import open_recording

    text = open_recording(recording).info.get("force_calibration")
    if not text:
        raise ValueError(
            f"{recording} keeps no force calibration (recorded without [sensing.force] "
            "calibration_file): set [sensing.force] calibration_file"
        )
    return ForceCalibration.loads(text)


@dataclass(frozen=True)
class ProbeMeasurement:
    """One measurement. ``T_world_probe``/``tip_world`` only when tracked; ``force_world``
    (3,) N is the calibrated sensor force turned into the world frame with the last tracked
    orientation (identity before the first); ``force_probe`` the same in the probe frame;
    ``contact`` the detector state and ``contact_event`` "press"/"release" on this call;
    ``T_world_rig``: the headset's pose the frame came with (None: none); ``force_stale``:
    no good force reading for ``[sensing.force] stale_s`` (the forces are the last known;
    no contact); ``camera_stalled``: the tracker camera's stream is stalled (hl2ss)."""

    t: float
    status: TrackingStatus
    T_world_probe: Pose | None
    tip_world: NDArray[np.float64] | None
    force_world: NDArray[np.float64]
    force_probe: NDArray[np.float64]
    contact: bool
    residual_m: float
    contact_event: ContactEvent | None = None
    T_world_rig: Pose | None = None
    device_time_s: float | None = None
    force_stale: bool = False
    camera_stalled: bool = False


def tip_transform(tool: ToolDefinition | str) -> Pose:
    """``T_probe_tip``: the tip frame on the tracked probe body (from the tool definition)."""
    tool = tool if isinstance(tool, ToolDefinition) else load_tool(tool)
    tip, z = np.asarray(tool.tip, dtype=float), np.asarray(tool.face_direction, dtype=float)
    z = z / np.linalg.norm(z)
    x = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = x - z * float(x @ z)
    x /= np.linalg.norm(x)
    return Pose(tip, matrix_to_quat(np.column_stack([x, np.cross(z, x), z])))

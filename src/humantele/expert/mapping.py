"""From the stylus to the virtual transducer: registration, motion scaling, clutch.

Frames (SI units):

- device: the haptic device's (Touch X convention: x to the user's right, y up, z toward the
  user, origin at the workspace centre);
- patient: the paper's, shared with the follower (x head to feet, y up, z from the patient's
  left to right, origin at the centre of the ellipsoid model);
- probe: the virtual transducer's tip frame (origin at the centre of the face, +z along the
  beam, into the patient). The stylus at rest (identity quaternion) holds the probe beam down
  (device -y); ``stylus_to_probe_deg`` says how the transducer sits on the stylus.

The map from device to patient positions is ``p_patient = R (scale * p_device) + t``
(:class:`Registration`): R turns the device's axes into the patient's (``device_yaw_deg`` about
y), ``scale`` is the motion scaling (1:1 by default), and ``t`` places the workspace over the
patient model: by default the device origin sits ``origin_above_model_m`` above the top of the
model, where the sim sonographer expects the surface. Orientations map 1:1 (rotated by R).

The clutch (a stylus button) re-indexes: while it is held, the virtual probe stays where it was
and the stylus moves freely; on release, ``t`` is shifted so the probe continues from there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from humantele.config import ConfigModel
from humantele.geometry import Pose, quat_from_axis_angle, quat_multiply, quat_normalize

UP = np.array([0.0, 1.0, 0.0])
Offset = Annotated[float, Field(ge=-2.0, le=2.0)]  # m
Angle = Annotated[float, Field(ge=-360.0, le=360.0)]  # deg


class MappingConfig(ConfigModel):
    """Registration, scaling and clutch of the expert's stylus (m, deg at this edge)."""

    scale: float = Field(1.0, gt=0.05, le=10.0, description="patient motion per device motion")
    device_yaw_deg: float = Field(
        0.0, ge=-180, le=180, description="device axes turned about y into the patient's"
    )
    origin_above_model_m: float = Field(
        0.03, ge=-0.2, le=0.5, description="device origin this far above the model's top"
    )
    origin_offset_m: tuple[Offset, Offset, Offset] = Field(
        (0.0, 0.0, 0.0), description="extra shift of the device origin, patient frame"
    )
    stylus_to_probe_deg: tuple[Angle, Angle, Angle] = Field(
        (90.0, 0.0, 0.0), description="rotation vector (deg) from stylus to probe tip frame"
    )
    clutch_button: int = Field(1, ge=0, le=7, description="stylus button bit for the clutch")


@dataclass(frozen=True)
class Registration:
    """``p_patient = R (scale * p_device) + t``; ``rotation`` is R as a quaternion."""

    rotation: NDArray[np.float64]
    translation: NDArray[np.float64]
    scale: float = 1.0

    @property
    def T_patient_device(self) -> Pose:  # noqa: N802 (frame names keep their case)
        """The rigid part (exact when ``scale`` is 1)."""
        return Pose(self.translation, self.rotation)

    def point_to_patient(self, p_device: ArrayLike) -> NDArray[np.float64]:
        return self.T_patient_device.rotate(self.scale * np.asarray(p_device, dtype=float)) + (
            self.translation
        )

    def point_to_device(self, p_patient: ArrayLike) -> NDArray[np.float64]:
        p = np.asarray(p_patient, dtype=float) - self.translation
        return self.T_patient_device.inverse().rotate(p) / self.scale

    def vector_to_device(self, v_patient: ArrayLike) -> NDArray[np.float64]:
        """A patient-frame direction or force in device axes (no scaling)."""
        return self.T_patient_device.inverse().rotate(v_patient)

    def with_translation(self, t: ArrayLike) -> Registration:
        return Registration(self.rotation, np.asarray(t, dtype=float).copy(), self.scale)


def default_registration(config: MappingConfig, model_top_patient: ArrayLike) -> Registration:
    """Device origin ``origin_above_model_m`` above the model's top point (patient frame)."""
    q = quat_from_axis_angle(UP, math.radians(config.device_yaw_deg))
    t = np.asarray(model_top_patient, dtype=float) + config.origin_above_model_m * UP
    t = t + np.asarray(config.origin_offset_m, dtype=float)
    return Registration(q, t, config.scale)


def _rotvec_quat(deg: tuple[float, float, float]) -> NDArray[np.float64]:
    rv = np.radians(np.asarray(deg, dtype=float))
    angle = float(np.linalg.norm(rv))
    return quat_from_axis_angle(rv, angle) if angle > 0 else np.array([0.0, 0.0, 0.0, 1.0])


class StylusMapping:
    """Stylus readings (device frame) to the virtual probe pose ``T_patient_probe``.

    ``update`` returns the pose to publish; ``registration`` is what the servo loop must use to
    render the model, and changes only when the clutch is released (``changed`` is then True
    once, so the daemon can pass it on).
    """

    def __init__(self, config: MappingConfig, registration: Registration) -> None:
        self.config = config
        self.registration = registration
        self._q_stylus_probe = _rotvec_quat(config.stylus_to_probe_deg)
        self.clutched = False
        self.changed = False
        self.last: Pose | None = None
        self.reindex_count = 0

    def set_registration(self, registration: Registration) -> None:
        self.registration = registration
        self.changed = True

    def probe_pose(self, p_device: ArrayLike, q_device: ArrayLike) -> Pose:
        """``T_patient_probe`` for a stylus at ``p_device`` (m) with orientation ``q_device``."""
        reg = self.registration
        q = quat_multiply(
            reg.rotation, quat_multiply(quat_normalize(q_device), self._q_stylus_probe)
        )
        return Pose(reg.point_to_patient(p_device), q)

    def update(self, p_device: ArrayLike, q_device: ArrayLike, buttons: int) -> Pose:
        """The virtual probe pose for one stylus reading (buttons: bitmask)."""
        held = bool(int(buttons) >> self.config.clutch_button & 1)
        if held and self.last is not None:
            if not self.clutched:
                self.clutched = True
            return self.last  # the virtual probe stays; the stylus moves freely
        if self.clutched:  # released: re-index so the probe continues from where it stayed
            self.clutched = False
            reg = self.registration
            moved = reg.point_to_patient(p_device) - reg.translation
            self.set_registration(reg.with_translation(self.last.position - moved))
            self.reindex_count += 1
        self.last = self.probe_pose(p_device, q_device)
        return self.last

    def take_changed(self) -> bool:
        """True once after the registration changed (for passing it to the servo loop)."""
        changed, self.changed = self.changed, False
        return changed

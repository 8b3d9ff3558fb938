"""The one haptic device interface, shared by the real and the simulated backends.

Device frame (Touch X convention, used by every backend): x to the user's right, y up, z toward
the user, origin at the workspace centre; metres, newtons, seconds inside. Times are
``time.monotonic()`` seconds (system-wide, so another process can compare them).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

from pydantic import Field

from humantele.config import ConfigModel

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


class DeviceError(RuntimeError):
    """A device that cannot be opened or stopped answering; the message says what to do."""


class DeviceSpec(ConfigModel):
    """Physical figures of a device, used for limits and the stability check.

    Defaults are the 3D Systems Touch X: 7.9 N peak force (spec sheet; chai3d's table), 1.75 N
    continuous force and ~0.023 mm nominal position resolution (spec sheet, >1100 dpi),
    workspace about 160 x 120 x 120 mm (W x H x D, spec sheet). Not published, so chosen and
    marked as such: ``damping_ns_per_m`` 0.5, the physical damping at which chai3d's nominal
    maximum stiffness for the Touch X (1000 N/m) sits exactly on the Colgate-Schenkel bound at
    1 kHz (b = K T / 2); ``coulomb_friction_n`` 0.04 and ``mass_kg`` 0.045 (apparent mass at the
    tip, the figure 3D Systems gives for the Touch), orders of magnitude only.
    """

    max_force_n: float = Field(7.9, ge=0.0, le=50.0)
    continuous_force_n: float = Field(1.75, ge=0.0, le=50.0)
    resolution_m: float = Field(0.023e-3, gt=0.0, le=1e-3)
    workspace_m: tuple[float, float, float] = (0.160, 0.120, 0.120)
    damping_ns_per_m: float = Field(0.5, ge=0.0, le=100.0)
    coulomb_friction_n: float = Field(0.04, ge=0.0, le=10.0)
    mass_kg: float = Field(0.045, gt=0.0, le=10.0)


@dataclass(frozen=True, slots=True)
class DeviceState:
    """One reading of the stylus, in the device frame.

    ``t``: monotonic time (s) of the reading; ``position`` (m); ``quaternion`` (x, y, z, w) of the
    stylus in the device frame; ``buttons`` bitmask (bit 0 = button 1); ``velocity`` (m/s) when
    the device estimates it itself, else None (the servo loop differentiates).
    """

    t: float
    position: Vec3
    quaternion: Quat = (0.0, 0.0, 0.0, 1.0)
    buttons: int = 0
    velocity: Vec3 | None = None

    def is_finite(self) -> bool:
        vals = (self.t, *self.position, *self.quaternion, *(self.velocity or ()))
        return all(math.isfinite(x) for x in vals)


class HapticDevice(ABC):
    """Read the stylus pose and buttons; command a 3-DOF force (N, device frame).

    ``open()`` raises DeviceError with a clear message when the device or its driver is
    missing; ``read()`` raises DeviceError when the device stops answering. ``command_force``
    never passes a non-finite or over-limit force to the hardware (it zeroes or clamps).
    """

    name: str = "device"
    has_force: bool = True
    spec: DeviceSpec

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def close(self) -> None:
        """Zero the force and release the device; safe to call twice."""

    @abstractmethod
    def read(self) -> DeviceState: ...

    @abstractmethod
    def command_force(self, force: Vec3) -> None: ...

    def __enter__(self) -> HapticDevice:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def safe_force(force: Vec3, limit: float) -> Vec3:
    """``force`` clamped in magnitude to ``limit`` (N), direction kept; zero if not finite."""
    fx, fy, fz = force
    if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
        return (0.0, 0.0, 0.0)
    n = math.sqrt(fx * fx + fy * fy + fz * fz)
    if n > limit:
        s = limit / n if n > 0.0 else 0.0
        return (fx * s, fy * s, fz * s)
    return (fx, fy, fz)

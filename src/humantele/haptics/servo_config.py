"""The servo loop's configuration (``[servo]`` of configs/expert.toml), checked for passivity."""

from __future__ import annotations

import logging
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from humantele.config import ConfigModel, Quaternion
from humantele.geometry import Pose
from humantele.haptics.devices import DeviceConfig
from humantele.haptics.devices.sim import SimDeviceConfig
from humantele.haptics.stability import check_passivity

log = logging.getLogger(__name__)


Coord = Annotated[float, Field(ge=-10.0, le=10.0)]  # m, a device within 10 m of the world origin


class RegistrationConfig(ConfigModel):
    """``T_patient_device``: device origin in the patient frame (m) and rotation (x, y, z, w)."""

    position_m: tuple[Coord, Coord, Coord] = (0.0, 0.0, 0.0)
    quaternion: Quaternion = (0.0, 0.0, 0.0, 1.0)

    def pose(self) -> Pose:
        return Pose(np.array(self.position_m), np.array(self.quaternion))


class ServoConfig(ConfigModel):
    """The servo loop (``[servo]`` of configs/expert.toml). Gains in the patient frame.

    ``registration`` None: automatic, the device origin ``clearance_m`` above the top of the
    model at the xiphoid, device axes along the patient's (the sonographer at the patient's
    right side, facing the patient). Gains that fail the passivity check (see
    :mod:`humantele.haptics.stability`) are refused unless ``allow_unstable_gains``.
    """

    device: DeviceConfig = Field(default_factory=SimDeviceConfig)
    rate_hz: float = Field(1000.0, ge=100.0, le=4000.0)
    kp: float = Field(300.0, ge=0.0, le=5000.0, description="N/m")
    kd: float = Field(0.1, ge=0.0, le=20.0, description="N s/m")
    force_limit_n: float = Field(3.0, ge=0.0, le=7.9)
    ramp_s: float = Field(0.2, ge=0.0, le=5.0)
    method: Literal["radial", "newton", "exact"] = "radial"
    registration: RegistrationConfig | None = None
    clearance_m: float = Field(0.03, ge=0.0, le=0.5)
    motion_scale: float = Field(1.0, gt=0.0, le=10.0)
    stale_after_s: float = Field(0.005, gt=0.0, le=1.0)
    late_after_s: float = Field(0.005, gt=0.0, le=1.0)
    fault_hold_s: float = Field(0.05, ge=0.0, le=5.0)
    velocity_cutoff_hz: float = Field(100.0, gt=0.0, le=2000.0)
    realtime_priority: int = Field(80, ge=0, le=99, description="SCHED_FIFO priority; 0 = off")
    cpu_affinity: list[int] | None = None
    cpu_latency_us: int | None = Field(
        0, ge=0, le=10_000, description="us, the CPUs' longest wake-up from idle while the "
        "servo runs (/dev/cpu_dma_latency, runtime.cpu_latency); None: no request",
    )  # fmt: skip
    spin_s: float = Field(
        0.0002, ge=0.0, le=0.001, description="s, the most spun before a tick (SpinBudget)"
    )
    allow_unstable_gains: bool = False

    @model_validator(mode="after")
    def _check_gains(self) -> ServoConfig:
        spec = self.device.spec
        if spec.max_force_n <= 0.0:
            return self  # no force output: nothing to destabilise
        if self.force_limit_n > spec.max_force_n:
            raise ValueError(
                f"force_limit_n {self.force_limit_n} N exceeds the device's peak force "
                f"{spec.max_force_n} N"
            )
        chk = self.passivity()
        if not chk.passive and not self.allow_unstable_gains:
            raise ValueError(
                f"kp/kd: {chk.reason}; lower kp or kd, or set allow_unstable_gains = true"
            )
        if not chk.passive:
            log.warning("servo gains are not passive: %s", chk.reason)
        return self

    def passivity(self):  # -> PassivityCheck
        spec = self.device.spec
        return check_passivity(
            self.kp,
            self.kd,
            1.0 / self.rate_hz,
            spec.damping_ns_per_m,
            spec.resolution_m,
            spec.coulomb_friction_n,
            self.motion_scale,
        )

"""The settings of the simulated force sensor board (:mod:`humantele.forcesense.sim`), apart
from its model so that choosing a backend never imports the simulator."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from humantele.config import ConfigModel
from humantele.forcesense.model import SensorGeometry


class SimForceConfig(ConfigModel):
    """Sim board. Fields in mT, temperatures in deg C, times in s."""

    backend: Literal["sim"] = "sim"
    seed: int = 0
    geometry: SensorGeometry = Field(default_factory=SensorGeometry)
    noise_mt: float = Field(
        0.02, ge=0, description="Hall noise per sample, RMS (board averages 32 conversions)"
    )
    offset_mt: float = Field(0.3, ge=0, description="fixed per-sensor offsets, RMS")
    gain_mismatch: float = Field(0.01, ge=0, le=0.2, description="per-sensor gain error, RMS")
    temp_swing_c: float = Field(0.0, ge=0, description="temperature swing amplitude")
    temp_period_s: float = Field(300.0, gt=0)
    offset_tempco_mt_per_c: float = Field(0.05, ge=0, description="Hall offset drift")
    outside_field_mt: float = Field(0.0, ge=0, description="outside field, slowly turning")
    rate_hz: float = Field(100.0, gt=0, le=10000)

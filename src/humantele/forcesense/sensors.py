"""Force sensor configuration and factory: sim or hid, the same ``read(t)`` interface."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field

from humantele.config import CONFIG_DIR, ConfigModel, load_config
from humantele.forcesense.contact import ContactConfig
from humantele.forcesense.hid import HidForceConfig, HidForceSensor
from humantele.forcesense.sim import SimForceConfig, SimForceSensor

ForceBackendConfig = Annotated[SimForceConfig | HidForceConfig, Field(discriminator="backend")]


class ForceSensorConfig(ConfigModel):
    """The sensor backend, where its calibration lives (None: calibrate the sim at start),
    and the contact detector. File: ``configs/forcesense/*.toml``."""

    sensor: ForceBackendConfig = Field(default_factory=SimForceConfig)
    calibration_file: str | None = None
    contact: ContactConfig = Field(default_factory=ContactConfig)


def make_force_sensor(config: SimForceConfig | HidForceConfig) -> SimForceSensor | HidForceSensor:
    """The backend a configuration asks for; HidForceSensor raises ForceSensorUnavailable."""
    if isinstance(config, SimForceConfig):
        return SimForceSensor(config)
    return HidForceSensor(config)


def calibration_path(config: ForceSensorConfig) -> Path | None:
    """The calibration file (relative names are in configs/forcesense/), or None."""
    if not config.calibration_file:
        return None
    p = Path(config.calibration_file)
    return p if p.is_absolute() else CONFIG_DIR / "forcesense" / p


def load_force_config(name_or_path: str = "sim") -> ForceSensorConfig:
    """A force sensor configuration by name in configs/forcesense/ or by path."""
    path = CONFIG_DIR / "forcesense" / f"{name_or_path}.toml"
    if name_or_path.endswith((".toml", ".json")):
        path = name_or_path
    return load_config(ForceSensorConfig, path)

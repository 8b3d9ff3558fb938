"""Force sensor configuration and factory: one config union, one function.

Each backend's configuration has a ``backend`` field that picks it: ``sim`` (the simulated
board, :mod:`humantele.forcesense.sim`), ``hid`` (the board over USB HID,
:mod:`humantele.forcesense.hid`) or ``replay`` (a device recording's HID reports through the
HID reader, :mod:`humantele.forcesense.replay`); all give
:class:`~humantele.forcesense.base.ForceSensor` s.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field

from humantele.config import ConfigModel, load_config, named_config_path
from humantele.forcesense.base import ForceSensor
from humantele.forcesense.contact import ContactConfig
from humantele.forcesense.hid import HidForceConfig, HidForceSensor
from humantele.forcesense.replay import ReplayForceConfig, ReplayForceSensor
from humantele.forcesense.sim_config import SimForceConfig

ForceBackendConfig = Annotated[
    SimForceConfig | HidForceConfig | ReplayForceConfig, Field(discriminator="backend")
]
"""A force sensor board's configuration, picked by its ``backend`` field: "sim", "hid" or
"replay"."""


class ForceSensorConfig(ConfigModel):
    """The sensor backend, where its calibration lives (None: calibrate the sim at start),
    and the contact detector. Packaged set-ups: ``humantele/defaults/forcesense/*.toml``."""

    sensor: ForceBackendConfig = Field(default_factory=SimForceConfig)
    calibration_file: str | None = None
    contact: ContactConfig = Field(default_factory=ContactConfig)
    read_rate_hz: float = Field(
        100.0, ge=5, le=2000, description="a real board is read at this rate, apart from "
        "the camera (the board sends 100 Hz)")  # fmt: skip
    stale_s: float = Field(
        0.2, gt=0, le=5, description="a read with no good report this long after the last "
        "good one: the force is stale (not sent, not used for contact or calibration)")  # fmt: skip


def make_force_sensor(
    config: SimForceConfig | HidForceConfig | ReplayForceConfig,
) -> ForceSensor:
    """The force sensor a configuration asks for, not yet opened (``open()`` raises
    ForceSensorUnavailable when the board is missing)."""
    if isinstance(config, SimForceConfig):
        from humantele.forcesense.sim import SimForceSensor  # only when asked: the simulator

        return SimForceSensor(config)
    if isinstance(config, HidForceConfig):
        return HidForceSensor(config)
    if isinstance(config, ReplayForceConfig):
        return ReplayForceSensor(config)
    raise TypeError(f"not a force sensor configuration: {type(config).__name__}")


def calibration_path(config: ForceSensorConfig) -> Path | None:
    """The calibration file (a relative path is from the current directory; ``~`` is the
    user's home), or None when the sim is calibrated at start."""
    if not config.calibration_file:
        return None
    return Path(config.calibration_file).expanduser()


def load_force_config(name_or_path: str = "sim") -> ForceSensorConfig:
    """A force sensor set-up by name (packaged ``humantele/defaults/forcesense/NAME.toml``:
    ``sim``, ``hid``) or by path."""
    path = named_config_path("forcesense", name_or_path, "force sensor set-up")
    return load_config(ForceSensorConfig, path)

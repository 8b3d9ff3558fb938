"""Haptic devices: one interface (:class:`HapticDevice`), backends picked by configuration.

The device layer's pattern, shared with frame sources, force sensors and video sources: an
abstract base per family, a pydantic config per backend whose ``backend`` field picks it, one
factory (:func:`make_device`) that builds the backend a config asks for, not yet opened.

``sim`` (a simulated Touch X and sonographer's hand), ``touchx`` (the real Touch X through
OpenHaptics' libHD) and ``hid`` (a 6-DOF HID input such as the SpaceMouse, no force).
Device frame: x right, y up, z toward the user, origin at the workspace centre, metres.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any

from pydantic import Field, TypeAdapter, ValidationError

from humantele.config import ConfigError, describe_validation_error
from humantele.haptics.devices.base import (
    DeviceError,
    DeviceSpec,
    DeviceState,
    HapticDevice,
    safe_force,
)
from humantele.haptics.devices.hid import HidDevice, HidDeviceConfig
from humantele.haptics.devices.sim import ManualClock, SimDeviceConfig, SimTouchX
from humantele.haptics.devices.touchx import TouchX, TouchXConfig

DeviceConfig = Annotated[
    SimDeviceConfig | TouchXConfig | HidDeviceConfig, Field(discriminator="backend")
]
"""A haptic device's configuration, picked by its ``backend`` field: "sim", "touchx", "hid"."""
_ADAPTER: TypeAdapter = TypeAdapter(DeviceConfig)


def device_config(data: Mapping[str, Any]) -> SimDeviceConfig | TouchXConfig | HidDeviceConfig:
    """Validate a device configuration mapping; ConfigError naming the bad field (an unknown
    ``backend`` lists the known ones)."""
    try:
        return _ADAPTER.validate_python(data)
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(exc, "device")) from exc


def make_device(
    config: SimDeviceConfig | TouchXConfig | HidDeviceConfig | Mapping[str, Any] | None = None,
) -> HapticDevice:
    """The haptic device a configuration asks for (None: the sim), not yet opened. A mapping is
    validated first (:func:`device_config`)."""
    if config is None:
        config = SimDeviceConfig()
    elif isinstance(config, Mapping):
        config = device_config(config)
    if isinstance(config, SimDeviceConfig):
        return SimTouchX(config)
    if isinstance(config, TouchXConfig):
        return TouchX(config)
    if isinstance(config, HidDeviceConfig):
        return HidDevice(config)
    raise TypeError(f"not a haptic device configuration: {type(config).__name__}")


__all__ = [
    "DeviceConfig",
    "DeviceError",
    "DeviceSpec",
    "DeviceState",
    "HapticDevice",
    "HidDevice",
    "HidDeviceConfig",
    "ManualClock",
    "SimDeviceConfig",
    "SimTouchX",
    "TouchX",
    "TouchXConfig",
    "device_config",
    "make_device",
    "safe_force",
]

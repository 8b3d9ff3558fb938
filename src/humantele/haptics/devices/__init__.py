"""Haptic devices: one interface (:class:`HapticDevice`), backends picked by configuration.

``sim`` (a simulated Touch X and sonographer's hand), ``touchx`` (the real Touch X through
OpenHaptics' libHD) and ``hid`` (a 6-DOF HID input such as the SpaceMouse, no force).
Device frame: x right, y up, z toward the user, origin at the workspace centre, metres.
"""

from __future__ import annotations

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

DEVICE_KINDS = {"sim": SimTouchX, "touchx": TouchX, "hid": HidDevice}

DeviceConfig = Annotated[
    SimDeviceConfig | TouchXConfig | HidDeviceConfig, Field(discriminator="kind")
]
_ADAPTER: TypeAdapter = TypeAdapter(DeviceConfig)


def device_config(data: dict[str, Any]) -> SimDeviceConfig | TouchXConfig | HidDeviceConfig:
    """Validate a device configuration mapping; ConfigError listing the known kinds."""
    kind = data.get("kind", "sim") if isinstance(data, dict) else None
    if kind not in DEVICE_KINDS:
        raise ConfigError(
            f"device kind {kind!r} is unknown; choose one of: {', '.join(DEVICE_KINDS)}"
        )
    try:
        return _ADAPTER.validate_python({**data, "kind": kind})
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(exc, f"device ({kind})")) from exc


def make_device(config: Any = None) -> HapticDevice:
    """The device for ``config`` (a device config model or a mapping with ``kind``); not opened."""
    if config is None:
        config = SimDeviceConfig()
    elif isinstance(config, dict):
        config = device_config(config)
    kind = getattr(config, "kind", None)
    if kind not in DEVICE_KINDS:
        raise ConfigError(
            f"device kind {kind!r} is unknown; choose one of: {', '.join(DEVICE_KINDS)}"
        )
    return DEVICE_KINDS[kind](config)


__all__ = [
    "DEVICE_KINDS",
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

"""A generic HID 6-DOF input (e.g. the 3Dconnexion SpaceMouse) as a haptic device without force.

A report map (:class:`HidProfile`: ``humantele/defaults/hid/*.toml``, or a file of yours)
says which report ids carry which axes at which byte offsets, and their scales. The axes are
velocity-like (deflection of a cap), so :class:`VelocityIntegrator` integrates them into a
stylus pose in the device frame of ``base`` (x right, y up, z toward the user, metres), kept
inside the workspace box. Short, unknown or out-of-range reports are dropped and counted,
never raised.
"""

from __future__ import annotations

import math
import struct
import time
from typing import Literal

from pydantic import Field

from humantele.config import ConfigModel, load_config, named_config_path
from humantele.geometry import quat_multiply_tuple
from humantele.haptics.devices.base import DeviceError, DeviceSpec, DeviceState, HapticDevice, Vec3

SLOTS = ("tx", "ty", "tz", "rx", "ry", "rz", "buttons")
_FORMATS = {"i16le": "<h", "u16le": "<H", "u8": "<B", "i8": "<b", "u32le": "<I"}


class HidField(ConfigModel):
    """One value in a report: ``slot`` it feeds (device frame: tx, ty, tz translation rates,
    rx, ry, rz rotation rates about x, y, z; or buttons), byte ``offset`` counted from the report
    id byte (offset 0), binary ``type`` and ``scale`` (m/s or rad/s per count; sign flips)."""

    slot: Literal["tx", "ty", "tz", "rx", "ry", "rz", "buttons"]
    offset: int = Field(ge=1, le=63)
    type: Literal["i16le", "u16le", "u8", "i8", "u32le"] = "i16le"
    scale: float = 1.0


class HidReport(ConfigModel):
    """A report layout: its id (first byte), its length in bytes including the id, its fields."""

    id: int = Field(ge=0, le=255)
    length: int = Field(ge=2, le=64)
    fields: list[HidField]


class HidProfile(ConfigModel):
    """A device's report map (see humantele/defaults/hid/spacemouse.toml)."""

    name: str = "HID 6-DOF device"
    vendor_ids: list[int] = []
    product_ids: list[int] = []  # empty: any product of the vendors
    max_abs: int = Field(512, ge=1)  # axis counts beyond this are garbage: report dropped
    deadband: int = Field(0, ge=0)  # axis counts at or below this read as zero
    reports: list[HidReport] = []


class HidReportParser:
    """Bytes of one report -> {slot: value}; None (and ``dropped`` += 1) if unusable."""

    def __init__(self, profile: HidProfile) -> None:
        self.profile = profile
        self._layouts: dict[int, list[HidReport]] = {}
        for rep in profile.reports:
            for f in rep.fields:
                if f.offset + struct.calcsize(_FORMATS[f.type]) > rep.length:
                    raise ValueError(f"report {rep.id}: field {f.slot} runs past its length")
            self._layouts.setdefault(rep.id, []).append(rep)
        for reps in self._layouts.values():
            reps.sort(key=lambda r: r.length, reverse=True)
        self.parsed = 0
        self.dropped = 0

    def parse(self, data: bytes | bytearray | list[int]) -> dict[str, float] | None:
        data = bytes(data)
        layout = None
        for rep in self._layouts.get(data[0], []) if data else []:
            if len(data) >= rep.length:  # the longest layout that fits (newer models send more)
                layout = rep
                break
        if layout is None:
            self.dropped += 1
            return None
        out: dict[str, float] = {}
        for f in layout.fields:
            (raw,) = struct.unpack_from(_FORMATS[f.type], data, f.offset)
            if f.slot == "buttons":
                out["buttons"] = float(raw)
                continue
            if abs(raw) > self.profile.max_abs:
                self.dropped += 1
                return None
            out[f.slot] = 0.0 if abs(raw) <= self.profile.deadband else raw * f.scale
        self.parsed += 1
        return out


class VelocityIntegrator:
    """Integrates rates (m/s, rad/s in the device frame) into a pose kept in a workspace box."""

    def __init__(self, workspace_m: tuple[float, float, float]) -> None:
        self.half = tuple(w / 2.0 for w in workspace_m)
        self.position = [0.0, 0.0, 0.0]
        self.quaternion = (0.0, 0.0, 0.0, 1.0)
        self.rates = {s: 0.0 for s in SLOTS[:6]}
        self.buttons = 0

    def update(self, values: dict[str, float]) -> None:
        for k, v in values.items():
            if k == "buttons":
                self.buttons = int(v)
            else:
                self.rates[k] = v

    def step(self, dt: float) -> None:
        r = self.rates
        for i, k in enumerate(("tx", "ty", "tz")):
            h = self.half[i]
            self.position[i] = min(h, max(-h, self.position[i] + r[k] * dt))
        w = (r["rx"], r["ry"], r["rz"])
        ang = math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2) * dt
        if ang > 0.0:
            s = math.sin(ang / 2.0) / (ang / dt)
            dq = (w[0] * s, w[1] * s, w[2] * s, math.cos(ang / 2.0))
            q = quat_multiply_tuple(dq, self.quaternion)  # rates about the fixed device axes
            n = math.sqrt(sum(c * c for c in q))
            self.quaternion = tuple(c / n for c in q)  # type: ignore[assignment]


def load_profile(name_or_path: str) -> HidProfile:
    """A profile by name (packaged ``humantele/defaults/hid/NAME.toml``) or by path."""
    return load_config(HidProfile, named_config_path("hid", name_or_path, "HID profile"))


class HidDeviceConfig(ConfigModel):
    """The ``hid`` backend: ``profile`` is a packaged profile's name (``spacemouse``) or the
    path of a .toml profile."""

    backend: Literal["hid"] = "hid"
    profile: str = "spacemouse"
    spec: DeviceSpec = DeviceSpec(max_force_n=0.0, continuous_force_n=0.0)


class HidDevice(HapticDevice):
    """A hidapi device read through a profile; no force output (``command_force`` ignores)."""

    name = "hid"
    has_force = False

    def __init__(self, config: HidDeviceConfig | None = None) -> None:
        self.config = config or HidDeviceConfig()
        self.spec = self.config.spec
        self.profile = load_profile(self.config.profile)
        self.parser = HidReportParser(self.profile)
        self.integrator = VelocityIntegrator(self.spec.workspace_m)
        self._dev = None
        self._t_last = 0.0

    def open(self) -> None:
        try:
            import hid
        except ImportError as exc:  # pragma: no cover - hidapi is a dependency
            raise DeviceError(f"hid: the hidapi package is not importable: {exc}") from exc
        prof = self.profile
        found = [
            d
            for d in hid.enumerate()
            if d["vendor_id"] in prof.vendor_ids
            and (not prof.product_ids or d["product_id"] in prof.product_ids)
        ]
        if not found:
            ids = ", ".join(f"0x{v:04x}" for v in prof.vendor_ids)
            raise DeviceError(
                f"hid: no {prof.name} found (vendor id {ids}); check the USB connection and "
                'read permission on /dev/hidraw* (a udev rule), or use backend = "sim".'
            )
        dev = hid.device()
        try:
            dev.open_path(found[0]["path"])
            dev.set_nonblocking(True)
        except OSError as exc:
            raise DeviceError(f"hid: cannot open {prof.name}: {exc} (permissions?)") from exc
        self._dev = dev
        self._t_last = time.monotonic()

    def close(self) -> None:
        if self._dev is not None:
            self._dev.close()
            self._dev = None

    def feed(self, report: bytes | list[int]) -> bool:
        """Parse one report into the integrator; False if it was dropped."""
        values = self.parser.parse(report)
        if values is None:
            return False
        self.integrator.update(values)
        return True

    def read(self) -> DeviceState:
        if self._dev is None:
            raise DeviceError("hid: device is not open")
        try:
            for _ in range(32):
                rep = self._dev.read(64)
                if not rep:
                    break
                self.feed(rep)
        except OSError as exc:
            raise DeviceError(f"hid: {self.profile.name} stopped answering: {exc}") from exc
        now = time.monotonic()
        self.integrator.step(min(now - self._t_last, 0.05))
        self._t_last = now
        it = self.integrator
        return DeviceState(now, tuple(it.position), it.quaternion, it.buttons, None)  # type: ignore[arg-type]

    def command_force(self, force: Vec3) -> None:
        """No force output on this device."""

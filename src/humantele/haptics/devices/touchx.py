"""The real 3D Systems Touch X through the vendor's OpenHaptics HD API (libHD.so, via ctypes).

The servo loop polls the device once per tick: ``hdBeginFrame``, ``hdGetDoublev`` of
``HD_CURRENT_TRANSFORM`` (4x4, column-major, mm) and ``HD_CURRENT_BUTTONS``, ``hdSetDoublev``
of ``HD_CURRENT_FORCE`` (N), ``hdEndFrame``; the HD scheduler is started so the driver talks to
the device. HD units are mm and N; this module converts to metres at the edge. The HD frame is
the device frame of ``base`` (x right, y up, z toward the user, origin at the workspace centre).

Not exercised against hardware here (no device on the build machine); tests cover the missing
library error. Constants are those of OpenHaptics' ``hdDefines.h``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import time
from typing import Literal

from humantele.config import ConfigModel
from humantele.haptics.devices.base import DeviceError, DeviceSpec, DeviceState, HapticDevice, Vec3
from humantele.haptics.devices.base import safe_force as _safe_force

HD_SUCCESS = 0x0000
HD_CURRENT_BUTTONS = 0x2000
HD_CURRENT_POSITION = 0x2050
HD_CURRENT_TRANSFORM = 0x2052
HD_CURRENT_FORCE = 0x2700
HD_FORCE_OUTPUT = 0x4000
HD_INVALID_HANDLE = 0xFFFFFFFF


class TouchXConfig(ConfigModel):
    """The ``touchx`` backend. ``library``: libHD path or name; ``device_name``: the name set in
    the Touch Setup tool (empty = HD_DEFAULT_DEVICE)."""

    backend: Literal["touchx"] = "touchx"
    library: str = "libHD.so"
    device_name: str = ""
    spec: DeviceSpec = DeviceSpec()


class _HDErrorInfo(ctypes.Structure):
    _fields_ = [("errorCode", ctypes.c_uint), ("internalErrorCode", ctypes.c_int),
                ("hHD", ctypes.c_uint)]  # fmt: skip


def load_hd_library(name: str) -> ctypes.CDLL:
    """Load libHD; DeviceError saying how to get it when it is not installed."""
    candidates = [name]
    found = ctypes.util.find_library("HD")
    if found and found not in candidates:
        candidates.append(found)
    errors = []
    for cand in candidates:
        try:
            return ctypes.CDLL(cand)
        except OSError as exc:
            errors.append(f"{cand}: {exc}")
    raise DeviceError(
        "touchx: the OpenHaptics HD library (libHD.so) is not installed or not found "
        f"({'; '.join(errors)}). Install the 3D Systems Touch device driver and OpenHaptics "
        "for Linux, or set [servo.device] library to the path of libHD.so; to run without the "
        'device use backend = "sim" (or "hid" for a SpaceMouse).'
    )


class TouchX(HapticDevice):
    """The Touch X via libHD; see the module docstring."""

    name = "touchx"
    has_force = True

    def __init__(self, config: TouchXConfig | None = None) -> None:
        self.config = config or TouchXConfig()
        self.spec = self.config.spec
        self._lib: ctypes.CDLL | None = None
        self._hhd: int | None = None
        self._m = (ctypes.c_double * 16)()
        self._buttons = ctypes.c_int(0)
        self._force = (ctypes.c_double * 3)()
        self._in_frame = False

    def open(self) -> None:
        lib = load_hd_library(self.config.library)
        lib.hdInitDevice.restype = ctypes.c_uint
        lib.hdInitDevice.argtypes = [ctypes.c_char_p]
        lib.hdGetError.restype = _HDErrorInfo
        lib.hdGetDoublev.argtypes = [ctypes.c_uint, ctypes.POINTER(ctypes.c_double)]
        lib.hdGetIntegerv.argtypes = [ctypes.c_uint, ctypes.POINTER(ctypes.c_int)]
        lib.hdSetDoublev.argtypes = [ctypes.c_uint, ctypes.POINTER(ctypes.c_double)]
        name = self.config.device_name.encode() if self.config.device_name else None
        hhd = lib.hdInitDevice(name)
        err = lib.hdGetError()
        if hhd == HD_INVALID_HANDLE or err.errorCode != HD_SUCCESS:
            raise DeviceError(
                f"touchx: hdInitDevice failed (HD error 0x{err.errorCode:04x}, internal "
                f"{err.internalErrorCode}); is the Touch X connected and set up (Touch_Setup)?"
            )
        lib.hdEnable(HD_FORCE_OUTPUT)
        lib.hdStartScheduler()
        err = lib.hdGetError()
        if err.errorCode != HD_SUCCESS:
            lib.hdDisableDevice(hhd)
            raise DeviceError(f"touchx: hdStartScheduler failed (HD error 0x{err.errorCode:04x})")
        self._lib, self._hhd = lib, hhd

    def close(self) -> None:
        lib, hhd = self._lib, self._hhd
        if lib is None or hhd is None:
            return
        try:
            self.command_force((0.0, 0.0, 0.0))
        except DeviceError:
            pass
        lib.hdStopScheduler()
        lib.hdDisableDevice(hhd)
        self._lib = self._hhd = None

    def read(self) -> DeviceState:
        """Begin an HD frame and read the stylus; the frame ends in ``command_force``."""
        lib = self._require()
        if self._in_frame:
            lib.hdEndFrame(self._hhd)
        lib.hdBeginFrame(self._hhd)
        self._in_frame = True
        lib.hdGetDoublev(HD_CURRENT_TRANSFORM, self._m)
        lib.hdGetIntegerv(HD_CURRENT_BUTTONS, ctypes.byref(self._buttons))
        self._check("reading the stylus")
        return self._state()

    def command_force(self, force: Vec3) -> None:
        """Set the force (N, device frame; clamped, zero if not finite) and end the frame."""
        lib = self._require()
        if not self._in_frame:
            lib.hdBeginFrame(self._hhd)
        self._force[0], self._force[1], self._force[2] = _safe_force(force, self.spec.max_force_n)
        lib.hdSetDoublev(HD_CURRENT_FORCE, self._force)
        lib.hdEndFrame(self._hhd)
        self._in_frame = False
        self._check("commanding the force")

    def _require(self) -> ctypes.CDLL:
        if self._lib is None:
            raise DeviceError("touchx: device is not open")
        return self._lib

    def _check(self, what: str) -> None:
        err = self._lib.hdGetError()  # type: ignore[union-attr]
        if err.errorCode != HD_SUCCESS:
            raise DeviceError(f"touchx: HD error 0x{err.errorCode:04x} while {what}")

    def _state(self) -> DeviceState:
        m = self._m  # column-major 4x4, translation in mm at 12..14
        pos = (m[12] * 1e-3, m[13] * 1e-3, m[14] * 1e-3)
        r00, r10, r20 = m[0], m[1], m[2]
        r01, r11, r21 = m[4], m[5], m[6]
        r02, r12, r22 = m[8], m[9], m[10]
        tr = r00 + r11 + r22
        if tr > 0.0:
            s = 2.0 * math.sqrt(tr + 1.0)
            q = ((r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s, 0.25 * s)
        else:  # rare for a stylus; fall back to the general conversion
            from humantele.geometry import matrix_to_quat

            q = tuple(matrix_to_quat([[r00, r01, r02], [r10, r11, r12], [r20, r21, r22]]))
        return DeviceState(time.monotonic(), pos, q, int(self._buttons.value), None)  # type: ignore[arg-type]

"""The real 3D Systems Touch X through the vendor's OpenHaptics HD API (libHD.so, via ctypes).

OpenHaptics wants device I/O inside its own servo thread: ``open`` schedules one asynchronous
callback at the highest priority (``hdScheduleAsynchronous``) and asks the scheduler for 1 kHz
(``hdSetSchedulerRate``). Each tick the callback opens an HD frame (``hdBeginFrame``), reads
``HD_CURRENT_TRANSFORM`` (4x4, column-major, mm), ``HD_CURRENT_VELOCITY`` (mm/s) and
``HD_CURRENT_BUTTONS``, checks the calibration, writes the latest commanded force to
``HD_CURRENT_FORCE`` (N) and closes the frame (``hdEndFrame``). ``read`` returns the newest
tick's state, ``command_force`` stores the force the next tick writes: neither waits on the
device, so the servo loop of :mod:`humantele.haptics.loop` keeps its own clock.

Units: HD speaks mm and N in the device frame of ``base`` (x right, y up, z toward the user,
origin at the workspace centre); this module converts mm to m at the edge and leaves forces in
N and in that frame. Safety: every force written is finite and at most the smaller of
``spec.max_force_n`` and the device's own ``HD_NOMINAL_MAX_FORCE``; it is zero while the device
is not calibrated, after an HD error and on close.

Calibration (``hdCheckCalibration``): ``ok``; ``needs_update`` is fixed at once with the best
style the device supports (``hdUpdateCalibration``: encoder reset, then auto);
``needs_manual_input`` (a Touch X or Omni asking for its inkwell) leaves the force zero until the
stylus has been put in the inkwell, and :attr:`TouchX.calibration` says so.

HD errors (``hdGetError``) become :class:`DeviceError` messages naming the error and what to do
(:func:`describe_hd_error`). Tested against a fake libHD compiled in tests/devices (no device
here). Constants are those of OpenHaptics' ``hdDefines.h`` and ``hdScheduler.h``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import math
import threading
import time
from typing import Literal

from humantele.config import ConfigModel
from humantele.haptics.devices.base import DeviceError, DeviceSpec, DeviceState, HapticDevice, Vec3
from humantele.haptics.devices.base import safe_force as _safe_force

log = logging.getLogger(__name__)

HD_SUCCESS = 0x0000
HD_CURRENT_BUTTONS = 0x2000
HD_CURRENT_POSITION = 0x2050
HD_CURRENT_VELOCITY = 0x2051
HD_CURRENT_TRANSFORM = 0x2052
HD_DEVICE_MODEL_TYPE = 0x2501
HD_DEVICE_SERIAL_NUMBER = 0x2504
HD_CALIBRATION_STYLE = 0x2555
HD_UPDATE_RATE = 0x2600
HD_NOMINAL_MAX_FORCE = 0x2603
HD_CURRENT_FORCE = 0x2700
HD_FORCE_OUTPUT = 0x4000
HD_MAX_SCHEDULER_PRIORITY = 0xFFFF
HD_CALIBRATION_OK = 0x5000
HD_CALIBRATION_NEEDS_UPDATE = 0x5001
HD_CALIBRATION_NEEDS_MANUAL_INPUT = 0x5002
HD_CALIBRATION_ENCODER_RESET = 1 << 0
HD_CALIBRATION_AUTO = 1 << 1
HD_CALIBRATION_INKWELL = 1 << 2
HD_CALLBACK_DONE = 0
HD_CALLBACK_CONTINUE = 1
HD_INVALID_HANDLE = 0xFFFFFFFF
SERVO_RATE_HZ = 1000

CALIBRATION_NAMES = {
    HD_CALIBRATION_OK: "ok",
    HD_CALIBRATION_NEEDS_UPDATE: "needs_update",
    HD_CALIBRATION_NEEDS_MANUAL_INPUT: "needs_manual_input",
}

# hdDefines.h error codes: (name, what the user should do).
HD_ERRORS: dict[int, tuple[str, str]] = {
    0x0100: ("HD_INVALID_ENUM", "a driver/library version mismatch; reinstall OpenHaptics"),
    0x0101: ("HD_INVALID_VALUE", "a driver/library version mismatch; reinstall OpenHaptics"),
    0x0102: ("HD_INVALID_OPERATION", "a driver/library version mismatch; reinstall OpenHaptics"),
    0x0103: ("HD_INVALID_INPUT_TYPE", "a driver/library version mismatch"),
    0x0104: ("HD_BAD_HANDLE", "the device was disabled or never initialised"),
    0x0200: ("HD_WARM_MOTORS", "the motors are hot; let the device cool for a few minutes"),
    0x0201: ("HD_EXCEEDED_MAX_FORCE", "the force exceeded the device's limit; lower the gains"),
    0x0202: ("HD_EXCEEDED_MAX_FORCE_IMPULSE", "the force changed too fast; lower the gains"),
    0x0203: ("HD_EXCEEDED_MAX_VELOCITY", "the stylus moved too fast; hold it more gently"),
    0x0204: ("HD_FORCE_ERROR", "the device refused the force; restart the device"),
    0x0300: ("HD_DEVICE_FAULT", "the device reported a fault; power-cycle it"),
    0x0301: (
        "HD_DEVICE_ALREADY_INITIATED",
        "another program holds the device (Touch Diagnostic?); close it",
    ),
    0x0302: ("HD_COMM_ERROR", "lost contact with the device; check its USB cable and power"),
    0x0303: ("HD_COMM_CONFIG_ERROR", "the device is not configured; run Touch_Setup"),
    0x0304: ("HD_TIMER_ERROR", "the servo thread missed its deadline; the machine is overloaded"),
    0x0400: ("HD_ILLEGAL_BEGIN", "an HD frame was opened twice (a bug in humantele)"),
    0x0401: ("HD_ILLEGAL_END", "an HD frame was closed twice (a bug in humantele)"),
    0x0402: ("HD_FRAME_ERROR", "an HD frame error (a bug in humantele)"),
    0x0500: ("HD_INVALID_PRIORITY", "the scheduler refused the callback priority"),
    0x0501: ("HD_SCHEDULER_FULL", "the HD scheduler has too many callbacks; restart"),
    0x0600: ("HD_INVALID_LICENSE", "OpenHaptics has no valid license for this machine"),
}


def describe_hd_error(code: int, internal: int = 0) -> str:
    """A one-line description of an HD error code: name, hex code, internal code, advice."""
    name, advice = HD_ERRORS.get(code, ("unknown HD error", "see the OpenHaptics manual"))
    return f"{name} (0x{code:04x}, internal {internal}): {advice}"


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


HDSchedulerCallback = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p)


def load_hd_library(name: str) -> ctypes.CDLL:
    """Load libHD with its signatures; DeviceError saying how to get it when it is missing."""
    candidates = [name]
    found = ctypes.util.find_library("HD")
    if found and found not in candidates:
        candidates.append(found)
    errors = []
    for cand in candidates:
        try:
            lib = ctypes.CDLL(cand)
            break
        except OSError as exc:
            errors.append(f"{cand}: {exc}")
    else:
        raise DeviceError(
            "touchx: the OpenHaptics HD library (libHD.so) is not installed or not found "
            f"({'; '.join(errors)}). Install the 3D Systems Touch device driver and OpenHaptics "
            "for Linux, or set [servo.device] library to the path of libHD.so; to run without "
            'the device use backend = "sim" (or "hid" for a SpaceMouse).'
        )
    c_uint, c_int, c_double = ctypes.c_uint, ctypes.c_int, ctypes.c_double
    sigs = {
        "hdInitDevice": (c_uint, [ctypes.c_char_p]),
        "hdDisableDevice": (None, [c_uint]),
        "hdMakeCurrentDevice": (None, [c_uint]),
        "hdGetError": (_HDErrorInfo, []),
        "hdBeginFrame": (None, [c_uint]),
        "hdEndFrame": (None, [c_uint]),
        "hdGetDoublev": (None, [c_uint, ctypes.POINTER(c_double)]),
        "hdGetIntegerv": (None, [c_uint, ctypes.POINTER(c_int)]),
        "hdGetString": (ctypes.c_char_p, [c_uint]),
        "hdSetDoublev": (None, [c_uint, ctypes.POINTER(c_double)]),
        "hdEnable": (None, [c_uint]),
        "hdCheckCalibration": (c_uint, []),
        "hdUpdateCalibration": (None, [c_uint]),
        "hdSetSchedulerRate": (None, [ctypes.c_ulong]),
        "hdStartScheduler": (None, []),
        "hdStopScheduler": (None, []),
        "hdScheduleAsynchronous": (
            ctypes.c_ulong,
            [HDSchedulerCallback, ctypes.c_void_p, ctypes.c_ushort],
        ),  # fmt: skip
        "hdUnschedule": (None, [ctypes.c_ulong]),
    }
    missing = []
    for fn, (restype, argtypes) in sigs.items():
        try:
            f = getattr(lib, fn)
        except AttributeError:
            missing.append(fn)
            continue
        f.restype, f.argtypes = restype, argtypes
    if missing:
        raise DeviceError(
            f"touchx: {name} lacks {', '.join(missing)}; is it the OpenHaptics HD library "
            "(3.4 or later)?"
        )
    return lib


class TouchX(HapticDevice):
    """The Touch X via libHD's scheduler; see the module docstring.

    ``calibration``: "ok", "needs_update" or "needs_manual_input" (force zero until "ok");
    ``ticks``: servo callbacks run; ``force_limit_n``: the limit actually applied (N);
    ``model``/``serial``: what the device says it is.
    """

    name = "touchx"
    has_force = True

    def __init__(self, config: TouchXConfig | None = None) -> None:
        self.config = config or TouchXConfig()
        self.spec = self.config.spec
        self.force_limit_n = self.spec.max_force_n
        self.calibration = "unknown"
        self.calibration_style = 0
        self.ticks = 0
        self.errors = 0
        self.model = self.serial = ""
        self._lib: ctypes.CDLL | None = None
        self._hhd: int | None = None
        self._handle: int | None = None
        self._cb = HDSchedulerCallback(self._servo_tick)  # kept alive while scheduled
        self._m = (ctypes.c_double * 16)()
        self._v = (ctypes.c_double * 3)()
        self._buttons = ctypes.c_int(0)
        self._out = (ctypes.c_double * 3)()
        self._force: Vec3 = (0.0, 0.0, 0.0)  # next force to write (already safe), N
        self._state: DeviceState | None = None
        self._error: str | None = None
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ open / close
    def open(self) -> None:
        lib = load_hd_library(self.config.library)
        name = self.config.device_name.encode() if self.config.device_name else None
        hhd = lib.hdInitDevice(name)
        err = lib.hdGetError()
        if hhd == HD_INVALID_HANDLE or err.errorCode != HD_SUCCESS:
            who = repr(self.config.device_name) if self.config.device_name else "the default"
            raise DeviceError(
                f"touchx: cannot open {who} device: "
                f"{describe_hd_error(err.errorCode, err.internalErrorCode)}; is the Touch X "
                "connected and set up (Touch_Setup)?"
            )
        self._lib, self._hhd = lib, hhd
        try:
            self._read_properties()
            lib.hdEnable(HD_FORCE_OUTPUT)
            lib.hdSetSchedulerRate(SERVO_RATE_HZ)
            self._raise_if_error("setting up the device")
            self._handle = lib.hdScheduleAsynchronous(self._cb, None, HD_MAX_SCHEDULER_PRIORITY)
            self._raise_if_error("scheduling the servo callback")
            lib.hdStartScheduler()
            self._raise_if_error("starting the HD scheduler")
        except DeviceError:
            self._release()
            raise

    def _read_properties(self) -> None:
        lib = self._lib
        assert lib is not None
        peak = ctypes.c_double(0.0)
        lib.hdGetDoublev(HD_NOMINAL_MAX_FORCE, ctypes.byref(peak))
        if math.isfinite(peak.value) and peak.value > 0.0:
            self.force_limit_n = min(self.spec.max_force_n, peak.value)
        style = ctypes.c_int(0)
        lib.hdGetIntegerv(HD_CALIBRATION_STYLE, ctypes.byref(style))
        self.calibration_style = style.value
        self.model = (lib.hdGetString(HD_DEVICE_MODEL_TYPE) or b"").decode(errors="replace")
        self.serial = (lib.hdGetString(HD_DEVICE_SERIAL_NUMBER) or b"").decode(errors="replace")
        lib.hdGetError()  # optional properties: an error here is not fatal

    def close(self) -> None:
        """Zero the force, stop the scheduler, release the device; safe to call twice."""
        if self._lib is None:
            return
        with self._lock:
            self._force = (0.0, 0.0, 0.0)
        self._release()

    def _release(self) -> None:
        lib, hhd = self._lib, self._hhd
        if lib is None:
            return
        self._force = (0.0, 0.0, 0.0)
        lib.hdStopScheduler()  # waits for the running tick
        if self._handle is not None:
            lib.hdUnschedule(self._handle)
            self._handle = None
        if hhd is not None:
            lib.hdDisableDevice(hhd)
        lib.hdGetError()
        self._lib = self._hhd = None

    # ------------------------------------------------------------------ servo loop side
    def read(self) -> DeviceState:
        """The newest servo tick's stylus state; DeviceError for an HD error since last read."""
        if self._lib is None:
            raise DeviceError("touchx: device is not open")
        with self._lock:
            error, self._error = self._error, None
            state = self._state
        if error is not None:
            raise DeviceError(f"touchx: {error}")
        if state is None:
            raise DeviceError("touchx: no servo tick yet (is the HD scheduler running?)")
        return state

    def command_force(self, force: Vec3) -> None:
        """Set the force the next servo tick writes (N, device frame; clamped, zero if NaN)."""
        if self._lib is None:
            raise DeviceError("touchx: device is not open")
        safe = _safe_force(force, self.force_limit_n)
        with self._lock:
            self._force = safe

    def _raise_if_error(self, what: str) -> None:
        err = self._lib.hdGetError()  # type: ignore[union-attr]
        if err.errorCode != HD_SUCCESS:
            raise DeviceError(
                f"touchx: {describe_hd_error(err.errorCode, err.internalErrorCode)} while {what}"
            )

    # ------------------------------------------------------------------ HD servo thread
    def _servo_tick(self, _data: int | None) -> int:
        """One HD scheduler tick (HD servo thread, 1 kHz). Never raises into C."""
        try:
            return self._tick()
        except Exception as exc:  # noqa: BLE001 - an exception must not kill the servo thread
            with self._lock:
                self._error = f"servo callback failed: {exc!r}"
            return HD_CALLBACK_CONTINUE

    def _tick(self) -> int:
        lib, hhd = self._lib, self._hhd
        if lib is None or hhd is None:
            return HD_CALLBACK_DONE
        lib.hdBeginFrame(hhd)
        lib.hdGetDoublev(HD_CURRENT_TRANSFORM, self._m)
        lib.hdGetDoublev(HD_CURRENT_VELOCITY, self._v)
        lib.hdGetIntegerv(HD_CURRENT_BUTTONS, ctypes.byref(self._buttons))
        cal = lib.hdCheckCalibration()
        if cal == HD_CALIBRATION_NEEDS_UPDATE:
            style = self.calibration_style
            for s in (HD_CALIBRATION_ENCODER_RESET, HD_CALIBRATION_AUTO):
                if style & s:
                    lib.hdUpdateCalibration(s)
                    break
        calibration = CALIBRATION_NAMES.get(cal, f"unknown 0x{cal:04x}")
        with self._lock:
            force = self._force if cal == HD_CALIBRATION_OK and self._error is None else None
        out = self._out
        out[0], out[1], out[2] = force or (0.0, 0.0, 0.0)
        lib.hdSetDoublev(HD_CURRENT_FORCE, out)
        lib.hdEndFrame(hhd)
        err = lib.hdGetError()
        state = self._make_state(time.monotonic())
        with self._lock:
            self.ticks += 1
            if calibration != self.calibration:
                self._calibration_changed(calibration)
            if err.errorCode != HD_SUCCESS:
                self.errors += 1
                self._error = describe_hd_error(err.errorCode, err.internalErrorCode)
                self._force = (0.0, 0.0, 0.0)  # an HD error drops the commanded force
            self._state = state
        return HD_CALLBACK_CONTINUE

    def _calibration_changed(self, calibration: str) -> None:
        self.calibration = calibration
        if calibration == "needs_manual_input":
            log.warning("touchx: calibration needed: put the stylus in the inkwell (force off)")
        elif calibration != "ok":
            log.warning("touchx: calibration %s (force off until ok)", calibration)

    def _make_state(self, t: float) -> DeviceState:
        m, v = self._m, self._v  # column-major 4x4, translation in mm at 12..14; v in mm/s
        pos = (m[12] * 1e-3, m[13] * 1e-3, m[14] * 1e-3)
        vel = (v[0] * 1e-3, v[1] * 1e-3, v[2] * 1e-3)
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
        return DeviceState(t, pos, q, int(self._buttons.value), vel)  # type: ignore[arg-type]

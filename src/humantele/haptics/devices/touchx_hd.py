"""OpenHaptics HD API for :mod:`humantele.haptics.devices.touchx`: constants (``hdDefines.h``,
``hdScheduler.h``; checked value by value against OpenHaptics 3.0 and 3.3 headers), error
descriptions, loading libHD with its signatures (:func:`load_hd_library`: a missing libHD or a
missing library it needs named as such), the Touch driver's ``GTDD_HOME``, the calibration style
OpenHaptics' Calibration example picks, and the servo callback's timing histogram."""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import os
import re

from humantele.haptics.devices.base import DeviceError

HD_SUCCESS = 0x0000
HD_WARM_MOTORS = 0x0200
HD_CURRENT_BUTTONS = 0x2000
HD_CURRENT_POSITION = 0x2050
HD_CURRENT_VELOCITY = 0x2051
HD_CURRENT_TRANSFORM = 0x2052
HD_DEVICE_MODEL_TYPE = 0x2501
HD_DEVICE_SERIAL_NUMBER = 0x2504
HD_OUTPUT_DOF = 0x2554
HD_CALIBRATION_STYLE = 0x2555
HD_UPDATE_RATE = 0x2600
HD_NOMINAL_MAX_FORCE = 0x2603
HD_NOMINAL_MAX_CONTINUOUS_FORCE = 0x2604
HD_MOTOR_TEMPERATURE = 0x2605
HD_CURRENT_FORCE = 0x2700
HD_FORCE_OUTPUT = 0x4000
HD_MAX_FORCE_CLAMPING = 0x4001
HD_FORCE_RAMPING = 0x4002
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
# PreventWarmMotors (OpenHaptics example): normalised motor temperature thresholds and the
# per-tick factors of its adaptive clamp.
TEMP_RAMP_DOWN_ON, TEMP_RAMP_DOWN_OFF = 0.7, 0.5
TEMP_DOWN_RATE, TEMP_UP_RATE = 0.999, 1.001
# The thermal budget's hot / cool thresholds, as fractions of the continuous force squared.
BUDGET_ON, BUDGET_OFF = 0.5, 0.25
CALIBRATION_UPDATE_EVERY_S = 0.1
# hduIsSchedulerError (OpenHaptics' hduError.cpp): errors "that would prevent proper operation
# of the servo loop": HD_COMM_ERROR, HD_COMM_CONFIG_ERROR, HD_TIMER_ERROR, HD_INVALID_PRIORITY,
# HD_SCHEDULER_FULL. Its examples stop the callback on them (HelloHapticDevice.c) and quit,
# "since the user likely unplugged the device" (ErrorHandling.c).
HD_SCHEDULER_ERRORS = frozenset({0x0302, 0x0303, 0x0304, 0x0500, 0x0501})

CALIBRATION_NAMES = {
    HD_CALIBRATION_OK: "ok",
    HD_CALIBRATION_NEEDS_UPDATE: "needs_update",
    HD_CALIBRATION_NEEDS_MANUAL_INPUT: "needs_manual_input",
}
STYLE_NAMES = {
    HD_CALIBRATION_AUTO: "auto",
    HD_CALIBRATION_INKWELL: "inkwell",
    HD_CALIBRATION_ENCODER_RESET: "encoder_reset",
}
# Libraries libHD needs that a user installs separately, and what to install for each.
DEPENDENCY_HINTS = {
    "libPhantomIOLib42": "the 3D Systems Touch device driver (TouchDriver for Linux): copy its "
    "usr/lib/libPhantomIOLib42.so to /usr/lib (or add its folder to LD_LIBRARY_PATH) and set "
    "GTDD_HOME",
    "libPHANToMIO": "the PHANTOM Device Drivers (PDD) that this OpenHaptics version was built for",
    "libncurses": "the ncurses 5 compatibility library (Debian/Ubuntu: libncurses5)",
    "libtinfo": "the ncurses 5 compatibility library (Debian/Ubuntu: libtinfo5)",
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
    0x0304: (
        "HD_TIMER_ERROR",
        "the servo loop missed its time slice (a callback ran long or the machine is "
        "overloaded); the device cut its force",
    ),
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


class _HDErrorInfo(ctypes.Structure):
    _fields_ = [("errorCode", ctypes.c_uint), ("internalErrorCode", ctypes.c_int),
                ("hHD", ctypes.c_uint)]  # fmt: skip


HDSchedulerCallback = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p)

_DLOPEN_MISSING = re.compile(r"^(?P<lib>[^:]+?): cannot open shared object file")


def missing_library(candidate: str, exc: OSError) -> str | None:
    """The library that is missing when loading ``candidate`` failed with ``exc``: None when it
    is ``candidate`` itself (or not a missing file), else the dependency's file name (glibc's
    dlopen message names the first file it could not open)."""
    m = _DLOPEN_MISSING.match(str(exc))
    if m is None:
        return None
    lib = os.path.basename(m.group("lib").strip())
    return None if lib == os.path.basename(candidate) else lib


def _dependency_hint(lib: str) -> str:
    for prefix, hint in DEPENDENCY_HINTS.items():
        if lib.startswith(prefix):
            return hint
    return "the package that provides it (ldd on libHD.so lists what is missing)"


class HDLibrary:
    """libHD's functions with their signatures, as attributes (``lib.hdBeginFrame(...)``).

    Those the servo callback calls are bound through ``ctypes.PyDLL``: they keep the GIL,
    because a ``CDLL`` call releases and re-takes it around every call, and each re-take waits
    for whatever other Python thread holds it (up to the switch interval: a dozen such waits in
    one callback made it run for milliseconds). The calls that block or wait for the scheduler
    thread (``GIL_FREE``: init, start/stop, unschedule, disable) release it, or stopping the
    scheduler would deadlock on a callback waiting for the GIL."""

    GIL_FREE = frozenset({"hdInitDevice", "hdDisableDevice", "hdStartScheduler",
                          "hdStopScheduler", "hdUnschedule", "hdScheduleAsynchronous"})  # fmt: skip

    def __init__(self, path: str, cdll: ctypes.CDLL) -> None:
        self.path = path
        self._c = cdll
        self._py = ctypes.PyDLL(path, handle=cdll._handle)

    def bind(self, fn: str, restype: object, argtypes: list) -> None:
        """Bind ``fn`` (AttributeError when libHD lacks it)."""
        f = getattr(self._c if fn in self.GIL_FREE else self._py, fn)
        f.restype, f.argtypes = restype, argtypes
        setattr(self, fn, f)


def load_hd_library(name: str) -> HDLibrary:
    """Load libHD with its signatures; DeviceError saying what is missing when it cannot be
    loaded: libHD itself, or a library it needs (named, with what to install)."""
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
            dep = missing_library(cand, exc)
            if dep is not None:
                raise DeviceError(
                    f"touchx: the OpenHaptics HD library {cand} is installed but a library it "
                    f"needs is missing: {dep} ({exc}). Install {_dependency_hint(dep)}."
                ) from exc
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
        "hdGetSchedulerTimeStamp": (c_double, []),
    }
    hd = HDLibrary(cand, lib)
    missing = []
    for fn, (restype, argtypes) in sigs.items():
        try:
            hd.bind(fn, restype, argtypes)
        except AttributeError:
            missing.append(fn)
    if missing:
        raise DeviceError(
            f"touchx: {name} lacks {', '.join(missing)}; is it the OpenHaptics HD library "
            "(3.0 or later)?"
        )
    return hd


def gtdd_home_problem(env: dict[str, str] | None = None) -> str | None:
    """Why the 3D Systems Touch driver cannot find its device configuration, or None. The driver
    (libPhantomIOLib42) reads what Touch_Setup saved under ``$GTDD_HOME/config``; without
    GTDD_HOME it prints "Config directory not set correctly." and finds no device."""
    env = os.environ if env is None else env
    home = env.get("GTDD_HOME")
    if not home:
        return (
            "GTDD_HOME is not set: the Touch device driver (libPhantomIOLib42.so) reads the "
            "device configuration Touch_Setup saved under $GTDD_HOME/config; set GTDD_HOME (for "
            "example /usr/share/3DSystems) in the environment of the expert daemon"
        )
    if not os.path.isdir(os.path.join(home, "config")):
        return (
            f"GTDD_HOME is {home!r} but {os.path.join(home, 'config')} does not exist: run "
            "Touch_Setup (as the same user) to save the device configuration there"
        )
    return None


def choose_calibration_style(supported: int) -> int:
    """The style OpenHaptics' Calibration example picks: AUTO, else INKWELL, else ENCODER_RESET
    (0 when none is supported)."""
    for style in (HD_CALIBRATION_AUTO, HD_CALIBRATION_INKWELL, HD_CALIBRATION_ENCODER_RESET):
        if supported & style:
            return style
    return 0


class CallbackTiming:
    """The servo callback's own period (entry to entry, as the Python code runs: GIL waits
    included) and duration (``hdGetSchedulerTimeStamp`` at its end: from the scheduler tick's
    start, so the wait for the GIL is counted), in 10 us bins; O(1) per tick."""

    BIN_US = 10.0
    NBINS = 5000

    def __init__(self) -> None:
        self.period = [0] * self.NBINS
        self.duration = [0] * self.NBINS
        self.n_period = self.n_duration = 0
        self.max_period_us = self.max_duration_us = 0.0
        self._last: float | None = None

    def enter(self, t: float) -> None:
        if self._last is not None:
            us = (t - self._last) * 1e6
            self.period[min(max(int(us / self.BIN_US), 0), self.NBINS - 1)] += 1
            self.n_period += 1
            self.max_period_us = max(self.max_period_us, us)
        self._last = t

    def done(self, seconds: float) -> None:
        us = seconds * 1e6
        if not math.isfinite(us):
            return
        self.duration[min(max(int(us / self.BIN_US), 0), self.NBINS - 1)] += 1
        self.n_duration += 1
        self.max_duration_us = max(self.max_duration_us, us)

    @classmethod
    def _pct(cls, hist: list[int], n: int, q: float, top: float) -> float:
        if n == 0:
            return 0.0
        want, acc = q * n, 0
        for i, c in enumerate(hist):
            acc += c
            if acc >= want and c:
                return min((i + 0.5) * cls.BIN_US, top)
        return top

    def count_over(self, which: str, us: float) -> int:
        hist = self.period if which == "period" else self.duration
        return sum(hist[int(us / self.BIN_US) :])

    def summary(self) -> dict[str, float]:
        """p50/p99/max of period and duration (us), and callbacks over 1 ms / periods over 2 ms."""
        p, d = self.period, self.duration
        return {
            "callbacks": float(self.n_duration),
            "period_p50_us": self._pct(p, self.n_period, 0.5, self.max_period_us),
            "period_p99_us": self._pct(p, self.n_period, 0.99, self.max_period_us),
            "period_max_us": self.max_period_us,
            "duration_p50_us": self._pct(d, self.n_duration, 0.5, self.max_duration_us),
            "duration_p99_us": self._pct(d, self.n_duration, 0.99, self.max_duration_us),
            "duration_max_us": self.max_duration_us,
            "durations_over_1ms": float(self.count_over("duration", 1000.0)),
            "periods_over_2ms": float(self.count_over("period", 2000.0)),
        }

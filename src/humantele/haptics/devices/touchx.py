"""The real 3D Systems Touch X through the vendor's OpenHaptics HD API (libHD.so, via ctypes).

Checked against OpenHaptics' own headers (``hdDefines.h``, ``hdDevice.h``, ``hdScheduler.h``),
its examples (Calibration, PreventWarmMotors, ErrorHandling) and its Programmer's Guide and API
reference (public copies: github.com/danepowell/openhaptics, github.com/hhmai/PhantomAPI).

OpenHaptics wants device I/O inside its own servo thread: ``open`` schedules one asynchronous
callback at the highest priority (``hdScheduleAsynchronous``) and asks the scheduler for 1 kHz
(``hdSetSchedulerRate``). Each tick the callback opens an HD frame (``hdBeginFrame``), reads
``HD_CURRENT_TRANSFORM`` (4x4, column-major, translation in mm at 12..14),
``HD_CURRENT_VELOCITY`` (mm/s), ``HD_CURRENT_BUTTONS`` and ``HD_MOTOR_TEMPERATURE``, checks the
calibration, writes the latest commanded force, limited as below, to ``HD_CURRENT_FORCE`` (N)
and closes the frame (``hdEndFrame``). ``read`` returns the newest tick's state,
``command_force`` stores the force the next tick writes, ``wait_tick`` blocks (the GIL free)
until the next tick: the servo process follows the device's clock instead of spinning on its
own, because every tick of this callback needs the GIL (see :mod:`humantele.haptics.servo_child`).
The libHD calls the callback makes keep the GIL (``ctypes.PyDLL``, see :class:`HDLibrary`), so
it takes the GIL once per tick, not once per call.

Calling convention: ``hdExport.h`` declares the API ``__attribute__((stdcall))`` on Linux, which
x86-64 ignores (System V ABI), and the callback with none: plain ``CDLL``/``CFUNCTYPE`` (OpenHaptics
3.4 for Linux is amd64 only). Types: ``HHD``/``HDenum`` unsigned int, ``HDSchedulerHandle``
unsigned long, priority ``HDushort``, ``hdGetError`` returns ``HDErrorInfo`` by value.

Units: HD speaks mm and N in the device frame of ``base`` (x right, y up, z toward the user,
origin at the workspace centre); this module converts mm to m at the edge and leaves forces in
N and in that frame.

Force limit (safety): every force written is finite and at most the peak, the smaller of
``spec.max_force_n`` and the device's ``HD_NOMINAL_MAX_FORCE``. Sustained force is held to the
continuous rating (``HD_NOMINAL_MAX_CONTINUOUS_FORCE``, 1.75 N on a Touch X) by OpenHaptics'
PreventWarmMotors scheme: once hot, an adaptive clamp starts at the force then commanded and
decays by 0.1 % a tick to the continuous rating; once cool it recovers by 0.1 % a tick. Hot is
the device's own motor model (``HD_MOTOR_TEMPERATURE`` above 0.7, cool below 0.5) or a thermal
budget on the squared force (motor heating goes as current squared: ``heat``, |F|^2 low-passed
over ``thermal_time_constant_s``, above half the continuous rating squared, cool below a
quarter), so a peak passes for a fraction of a second and a sustained press settles at the
rating with no step. If the device still reports ``HD_WARM_MOTORS``,
the force ramps down to zero over ``warm_ramp_s`` (logged: never a step mid-contact), stays
off until the motors have cooled (temperature below 0.5, or ``warm_cooldown_s`` without a
temperature reading) and ramps back up over ``ramp_s``.

Calibration, as OpenHaptics' Calibration example: the supported styles
(``HD_CALIBRATION_STYLE``) give one style, AUTO first, then INKWELL, then ENCODER_RESET.
``needs_update`` is updated with that style from the servo tick (``hdUpdateCalibration``, after
the frame, at most every 0.1 s): AUTO as the arm moves, INKWELL once the stylus is in the inkwell
(``needs_manual_input`` says to put it there). ENCODER_RESET zeroes the encoders wherever the arm
is, so the tick never does it: only :mod:`.touchx_reset` (``python -m
humantele.haptics.devices.touchx_reset``), before the scheduler starts and after the user
confirmed the arm is at its reset pose. Force is zero while not calibrated and, as the guide
warns that the position may jump when calibration changes, ramps back over
``ramp_s`` when it returns to ok. :attr:`TouchX.calibration` says what is needed.

HD errors (``hdGetError``, drained each tick) become :class:`DeviceError` messages naming the
error and what to do (:func:`describe_hd_error`) and zero the commanded force; a missing libHD, a
missing library libHD needs (the Touch driver's ``libPhantomIOLib42.so``) and an unset
``GTDD_HOME`` are each named as what is missing. The callback's own period and duration
(``hdGetSchedulerTimeStamp`` at its end: the wait for the GIL counted) are kept in
:attr:`TouchX.timing`. Constants, error texts and the loader: :mod:`.touchx_hd`. Tested against a
fake libHD compiled in tests/devices (no device here).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import math
import os
import threading
import time
from typing import Literal

from pydantic import Field

from humantele.config import ConfigModel
from humantele.haptics.devices.base import DeviceError, DeviceSpec, DeviceState, HapticDevice, Vec3
from humantele.haptics.devices.base import safe_force as _safe_force
from humantele.haptics.devices.touchx_hd import (  # noqa: F401 - re-exported
    BUDGET_OFF,
    BUDGET_ON,
    CALIBRATION_NAMES,
    CALIBRATION_UPDATE_EVERY_S,
    HD_CALIBRATION_ENCODER_RESET,
    HD_CALIBRATION_INKWELL,
    HD_CALIBRATION_NEEDS_UPDATE,
    HD_CALIBRATION_OK,
    HD_CALIBRATION_STYLE,
    HD_CALLBACK_CONTINUE,
    HD_CALLBACK_DONE,
    HD_CURRENT_BUTTONS,
    HD_CURRENT_FORCE,
    HD_CURRENT_TRANSFORM,
    HD_CURRENT_VELOCITY,
    HD_DEVICE_MODEL_TYPE,
    HD_DEVICE_SERIAL_NUMBER,
    HD_ERRORS,
    HD_FORCE_OUTPUT,
    HD_FORCE_RAMPING,
    HD_INVALID_HANDLE,
    HD_MAX_FORCE_CLAMPING,
    HD_MAX_SCHEDULER_PRIORITY,
    HD_MOTOR_TEMPERATURE,
    HD_NOMINAL_MAX_CONTINUOUS_FORCE,
    HD_NOMINAL_MAX_FORCE,
    HD_OUTPUT_DOF,
    HD_SCHEDULER_ERRORS,
    HD_SUCCESS,
    HD_WARM_MOTORS,
    SERVO_RATE_HZ,
    STYLE_NAMES,
    TEMP_DOWN_RATE,
    TEMP_RAMP_DOWN_OFF,
    TEMP_RAMP_DOWN_ON,
    TEMP_UP_RATE,
    CallbackTiming,
    HDLibrary,
    HDSchedulerCallback,
    choose_calibration_style,
    describe_hd_error,
    gtdd_home_problem,
    load_hd_library,
    missing_library,
)

log = logging.getLogger(__name__)


class TouchXConfig(ConfigModel):
    """The ``touchx`` backend. ``library``: libHD path or name; ``device_name``: the name set in
    the Touch Setup tool (empty = HD_DEFAULT_DEVICE); ``thermal_time_constant_s``: the window of
    the force budget (s); ``ramp_s``: force ramp-up after calibration or warm motors (s);
    ``warm_ramp_s``: ramp-down on HD_WARM_MOTORS (s); ``warm_cooldown_s``: how long the force
    stays off after HD_WARM_MOTORS when the device gives no motor temperature (s)."""

    backend: Literal["touchx"] = "touchx"
    library: str = "libHD.so"
    device_name: str = ""
    spec: DeviceSpec = DeviceSpec()
    thermal_time_constant_s: float = Field(1.0, gt=0.0, le=600.0)
    ramp_s: float = Field(1.0, ge=0.0, le=10.0)
    warm_ramp_s: float = Field(0.2, gt=0.0, le=10.0)
    warm_cooldown_s: float = Field(60.0, ge=0.0, le=3600.0)
    reopen_first_s: float = Field(0.5, ge=0.0, le=60.0)
    reopen_max_s: float = Field(8.0, ge=0.0, le=600.0)


class TouchX(HapticDevice):
    """The Touch X via libHD's scheduler; see the module docstring.

    ``calibration``: "ok", "needs_update" or "needs_manual_input" (force zero until "ok");
    ``calibration_styles``/``calibration_style``: supported and chosen (``STYLE_NAMES``);
    ``ticks``: servo callbacks run; ``force_limit_n``: peak limit (N); ``continuous_force_n``:
    the sustained limit (N); ``limit_n``: the limit of the last tick (N); ``warm_motors``: force
    ramped off until the motors cool; ``temperature``: the hottest motor (0 room .. 1 overheat,
    None if the device gives none); ``timing``: the callback's period and duration;
    ``model``/``serial``: what the device says it is; ``thread_priority``: the SCHED_FIFO
    priority the HD servo thread is given from inside its first callback (0: left as it is; set
    before ``open``); ``thread_fifo``: the priority it then has (0: normal), read back there;
    ``thread_policy``: the same in words.
    """

    name = "touchx"
    has_force = True

    def __init__(self, config: TouchXConfig | None = None) -> None:
        self.config = config or TouchXConfig()
        self.spec = self.config.spec
        self.force_limit_n = self.spec.max_force_n
        self.continuous_force_n = min(self.spec.continuous_force_n, self.force_limit_n)
        self.limit_n = self.force_limit_n
        self.calibration = "unknown"
        self.calibration_styles = 0
        self.calibration_style = 0
        self.ticks = 0
        self.errors = 0
        self.warm_motors = False
        self.temperature: float | None = None
        self.timing = CallbackTiming()
        self.model = self.serial = ""
        self.thread_priority = 0
        self.thread_fifo = 0
        self.thread_policy = "not started"
        self.lost: str | None = None  # why the device was lost (a scheduler error), or None
        self.reinits = 0  # times the device was re-initialised after it was lost
        self.reopen_attempts = 0  # attempts since it was lost
        self._lost_at = self._next_try = 0.0
        self._backoff = self.config.reopen_first_s
        self._clock = time.monotonic  # the back-off's clock (s); tests drive it
        self._thread_setup = False  # the next tick sets its thread's policy (a new thread)
        self._stop_cb = False  # a scheduler error in this session: the callback stops
        self._lib: HDLibrary | None = None
        self._hhd: int | None = None
        self._handle: int | None = None
        self._cb = HDSchedulerCallback(self._servo_tick)  # kept alive while scheduled
        self._m = (ctypes.c_double * 16)()
        self._v = (ctypes.c_double * 3)()
        self._temps = (ctypes.c_double * 6)()
        self._n_motors = 0  # 0: no HD_MOTOR_TEMPERATURE
        self._buttons = ctypes.c_int(0)
        self._in_frame = False
        self._out = (ctypes.c_double * 3)()
        self._force: Vec3 = (0.0, 0.0, 0.0)  # next force to write (already safe), N
        self._state: DeviceState | None = None
        self._error: str | None = None
        self._messages: list[tuple[str, tuple[object, ...]]] = []  # from the HD servo thread
        self._lock = threading.Lock()
        self._cv = threading.Condition(self._lock)
        # force limiting (HD servo thread only)
        self._dt = 1.0 / SERVO_RATE_HZ
        self._heat = 0.0  # |F|^2 low-passed, N^2
        self._clamp = self.force_limit_n  # the adaptive clamp (N), see _limited
        self._hot = self._hot_said = False
        self._scale = 1.0  # ramp factor: calibration and warm motors
        self._warm_last = -math.inf
        self._last_update = -math.inf

    # ------------------------------------------------------------------ open / close
    def open(self) -> None:
        lib = load_hd_library(self.config.library)
        name = self.config.device_name.encode() if self.config.device_name else None
        for _ in range(64):  # errors left from a session before (a lost device's last ticks)
            if lib.hdGetError().errorCode == HD_SUCCESS:
                break
        hhd = lib.hdInitDevice(name)
        err = lib.hdGetError()
        if hhd == HD_INVALID_HANDLE or err.errorCode != HD_SUCCESS:
            if hhd != HD_INVALID_HANDLE:  # opened, yet an error: release it, or it stays held
                lib.hdDisableDevice(hhd)
            who = repr(self.config.device_name) if self.config.device_name else "the default"
            gtdd = gtdd_home_problem()
            raise DeviceError(
                f"touchx: cannot open {who} device: "
                f"{describe_hd_error(err.errorCode, err.internalErrorCode)}; "
                + (f"{gtdd}." if gtdd else "is the Touch X connected and set up (Touch_Setup)?")
            )
        self._lib, self._hhd = lib, hhd
        with self._lock:
            self._state, self._error, self._force = None, None, (0.0, 0.0, 0.0)
        if self.ticks:  # re-initialised: the force ramps back, calibration is read anew
            self._scale = 0.0
            self.calibration = "unknown"
        try:
            self._read_properties()
            lib.hdEnable(HD_FORCE_OUTPUT)
            self._raise_if_error("enabling force output")
            for cap in (HD_FORCE_RAMPING, HD_MAX_FORCE_CLAMPING):  # as OpenHaptics' examples
                lib.hdEnable(cap)
            self._drain_errors()  # optional safety features: not fatal if unsupported
            lib.hdSetSchedulerRate(SERVO_RATE_HZ)
            self._raise_if_error("setting the scheduler rate")
            self._handle = lib.hdScheduleAsynchronous(self._cb, None, HD_MAX_SCHEDULER_PRIORITY)
            self._raise_if_error("scheduling the servo callback")
            self._thread_setup = True
            self._stop_cb = False
            lib.hdStartScheduler()
            self._raise_if_error("starting the HD scheduler")
        except Exception:  # a DeviceError, or anything: never a half-open device
            self._release()
            raise

    def _read_properties(self) -> None:
        lib = self._lib
        assert lib is not None
        self._drain_errors()
        val = ctypes.c_double(0.0)
        lib.hdGetDoublev(HD_NOMINAL_MAX_FORCE, ctypes.byref(val))
        if lib.hdGetError().errorCode == HD_SUCCESS and math.isfinite(val.value) and val.value > 0:
            self.force_limit_n = min(self.spec.max_force_n, val.value)
        val.value = 0.0
        lib.hdGetDoublev(HD_NOMINAL_MAX_CONTINUOUS_FORCE, ctypes.byref(val))
        cont = val.value if lib.hdGetError().errorCode == HD_SUCCESS else math.nan
        if not (math.isfinite(cont) and cont > 0):
            cont = self.spec.continuous_force_n
            log.warning("touchx: no HD_NOMINAL_MAX_CONTINUOUS_FORCE; using the spec's %.2f N", cont)
        self.continuous_force_n = min(self.spec.continuous_force_n, cont, self.force_limit_n)
        self.limit_n = self._clamp = self.force_limit_n
        dof = ctypes.c_int(0)
        lib.hdGetIntegerv(HD_OUTPUT_DOF, ctypes.byref(dof))
        n = dof.value if lib.hdGetError().errorCode == HD_SUCCESS and 0 < dof.value <= 6 else 3
        lib.hdGetDoublev(HD_MOTOR_TEMPERATURE, self._temps)
        self._n_motors = n if lib.hdGetError().errorCode == HD_SUCCESS else 0
        style = ctypes.c_int(0)
        lib.hdGetIntegerv(HD_CALIBRATION_STYLE, ctypes.byref(style))
        self.calibration_styles = style.value if lib.hdGetError().errorCode == HD_SUCCESS else 0
        self.calibration_style = choose_calibration_style(self.calibration_styles)
        self.model = (lib.hdGetString(HD_DEVICE_MODEL_TYPE) or b"").decode(errors="replace")
        self.serial = (lib.hdGetString(HD_DEVICE_SERIAL_NUMBER) or b"").decode(errors="replace")
        self._drain_errors()  # optional properties: an error here is not fatal

    def close(self) -> None:
        """Zero the force, stop the scheduler, release the device; safe to call twice."""
        self.lost = None
        if self._lib is None:
            with self._cv:
                self._cv.notify_all()
            return
        with self._lock:
            self._force = (0.0, 0.0, 0.0)
        self._release()
        self._flush_messages()

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
        for _ in range(64):  # nothing of this session is left for the next
            if lib.hdGetError().errorCode == HD_SUCCESS:
                break
        self._lib = self._hhd = None
        with self._cv:
            self._cv.notify_all()

    # ------------------------------------------------------------------ servo loop side
    def read(self) -> DeviceState:
        """The newest servo tick's stylus state; DeviceError for an HD error since last read,
        and while the device is lost (:meth:`_recover` re-initialises it with back-off)."""
        if self.lost is not None:
            self._recover()
        if self._lib is None:
            raise DeviceError("touchx: device is not open")
        with self._lock:
            error, self._error = self._error, None
            state = self._state
        if self._messages:
            self._flush_messages()
        if error is not None:
            raise DeviceError(f"touchx: {error}")
        if state is None:
            raise DeviceError("touchx: no servo tick yet (is the HD scheduler running?)")
        return state

    def wait_tick(self, after: int, timeout: float) -> int:
        """Block until a servo tick later than tick number ``after`` has run, at most
        ``timeout`` s; returns the newest tick number. The wait holds no GIL, so the HD servo
        thread's callback is never kept waiting by the caller. While the device is lost it
        waits the whole ``timeout`` (the loop never spins)."""
        with self._cv:
            if self.ticks <= after and (self._lib is not None or self.lost is not None):
                self._cv.wait(timeout)
            return self.ticks

    def command_force(self, force: Vec3) -> None:
        """Set the force the next servo tick writes (N, device frame; clamped, zero if NaN)."""
        if self._lib is None or self.lost is not None:
            raise DeviceError(f"touchx: device {'lost' if self.lost else 'is not open'}")
        safe = _safe_force(force, self.force_limit_n)
        with self._lock:
            self._force = safe

    # ------------------------------------------------------------------ a lost device
    def _recover(self) -> None:
        """The device was lost (a scheduler error stopped the callback, see
        :meth:`_handle_errors`): release it once, then re-initialise it (:meth:`open`: a new
        hdInitDevice, as a replugged device needs) when the back-off says, waiting
        ``reopen_first_s`` first and doubling up to ``reopen_max_s``. Raises DeviceError saying
        so until it is back; the force then ramps back over ``ramp_s``. Servo loop thread."""
        reason = self.lost
        now = self._clock()
        if self._lib is not None:  # first call since it was lost: release the session
            self._release()
            self._flush_messages()
            self._lost_at = now
            self._backoff = self.config.reopen_first_s
            self._next_try = now + self._backoff
            log.warning("touchx: device lost: %s; the servo callback stopped and the device is "
                        "released (force off); re-initialising in %.1f s", reason,
                        self._backoff)  # fmt: skip
        if now >= self._next_try:
            self.reopen_attempts += 1
            try:
                self.open()
            except Exception as exc:  # noqa: BLE001 - a failed attempt whatever it raised
                self._backoff = min(max(2.0 * self._backoff, 1e-3), self.config.reopen_max_s)
                self._next_try = now + self._backoff
                if self.reopen_attempts <= 3 or self.reopen_attempts % 10 == 0:
                    log.warning("touchx: re-initialising failed (attempt %d): %s; next in %.1f s",
                                self.reopen_attempts, exc, self._backoff)  # fmt: skip
            else:
                log.warning("touchx: device re-initialised after %.1f s (%d attempts); force "
                            "ramps back over %.1f s", now - self._lost_at, self.reopen_attempts,
                            self.config.ramp_s)  # fmt: skip
                self.reinits += 1
                self.reopen_attempts = 0
                with self._lock:
                    self.lost = None
                return
        raise DeviceError(
            f"touchx: device lost ({reason}); re-initialising: attempt {self.reopen_attempts}, "
            f"next in {max(0.0, self._next_try - now):.1f} s"
        )

    def _say(self, msg: str, *args: object) -> None:
        """Queue a warning from the HD servo thread (no I/O in the callback); ``read`` logs it."""
        if len(self._messages) < 100:
            self._messages.append((msg, args))

    def _flush_messages(self) -> None:
        while self._messages:
            msg, args = self._messages.pop(0)
            log.warning(msg, *args)

    def _raise_if_error(self, what: str) -> None:
        err = self._lib.hdGetError()  # type: ignore[union-attr]
        if err.errorCode != HD_SUCCESS:
            self._drain_errors()
            raise DeviceError(
                f"touchx: {describe_hd_error(err.errorCode, err.internalErrorCode)} while {what}"
            )

    def _drain_errors(self, limit: int = 16) -> list[tuple[int, int]]:
        """Pop HD's error stack (most recent first); the (code, internal) pairs."""
        out = []
        for _ in range(limit):
            err = self._lib.hdGetError()  # type: ignore[union-attr]
            if err.errorCode == HD_SUCCESS:
                break
            out.append((int(err.errorCode), int(err.internalErrorCode)))
        return out

    # ------------------------------------------------------------------ HD servo thread
    def _servo_tick(self, _data: int | None) -> int:
        """One HD scheduler tick (HD servo thread, 1 kHz). Never raises into C."""
        try:
            return self._tick()
        except Exception as exc:  # noqa: BLE001 - an exception must not kill the servo thread
            with self._lock:
                self._error = f"servo callback failed: {exc!r}"
                self._force = (0.0, 0.0, 0.0)
            if self._in_frame and self._lib is not None:  # close it with zero force
                self._in_frame = False
                try:
                    self._out[0] = self._out[1] = self._out[2] = 0.0
                    self._lib.hdSetDoublev(HD_CURRENT_FORCE, self._out)
                    self._lib.hdEndFrame(self._hhd)
                except Exception:  # noqa: BLE001 - nothing more to do from here
                    pass
            return HD_CALLBACK_CONTINUE

    def _tick(self) -> int:
        lib, hhd = self._lib, self._hhd
        if lib is None or hhd is None:
            return HD_CALLBACK_DONE
        if self._thread_setup:
            self._setup_thread()
        t = time.monotonic()
        self.timing.enter(t)
        now = self.ticks * self._dt  # servo time (s): ramps and waits count ticks
        lib.hdBeginFrame(hhd)
        self._in_frame = True
        lib.hdGetDoublev(HD_CURRENT_TRANSFORM, self._m)
        lib.hdGetDoublev(HD_CURRENT_VELOCITY, self._v)
        lib.hdGetIntegerv(HD_CURRENT_BUTTONS, ctypes.byref(self._buttons))
        if self._n_motors:
            lib.hdGetDoublev(HD_MOTOR_TEMPERATURE, self._temps)
        cal = lib.hdCheckCalibration()
        errors = self._drain_errors()  # raised since the last tick (the scheduler's own)
        if errors:
            self._handle_errors(errors, now)
        with self._lock:
            cmd = self._force if self._error is None and not self._stop_cb else (0.0, 0.0, 0.0)
        out = self._out
        out[0], out[1], out[2] = self._limited(cmd, cal == HD_CALIBRATION_OK, now)
        lib.hdSetDoublev(HD_CURRENT_FORCE, out)
        lib.hdEndFrame(hhd)
        self._in_frame = False
        if cal == HD_CALIBRATION_NEEDS_UPDATE:
            self._update_calibration(now)
        errors = self._drain_errors()  # raised by this tick's frame
        if errors:
            self._handle_errors(errors, now)
        state = self._make_state(t)
        calibration = CALIBRATION_NAMES.get(cal, f"unknown 0x{cal:04x}")
        with self._cv:
            self.ticks += 1
            if calibration != self.calibration:
                self._calibration_changed(calibration)
            self._state = state
            self._cv.notify_all()
        self.timing.done(lib.hdGetSchedulerTimeStamp())
        # A scheduler error: stop, as OpenHaptics' examples do; read() re-initialises.
        return HD_CALLBACK_DONE if self._stop_cb else HD_CALLBACK_CONTINUE

    def _setup_thread(self) -> None:
        """Give the HD servo thread (the caller: the first tick) SCHED_FIFO at
        ``thread_priority`` and read its policy back. OpenHaptics starts the thread in the Touch
        driver (``startServoLoop``), whose policy the caller cannot see or set beforehand: a
        SCHED_FIFO set earlier on another thread reaches it only if the driver lets it inherit.
        On Linux ``sched_setscheduler(0, ...)`` acts on the calling thread alone."""
        self._thread_setup = False
        prio, refused = self.thread_priority, ""
        if prio > 0:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
            except (OSError, AttributeError, ValueError) as exc:
                refused = f" (SCHED_FIFO {prio} refused: {exc})"
        try:
            policy, got = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
        except (OSError, AttributeError):
            policy, got = -1, 0
        fifo = policy == getattr(os, "SCHED_FIFO", 1)
        self.thread_fifo = got if fifo else 0
        self.thread_policy = f"SCHED_FIFO {got}" if fifo else f"normal priority{refused}"
        if prio > 0 and not fifo:
            self._say("touchx: the HD servo thread runs at %s", self.thread_policy)

    def _limited(self, cmd: Vec3, calibrated: bool, now: float) -> Vec3:
        """The force to write this tick (N): ``cmd`` within the adaptive clamp and the ramp;
        zero while not calibrated. HD servo thread only.

        The clamp is OpenHaptics' PreventWarmMotors: when the motors get hot it starts at the
        force then commanded and decays by 0.1 % a tick to the continuous rating; when they are
        cool again it grows by 0.1 % a tick back to the peak. "Hot" is the device's own motor
        temperature above 0.7 (below 0.5: cool), or the thermal budget: ``heat`` (|F|^2
        low-passed over ``thermal_time_constant_s``) above half the continuous rating squared
        (cool below a quarter). A sustained press so settles at the continuous rating, where
        ``heat`` stays at its square, and a peak passes for a fraction of a second.
        """
        dt, peak, cont = self._dt, self.force_limit_n, self.continuous_force_n
        temp = None
        if self._n_motors:
            t = max(self._temps[i] for i in range(self._n_motors))
            temp = self.temperature = t if math.isfinite(t) else None
        c2 = cont * cont
        hot_temp = temp is not None and temp > TEMP_RAMP_DOWN_ON
        if not self._hot and (hot_temp or self._heat > BUDGET_ON * c2):
            self._hot = True
            cx, cy, cz = cmd
            self._clamp = min(self._clamp, max(cont, math.sqrt(cx * cx + cy * cy + cz * cz)))
            if hot_temp and not self._hot_said:
                self._hot_said = True
                self._say("touchx: motors at %.0f %% of their limit: force limited toward the "
                          "continuous %.2f N", 100 * temp, cont)  # fmt: skip
        elif (
            self._hot
            and self._heat < BUDGET_OFF * c2
            and (temp is None or temp < TEMP_RAMP_DOWN_OFF)
        ):
            self._hot = self._hot_said = False
        if self._hot:
            self._clamp = max(cont, self._clamp * TEMP_DOWN_RATE)
        else:
            self._clamp = min(peak, self._clamp * TEMP_UP_RATE)
        if self.warm_motors and self._cooled(now):
            self.warm_motors = False
            self._say("touchx: motors cooled; force ramps back over %.1f s", self.config.ramp_s)
        if not calibrated:
            self._scale = 0.0
        elif self.warm_motors:
            self._scale = max(0.0, self._scale - dt / self.config.warm_ramp_s)
        elif self._scale < 1.0:
            ramp = self.config.ramp_s
            self._scale = 1.0 if ramp <= 0.0 else min(1.0, self._scale + dt / ramp)
        # 1 ppb under: the rounding of the clamp must not cross the device's own max force check
        limit = min(self._clamp, peak) * (1.0 - 1e-9)
        self.limit_n = limit
        fx, fy, fz = _safe_force(cmd, limit)
        s = self._scale
        fx, fy, fz = fx * s, fy * s, fz * s
        alpha = min(1.0, dt / self.config.thermal_time_constant_s)
        self._heat += alpha * (fx * fx + fy * fy + fz * fz - self._heat)
        return (fx, fy, fz)

    def _handle_errors(self, errors: list[tuple[int, int]], now: float) -> None:
        """HD_WARM_MOTORS ramps the force off (:meth:`_warm`); a scheduler error
        (``HD_SCHEDULER_ERRORS``: OpenHaptics' ``hduIsSchedulerError``) marks the device lost:
        this tick writes zero force and the callback stops (``HD_CALLBACK_DONE``, as
        HelloHapticDevice.c), :meth:`read` re-initialises it; any other error is reported by the
        next ``read`` and drops the commanded force."""
        for code, internal in errors:
            if code == HD_WARM_MOTORS:
                self._warm(now)
                continue
            with self._lock:
                self.errors += 1
                self._error = describe_hd_error(code, internal)
                self._force = (0.0, 0.0, 0.0)
                if code in HD_SCHEDULER_ERRORS:
                    self._stop_cb = True
                    if self.lost is None:
                        self.lost = self._error

    def _warm(self, now: float) -> None:
        if not self.warm_motors:
            self._say(
                "touchx: HD_WARM_MOTORS: the motors are too warm; force ramps down to zero over "
                "%.1f s and stays off until they cool", self.config.warm_ramp_s,
            )  # fmt: skip
        self.warm_motors = True
        self._warm_last = now

    def _cooled(self, now: float) -> bool:
        since = now - self._warm_last
        if self._n_motors and self.temperature is not None:
            return since > 1.0 and self.temperature < TEMP_RAMP_DOWN_OFF
        return since > self.config.warm_cooldown_s

    def _update_calibration(self, now: float) -> None:
        """``hdUpdateCalibration`` with the chosen style, outside the frame (as OpenHaptics'
        Calibration example), at most every 0.1 s; never ENCODER_RESET (:mod:`.touchx_reset`)."""
        style = self.calibration_style
        if style in (0, HD_CALIBRATION_ENCODER_RESET):
            return
        if now - self._last_update < CALIBRATION_UPDATE_EVERY_S:
            return
        self._last_update = now
        self._lib.hdUpdateCalibration(style)  # type: ignore[union-attr]

    def _calibration_changed(self, calibration: str) -> None:
        prev, self.calibration = self.calibration, calibration
        style = self.calibration_style
        inkwell = bool(self.calibration_styles & HD_CALIBRATION_INKWELL)
        if calibration == "ok":
            if prev != "unknown":
                self._say("touchx: calibrated; force ramps back over %.1f s (the position may "
                            "have jumped)", self.config.ramp_s)  # fmt: skip
        elif style == HD_CALIBRATION_ENCODER_RESET:
            self._say(
                "touchx: calibration %s: hold the arm at its reset pose and run `python -m "
                "humantele.haptics.devices.touchx_reset` with the servo stopped "
                "(force off until then)", calibration,
            )  # fmt: skip
        elif calibration == "needs_manual_input" and inkwell:
            self._say("touchx: calibration needed: put the stylus in the inkwell (force off)")
        elif calibration == "needs_manual_input":
            self._say("touchx: calibration needs manual input (force off until ok); run "
                        "Touch_Diagnostic to calibrate")  # fmt: skip
        else:
            self._say("touchx: calibration %s (%s; force off until ok)", calibration,
                        STYLE_NAMES.get(style, "no supported style"))  # fmt: skip

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

"""One servo tick without timing: device state in, ellipsoid force and the tick's sample out.

Frames: the device frame of :mod:`humantele.haptics.devices` (x right, y up, z toward the user);
the patient frame the model is given in (the expert's: :mod:`humantele.expert.mapping`).
``T_patient_device`` maps device points into the patient frame, with optional motion scaling
``s``: ``p_patient = R (s p_device) + t``. The force is computed in the patient frame and
rotated back into the device frame (unscaled). Each tick's sample carries the stylus both as
the device read it and in the patient frame the force law used.

Safety: the force crossfades over ``ramp_s`` at start, after a model or registration change and
after a fault (no kick); stale device data, a device error, non-finite data or a tick later than
``late_after_s`` zero the force and set a fault flag; every command is finite and within
``force_limit_n``.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from humantele.geometry import Pose, quat_multiply_tuple
from humantele.haptics.devices import DeviceError, DeviceState
from humantele.haptics.devices.sim import ManualClock, SimTouchX
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.haptics.servo_config import ServoConfig

log = logging.getLogger(__name__)

# Fault flags (bitmask in ServoSample.fault_flags).
FAULT_STALE = 1  # device data older than stale_after_s
FAULT_LATE = 2  # a tick started more than late_after_s after its deadline
FAULT_DEVICE = 4  # the device raised (disconnect, driver error)
FAULT_BAD_DATA = 8  # non-finite or implausible (beyond 1 m, 100 m/s) device data
FAULT_MODEL = 16  # a tick failed on the model (dropped for the last good one)
FAULT_NAMES = {FAULT_STALE: "stale", FAULT_LATE: "late", FAULT_DEVICE: "device",
               FAULT_BAD_DATA: "bad_data", FAULT_MODEL: "model"}  # fmt: skip


def _rot(q: tuple[float, float, float, float]) -> tuple:
    x, y, z, w = q
    return (
        (1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
        (2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
        (2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)),
    )


def auto_registration(model: Ellipsoid | None, clearance_m: float) -> Pose:
    """Default ``T_patient_device``: origin ``clearance_m`` above the model's top at the
    xiphoid, device axes along the model's axes (identity if there is no model). The model's
    ``T_world_patient`` is its principal frame in the frame it is given in: here the patient
    frame."""
    if model is None:
        return Pose.identity()
    top = model.center + np.array([0.0, model.semi_axes[1] + clearance_m, 0.0])
    return Pose(top, model.T_world_patient.quaternion)


class _Setup:
    """A model with its registration, precomputed for the loop (pure-Python floats)."""

    __slots__ = ("model", "t", "q", "R", "scale")

    def __init__(self, model: Ellipsoid | None, T_patient_device: Pose, scale: float) -> None:
        self.model = model
        self.t = tuple(float(c) for c in T_patient_device.position)
        self.q = tuple(float(c) for c in T_patient_device.quaternion)
        self.R = _rot(self.q)
        self.scale = scale

    def to_patient(self, p: tuple, v: tuple) -> tuple[tuple, tuple]:
        R, s, t = self.R, self.scale, self.t
        pp = tuple(s * (R[i][0] * p[0] + R[i][1] * p[1] + R[i][2] * p[2]) + t[i] for i in range(3))
        vp = tuple(s * (R[i][0] * v[0] + R[i][1] * v[1] + R[i][2] * v[2]) for i in range(3))
        return pp, vp

    def to_device(self, f: tuple) -> tuple[float, float, float]:
        R = self.R
        return tuple(R[0][i] * f[0] + R[1][i] * f[1] + R[2][i] * f[2] for i in range(3))  # type: ignore[return-value]


_ZERO3 = (0.0, 0.0, 0.0)
MAX_DEVICE_COORD_M = 1.0  # a device reading farther than this from its origin is garbage
MAX_DEVICE_SPEED = 100.0  # m/s, likewise for a device's own velocity estimate
MAX_REGISTRATION_M = 10.0  # m, a device origin farther from the world origin is refused


def _plausible(state: DeviceState) -> bool:
    if any(abs(c) > MAX_DEVICE_COORD_M for c in state.position):
        return False
    if not 0.5 < sum(c * c for c in state.quaternion) < 2.0:  # not a rotation
        return False
    return state.velocity is None or all(abs(c) <= MAX_DEVICE_SPEED for c in state.velocity)


class ForceRenderer:
    """One tick of the servo, without timing: device state in, device force and sample out.

    Used by the servo process and by :func:`run_lockstep`. Not thread-safe (one loop owns it).
    ``sample`` after a tick: stylus position, quaternion and velocity (patient frame), force
    (N, patient frame), force sent (N, device frame), depth (m), buttons, fault flags, ramp
    (0-1), and the stylus position and quaternion as the device read them (device frame).
    """

    def __init__(self, config: ServoConfig) -> None:
        self.config = config
        self.kp, self.kd = config.kp, config.kd
        self.limit = config.force_limit_n if config.device.spec.max_force_n > 0 else 0.0
        self._cur = _Setup(None, Pose.identity(), config.motion_scale)
        self._old: _Setup | None = None  # None = zero force (ramp in from nothing)
        self._fade_t0: float | None = None
        self._model: Ellipsoid | None = None
        self._reg: Pose | None = (
            None if config.registration is None else (config.registration.pose())
        )
        self._scale = config.motion_scale
        self._prev: DeviceState | None = None
        self._v = [0.0, 0.0, 0.0]
        self._fault_until = -math.inf
        self._faulted = False
        self._flags = 0
        self._good: Ellipsoid | None = None  # the last model a tick rendered without error
        self.counts = {"stale": 0, "device": 0, "bad_data": 0, "late": 0, "episodes": 0,
                       "nonfinite": 0, "clamped": 0, "refused": 0, "tick_errors": 0}  # fmt: skip
        self.last_refusal = ""
        self.sample = None

    @property
    def model(self) -> Ellipsoid | None:
        return self._model

    @property
    def registration(self) -> Pose | None:
        """``T_world_device`` as commanded (None: automatic)."""
        return self._reg

    @property
    def scale(self) -> float:
        return self._scale

    # -- commands ---------------------------------------------------------------------------
    def set_model(self, model: Ellipsoid | None, now: float) -> None:
        self._model = model
        self._rebuild(now)

    def set_registration(self, T_patient_device: Pose | None, scale: float, now: float) -> None:
        """``None``: automatic registration from the model."""
        self._reg = T_patient_device
        self._scale = scale
        self._rebuild(now)

    def configure(
        self, model: Ellipsoid | None, T_patient_device: Pose | None, scale: float, now: float
    ) -> None:
        """Model and registration together (one crossfade)."""
        self._model, self._reg, self._scale = model, T_patient_device, scale
        self._rebuild(now)

    def _rebuild(self, now: float) -> None:
        reg = self._reg or auto_registration(self._model, self.config.clearance_m)
        self._old = self._blend_source(now)
        self._cur = _Setup(self._model, reg, self._scale)
        self._fade_t0 = now

    def _blend_source(self, now: float) -> _Setup | None:
        # Crossfading from the middle of a crossfade: take whichever side dominates.
        if self._fade_t0 is not None and self._alpha(now) < 0.5:
            return self._old
        return self._cur if not self._faulted else None

    def _alpha(self, now: float) -> float:
        if self._fade_t0 is None:
            return 1.0
        ramp = self.config.ramp_s
        return 1.0 if ramp <= 0.0 else min(1.0, max(0.0, (now - self._fade_t0) / ramp))

    # -- one tick -------------------------------------------------------------------------
    def fault(self, flags: int, now: float) -> None:
        """Register a fault detected outside :meth:`tick` (late tick, device error)."""
        self._flags |= flags
        if flags & FAULT_LATE:
            self.counts["late"] += 1
        if flags & FAULT_DEVICE:
            self.counts["device"] += 1
        self._enter_fault(now)

    def _enter_fault(self, now: float) -> None:
        if not self._faulted:
            self.counts["episodes"] += 1
        self._faulted = True
        self._fault_until = now + self.config.fault_hold_s

    def tick(self, state: DeviceState | None, now: float, extra_flags: int = 0):
        """Force for the device (N, device frame); the tick's sample is in :attr:`sample`.

        ``state`` None means the device could not be read (the caller passes FAULT_DEVICE).
        """
        flags = extra_flags
        if state is None:
            flags |= FAULT_DEVICE
        elif not state.is_finite() or not _plausible(state):
            flags |= FAULT_BAD_DATA
            self.counts["bad_data"] += 1
        elif now - state.t > self.config.stale_after_s:
            flags |= FAULT_STALE
            self.counts["stale"] += 1
        if flags:
            self._enter_fault(now)
        elif self._faulted and now >= self._fault_until:
            self._faulted = False  # recovered: ramp in again from zero
            self._old = None
            self._fade_t0 = now
        good = state is not None and not (flags & (FAULT_BAD_DATA | FAULT_DEVICE))
        if good:
            self._update_velocity(state)
            p = state.position
        else:
            p = self._prev.position if self._prev is not None else _ZERO3
        v = tuple(self._v)
        cur = self._cur
        pp, vp = cur.to_patient(p, v)
        depth = 0.0
        f_patient = _ZERO3
        alpha = self._alpha(now)
        if not self._faulted:
            f_patient = self._force(cur, pp, vp)
            if alpha < 1.0:
                old = self._old
                f_old = self._force(old, *old.to_patient(p, v)) if old is not None else _ZERO3
                w = 1.0 - alpha
                f_patient = tuple(alpha * a + w * b for a, b in zip(f_patient, f_old, strict=True))
            elif self._fade_t0 is not None:
                self._fade_t0, self._old = None, None
        if cur.model is not None and good:
            depth = cur.model.penetration(pp, self.config.method)[0]
        f_dev = self._clamp(cur.to_device(f_patient))
        if f_dev is _ZERO3:
            f_patient = _ZERO3
        q = state.quaternion if good else (0.0, 0.0, 0.0, 1.0)
        qp = quat_multiply_tuple(cur.q, q)
        buttons = state.buttons if state is not None else 0
        if flags:
            self._flags |= flags
        elif not self._faulted:
            self._flags = 0
        ramp = 0.0 if self._faulted else alpha
        self.sample = (pp, qp, vp, f_patient, f_dev, depth, buttons, self._flags, ramp, p, q)
        return f_dev

    def refuse(self, why: str) -> None:
        """Count and log a refused model or registration command (the last good one stays)."""
        self.counts["refused"] += 1
        self.last_refusal = why
        if self.counts["refused"] <= 10:
            log.warning("servo: %s; keeping the last good one", why)

    def safe_tick(self, state: DeviceState | None, now: float, extra_flags: int = 0):
        """:meth:`tick` that never raises: a tick that fails zeroes the force, drops the model
        for the last good one (or none) and flags FAULT_MODEL; the loop goes on."""
        try:
            f = self.tick(state, now, extra_flags)
        except Exception as exc:  # noqa: BLE001 - the servo must outlive any one tick
            return self._tick_failed(exc, now)
        self._good = self._model
        return f

    def _tick_failed(self, exc: Exception, now: float) -> tuple:
        self.counts["tick_errors"] += 1
        if self.counts["tick_errors"] in (1, 10, 100, 1000):
            log.error(
                "servo: a tick failed (%d so far): %s: %s; force zeroed, model %s",
                self.counts["tick_errors"], type(exc).__name__, exc,
                "dropped" if self._model is not None else "none",
            )  # fmt: skip
        bad = self._model
        self._model = self._good if self._good is not bad else None
        self._good = self._model
        self._enter_fault(now)
        self._flags |= FAULT_MODEL
        try:
            self._rebuild(now)
        except Exception:  # noqa: BLE001 - fall back to free space
            self._model, self._reg = None, None
            self._cur = _Setup(None, Pose.identity(), self._scale)
        self._old, self._fade_t0 = None, None
        prev = self.sample
        pw, qw, vw, buttons = (prev[0], prev[1], prev[2], prev[6]) if prev else (
            _ZERO3, (0.0, 0.0, 0.0, 1.0), _ZERO3, 0)  # fmt: skip
        self.sample = (pw, qw, vw, _ZERO3, _ZERO3, 0.0, buttons, self._flags, 0.0)
        return _ZERO3

    def _force(self, setup: _Setup, pp: tuple, vp: tuple) -> tuple:
        if setup.model is None:
            return _ZERO3
        return setup.model.force(pp, vp, self.kp, self.kd, self.config.method, self.limit)

    def _clamp(self, f: tuple) -> tuple:
        fx, fy, fz = f
        if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
            self.counts["nonfinite"] += 1
            return _ZERO3
        n = math.sqrt(fx * fx + fy * fy + fz * fz)
        if n > self.limit:
            self.counts["clamped"] += 1
            if self.limit <= 0.0 or n == 0.0:
                return _ZERO3
            s = self.limit / n
            return (fx * s, fy * s, fz * s)
        if n == 0.0:
            return _ZERO3
        return f

    def _update_velocity(self, state: DeviceState) -> None:
        prev = self._prev
        self._prev = state
        if state.velocity is not None:
            self._v = list(state.velocity)
            return
        if prev is None:
            return
        dt = state.t - prev.t
        if dt <= 0.0:
            return
        a = dt / (dt + 1.0 / (2.0 * math.pi * self.config.velocity_cutoff_hz))
        for i in range(3):
            raw = (state.position[i] - prev.position[i]) / dt
            v = self._v[i] + a * (raw - self._v[i])
            self._v[i] = v if math.isfinite(v) else 0.0  # never let one bad sample poison it


def run_lockstep(
    config: ServoConfig,
    model: Ellipsoid | None,
    duration_s: float,
    device: SimTouchX | None = None,
) -> dict[str, np.ndarray]:
    """Simulate the servo loop on the sim device in lockstep (no process, no wall clock).

    Returns per-tick arrays: ``t`` (s), ``position`` (true device position, m, device frame),
    ``force`` (commanded, N, device frame), ``depth`` (m), ``faults``. Deterministic.
    """
    clock = ManualClock(0.0)
    dev = device or SimTouchX(config.device, clock=clock)  # type: ignore[arg-type]
    if device is not None:
        dev._clock = clock  # noqa: SLF001 - the sim reads this clock
    dev.open()
    r = ForceRenderer(config)
    r.set_model(model, 0.0)
    period = 1.0 / config.rate_hz
    n = int(round(duration_s * config.rate_hz))
    out = {k: np.zeros((n, 3)) for k in ("position", "force")}
    out.update({k: np.zeros(n) for k in ("t", "depth", "faults")})
    for k in range(n):
        clock.t = k * period
        try:
            state = dev.read()
        except DeviceError:
            state = None
        f = r.tick(state, clock.t)
        dev.command_force(f)
        out["t"][k] = clock.t
        out["position"][k] = dev.true_position
        out["force"][k] = f
        out["depth"][k] = r.sample[5]
        out["faults"][k] = r.sample[7]
    dev.close()
    return out

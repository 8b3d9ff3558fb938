"""The 1 kHz servo loop: read the device, compute the ellipsoid force, command it.

It runs in its own process (``multiprocessing`` spawn) so the daemon's Python threads never
hold its GIL; it asks for SCHED_FIFO and a CPU (falls back, logged once, when refused), sleeps
to a deadline and spins the last ``spin_s``. The daemon talks to it through three seqlocked
shared-memory blocks (:mod:`humantele.haptics.shm`): commands (model, registration, stop) in,
the latest sample and the statistics out. The servo never waits on the daemon.

Frames: the device frame of :mod:`humantele.haptics.devices` (x right, y up, z toward the user);
the world frame of the model (headset world, y up). ``T_world_device`` maps device points into
the world, with optional motion scaling ``s``: ``p_world = R (s p_device) + t``. The force is
computed in the world frame and rotated back into the device frame (unscaled).

Safety: the force crossfades over ``ramp_s`` at start, after a model or registration change and
after a fault (no kick); stale device data, a device error, non-finite data or a tick later than
``late_after_s`` zero the force and set a fault flag the daemon reads; every command is finite
and within ``force_limit_n``; SIGTERM, ``stop()`` or the parent's death end the loop with the
force zeroed. SIGINT is ignored: a terminal's Ctrl-C reaches the whole process group, and the
daemon stops the servo itself (it would otherwise see it die and restart it).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import multiprocessing as mp
import os
import signal
import threading
import time
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from humantele.config import ConfigModel, Quaternion
from humantele.geometry import Pose, quat_multiply_tuple
from humantele.haptics.devices import DeviceConfig, DeviceError, DeviceState, make_device
from humantele.haptics.devices.sim import ManualClock, SimDeviceConfig, SimTouchX
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.haptics.shm import SeqlockArray
from humantele.haptics.stability import check_passivity

log = logging.getLogger(__name__)

# Fault flags (bitmask in ServoSample.fault_flags).
FAULT_STALE = 1  # device data older than stale_after_s
FAULT_LATE = 2  # a tick started more than late_after_s after its deadline
FAULT_DEVICE = 4  # the device raised (disconnect, driver error)
FAULT_BAD_DATA = 8  # non-finite or implausible (beyond 1 m, 100 m/s) device data
FAULT_MODEL = 16  # a tick failed on the model (dropped for the last good one)
FAULT_NAMES = {FAULT_STALE: "stale", FAULT_LATE: "late", FAULT_DEVICE: "device",
               FAULT_BAD_DATA: "bad_data", FAULT_MODEL: "model"}  # fmt: skip

# Demo patient (world, m, y up): a torso 0.30 m wide whose xiphoid is 0.22 m above the bed.
DEMO_LANDMARKS = {
    "xiphoid": (0.0, 0.97, 0.0),
    "left": (0.0, 0.86, -0.15),
    "right": (0.0, 0.86, 0.15),
    "bed": (0.3, 0.75, 0.2),
}


def demo_model() -> Ellipsoid:
    """The ellipsoid of :data:`DEMO_LANDMARKS` (the demo's and the benchmark's patient)."""
    return Ellipsoid.from_landmarks(**{k: v for k, v in DEMO_LANDMARKS.items()})


Coord = Annotated[float, Field(ge=-10.0, le=10.0)]  # m, a device within 10 m of the world origin


class RegistrationConfig(ConfigModel):
    """``T_world_device``: device origin in the world (m) and rotation (x, y, z, w)."""

    position_m: tuple[Coord, Coord, Coord] = (0.0, 0.0, 0.0)
    quaternion: Quaternion = (0.0, 0.0, 0.0, 1.0)

    def pose(self) -> Pose:
        return Pose(np.array(self.position_m), np.array(self.quaternion))


class ServoConfig(ConfigModel):
    """The servo loop (``[servo]`` of configs/expert.toml). Gains in the world frame.

    ``registration`` None: automatic, the device origin ``clearance_m`` above the top of the
    model at the xiphoid, device axes along the patient's (the sonographer at the patient's
    right side, facing the patient). Gains that fail the passivity check (see
    :mod:`humantele.haptics.stability`) are refused unless ``allow_unstable_gains``.
    """

    device: DeviceConfig = Field(default_factory=SimDeviceConfig)
    rate_hz: float = Field(1000.0, ge=100.0, le=4000.0)
    kp: float = Field(300.0, ge=0.0, le=5000.0, description="N/m")
    kd: float = Field(0.1, ge=0.0, le=20.0, description="N s/m")
    force_limit_n: float = Field(3.0, ge=0.0, le=7.9)
    ramp_s: float = Field(0.2, ge=0.0, le=5.0)
    method: Literal["radial", "newton", "exact"] = "radial"
    registration: RegistrationConfig | None = None
    clearance_m: float = Field(0.03, ge=0.0, le=0.5)
    motion_scale: float = Field(1.0, gt=0.0, le=10.0)
    stale_after_s: float = Field(0.005, gt=0.0, le=1.0)
    late_after_s: float = Field(0.005, gt=0.0, le=1.0)
    fault_hold_s: float = Field(0.05, ge=0.0, le=5.0)
    velocity_cutoff_hz: float = Field(100.0, gt=0.0, le=2000.0)
    realtime_priority: int = Field(80, ge=0, le=99, description="SCHED_FIFO priority; 0 = off")
    cpu_affinity: list[int] | None = None
    spin_s: float = Field(0.0002, ge=0.0, le=0.001)
    allow_unstable_gains: bool = False

    @model_validator(mode="after")
    def _check_gains(self) -> ServoConfig:
        spec = self.device.spec
        if spec.max_force_n <= 0.0:
            return self  # no force output: nothing to destabilise
        if self.force_limit_n > spec.max_force_n:
            raise ValueError(
                f"force_limit_n {self.force_limit_n} N exceeds the device's peak force "
                f"{spec.max_force_n} N"
            )
        chk = self.passivity()
        if not chk.passive and not self.allow_unstable_gains:
            raise ValueError(
                f"kp/kd: {chk.reason}; lower kp or kd, or set allow_unstable_gains = true"
            )
        if not chk.passive:
            log.warning("servo gains are not passive: %s", chk.reason)
        return self

    def passivity(self):  # -> PassivityCheck
        spec = self.device.spec
        return check_passivity(
            self.kp,
            self.kd,
            1.0 / self.rate_hz,
            spec.damping_ns_per_m,
            spec.resolution_m,
            spec.coulomb_friction_n,
            self.motion_scale,
        )


@dataclass(frozen=True)
class ServoSample:
    """The latest tick. ``t`` monotonic s; ``pose`` T_world_stylus (m); ``velocity`` m/s and
    ``force`` N in the world frame (``force_device``: what went to the device); ``depth`` m
    (> 0 in contact); ``fault`` names of the active faults, '' when none."""

    t: float
    pose: Pose
    velocity: tuple[float, float, float]
    force: tuple[float, float, float]
    force_device: tuple[float, float, float]
    depth: float
    buttons: int
    fault_flags: int
    tick: int
    ramp: float

    @property
    def fault(self) -> str:
        return ",".join(name for bit, name in FAULT_NAMES.items() if self.fault_flags & bit)


@dataclass(frozen=True)
class ServoStats:
    """Loop statistics since start. Periods are between tick starts (us); ``overruns``: periods
    over 1.5 T (a tick slipped); ``periods_over_2t``: periods over 2 T (2 ms at 1 kHz);
    ``late_ticks``: later than late_after_s (fault)."""

    ticks: int
    elapsed_s: float
    rate_hz: float
    period_p50_us: float
    period_p99_us: float
    period_max_us: float
    overruns: int
    periods_over_2t: int
    late_ticks: int
    stale_ticks: int
    device_errors: int
    bad_data: int
    fault_episodes: int
    nonfinite_forces: int
    clamped_forces: int
    realtime: bool
    models_refused: int = 0  # models/registrations refused on arrival (the last good kept)
    tick_errors: int = 0  # ticks that raised (force zeroed, the model dropped)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


# ------------------------------------------------------------------------------- rendering
def _rot(q: tuple[float, float, float, float]) -> tuple:
    x, y, z, w = q
    return (
        (1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
        (2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
        (2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)),
    )


def auto_registration(model: Ellipsoid | None, clearance_m: float) -> Pose:
    """Default ``T_world_device``: origin ``clearance_m`` above the model's top at the xiphoid,
    device axes along the patient axes (identity if there is no model)."""
    if model is None:
        return Pose.identity()
    top = model.center + np.array([0.0, model.semi_axes[1] + clearance_m, 0.0])
    return Pose(top, model.T_world_patient.quaternion)


class _Setup:
    """A model with its registration, precomputed for the loop (pure-Python floats)."""

    __slots__ = ("model", "t", "q", "R", "scale")

    def __init__(self, model: Ellipsoid | None, T_world_device: Pose, scale: float) -> None:
        self.model = model
        self.t = tuple(float(c) for c in T_world_device.position)
        self.q = tuple(float(c) for c in T_world_device.quaternion)
        self.R = _rot(self.q)
        self.scale = scale

    def to_world(self, p: tuple, v: tuple) -> tuple[tuple, tuple]:
        R, s, t = self.R, self.scale, self.t
        pw = tuple(s * (R[i][0] * p[0] + R[i][1] * p[1] + R[i][2] * p[2]) + t[i] for i in range(3))
        vw = tuple(s * (R[i][0] * v[0] + R[i][1] * v[1] + R[i][2] * v[2]) for i in range(3))
        return pw, vw

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

    def set_registration(self, T_world_device: Pose | None, scale: float, now: float) -> None:
        """``None``: automatic registration from the model."""
        self._reg = T_world_device
        self._scale = scale
        self._rebuild(now)

    def configure(
        self, model: Ellipsoid | None, T_world_device: Pose | None, scale: float, now: float
    ) -> None:
        """Model and registration together (one crossfade)."""
        self._model, self._reg, self._scale = model, T_world_device, scale
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
        """Force for the device (N, device frame) and the world sample of this tick.

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
        pw, vw = cur.to_world(p, v)
        depth = 0.0
        f_world = _ZERO3
        alpha = self._alpha(now)
        if not self._faulted:
            f_world = self._force(cur, pw, vw)
            if alpha < 1.0:
                old = self._old
                f_old = self._force(old, *old.to_world(p, v)) if old is not None else _ZERO3
                w = 1.0 - alpha
                f_world = tuple(alpha * a + w * b for a, b in zip(f_world, f_old, strict=True))
            elif self._fade_t0 is not None:
                self._fade_t0, self._old = None, None
        if cur.model is not None and good:
            depth = cur.model.penetration(pw, self.config.method)[0]
        f_dev = self._clamp(cur.to_device(f_world))
        if f_dev is _ZERO3:
            f_world = _ZERO3
        q = state.quaternion if good else (0.0, 0.0, 0.0, 1.0)
        qw = quat_multiply_tuple(cur.q, q)
        buttons = state.buttons if state is not None else 0
        if flags:
            self._flags |= flags
        elif not self._faulted:
            self._flags = 0
        ramp = 0.0 if self._faulted else alpha
        self.sample = (pw, qw, vw, f_world, f_dev, depth, buttons, self._flags, ramp)
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

    def _force(self, setup: _Setup, pw: tuple, vw: tuple) -> tuple:
        if setup.model is None:
            return _ZERO3
        return setup.model.force(pw, vw, self.kp, self.kd, self.config.method, self.limit)

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


# ------------------------------------------------------------------------------- shared layout
# Commands (daemon -> servo).
C_MODEL_GEN, C_MODEL_ON, C_MODEL = 0, 1, 2  # model: 7 floats (Ellipsoid.as_array)
C_REG_GEN, C_REG_ON, C_REG_P, C_REG_Q, C_REG_S = 9, 10, 11, 14, 18
C_STOP = 19
CMD_LEN = 20
# Sample (servo -> daemon), written every tick.
S_T, S_P, S_Q, S_V, S_F, S_FD, S_DEPTH, S_BUTTONS, S_FAULT, S_TICK, S_RAMP = (
    0, 1, 4, 8, 11, 14, 17, 18, 19, 20, 21)  # fmt: skip
SAMPLE_LEN = 22
STAT_FIELDS = [f for f in ServoStats.__dataclass_fields__]
STATS_LEN = len(STAT_FIELDS)


class ServoError(RuntimeError):
    """The servo process could not start (the message carries the child's reason)."""


class _Timing:
    """Period statistics with O(1) work per tick (1 us histogram bins)."""

    BINS = 20000

    def __init__(self, period: float) -> None:
        self.period = period
        self.hist = np.zeros(self.BINS, dtype=np.int64)
        self.min_us = float("inf")
        self.max_us = 0.0
        self.max_at = 0
        self.ticks = 0
        self.overruns = 0
        self.t_first = None
        self.t_last = None

    def add(self, t: float) -> None:
        if self.t_last is not None:
            p_us = (t - self.t_last) * 1e6
            self.hist[min(int(p_us), self.BINS - 1)] += 1
            self.min_us = min(self.min_us, p_us)
            if p_us > self.max_us:
                self.max_us = p_us
                self.max_at = self.ticks
            if p_us > 1.5e6 * self.period:
                self.overruns += 1
        else:
            self.t_first = t
        self.t_last = t
        self.ticks += 1

    def count_over(self, seconds: float) -> int:
        """Periods longer than ``seconds``."""
        return int(self.hist[int(seconds * 1e6) :].sum())

    def percentile(self, q: float) -> float:
        """The ``q`` quantile of the periods, us: a bin's middle, kept within [min, max]."""
        total = int(self.hist.sum())
        if total == 0:
            return 0.0
        idx = int(np.searchsorted(np.cumsum(self.hist), q * total))
        return min(max(idx + 0.5, self.min_us), self.max_us)

    def rate(self) -> float:
        if self.ticks < 2:
            return 0.0
        return (self.ticks - 1) / (self.t_last - self.t_first)


def _try_realtime(config: ServoConfig) -> bool:
    ok = False
    if config.realtime_priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(config.realtime_priority))
            ok = True
        except (OSError, AttributeError) as exc:
            log.warning("servo: SCHED_FIFO refused (%s); running with normal priority", exc)
    if config.cpu_affinity:
        try:
            os.sched_setaffinity(0, config.cpu_affinity)
        except (OSError, ValueError) as exc:
            log.warning("servo: CPU affinity %s refused (%s)", config.cpu_affinity, exc)
    try:  # 1 ns timer slack: sleeps end on time (Linux prctl PR_SET_TIMERSLACK)
        import ctypes

        ctypes.CDLL(None).prctl(29, 1, 0, 0, 0)
    except (OSError, AttributeError):
        pass
    return ok


def _servo_main(config_json: str, names: tuple[str, str, str], parent_pid: int, conn) -> None:
    """Entry point of the servo process."""
    stop = {"flag": False}

    def _on_signal(signum, frame):  # noqa: ARG001
        stop["flag"] = True

    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the daemon stops us
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    cmd = SeqlockArray(CMD_LEN, names[0])
    out = SeqlockArray(SAMPLE_LEN, names[1])
    st = SeqlockArray(STATS_LEN, names[2])
    device = None
    try:
        config = ServoConfig.model_validate_json(config_json)
        device = make_device(config.device)
        device.open()
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises it
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        for b in (cmd, out, st):
            b.close()
        return
    realtime = _try_realtime(config)
    conn.send(("ready", {"realtime": realtime, "pid": os.getpid()}))
    try:
        _run(config, device, cmd, out, st, stop, parent_pid, realtime)
    finally:
        try:
            device.command_force((0.0, 0.0, 0.0))
        except Exception:  # noqa: BLE001 - closing anyway
            pass
        device.close()
        last = out.read()  # the daemon sees the zeroed force of the stopped loop
        last[S_F : S_F + 3] = 0.0
        last[S_FD : S_FD + 3] = 0.0
        last[S_RAMP] = 0.0
        out.write(last)
        for b in (cmd, out, st):
            b.close()


def _run(config, device, cmd, out, st, stop, parent_pid, realtime) -> None:
    r = ForceRenderer(config)
    period = 1.0 / config.rate_hz
    timing = _Timing(period)
    model_gen = reg_gen = -1.0
    spin = config.spin_s
    sample = np.zeros(SAMPLE_LEN)
    gc.collect()
    gc.disable()  # the loop makes no reference cycles; a GC pause would be a late tick
    clock = time.monotonic
    next_t = clock() + period
    next_stats = next_t
    # Until the first consistent read: no stop, and generations equal to "nothing applied yet"
    # (the renderer starts with no model: zero force).
    c = np.zeros(CMD_LEN)
    c[C_MODEL_GEN] = c[C_REG_GEN] = -1.0
    try:
        while not stop["flag"]:
            # Wait for the deadline: sleep, then spin the last `spin` seconds.
            delay = next_t - clock() - spin
            if delay > 0.0:
                time.sleep(delay)
            while clock() < next_t:
                pass
            now = clock()
            timing.add(now)
            flags = FAULT_LATE if now - next_t > config.late_after_s else 0
            if flags:
                r.fault(flags, now)
            # Commands from the daemon; mid-write (the daemon preempted): last tick's copy.
            c_new = cmd.try_read()
            if c_new is not None:
                c = c_new
            if c[C_STOP] != 0.0 or os.getppid() != parent_pid:
                break
            if c[C_MODEL_GEN] != model_gen or c[C_REG_GEN] != reg_gen:
                apply_commands(r, c, now)
                model_gen, reg_gen = c[C_MODEL_GEN], c[C_REG_GEN]
            # Device, force, device.
            try:
                state = device.read()
            except DeviceError:
                state = None
            f = r.safe_tick(state, now, flags)
            try:
                device.command_force(f)
            except DeviceError:
                r.fault(FAULT_DEVICE, now)
            pw, qw, vw, fw, fd, depth, buttons, fflags, ramp = r.sample
            sample[S_T] = now
            sample[S_P : S_P + 3] = pw
            sample[S_Q : S_Q + 4] = qw
            sample[S_V : S_V + 3] = vw
            sample[S_F : S_F + 3] = fw
            sample[S_FD : S_FD + 3] = fd
            sample[S_DEPTH] = depth
            sample[S_BUTTONS] = buttons
            sample[S_FAULT] = fflags
            sample[S_TICK] = timing.ticks
            sample[S_RAMP] = ramp
            out.write(sample)
            if now >= next_stats:
                st.write(_stats_row(timing, r, realtime))
                next_stats = now + 0.25
            # Next deadline; after a long stall restart the schedule instead of bursting.
            next_t += period
            if clock() > next_t + period:
                next_t = clock() + period
    finally:
        gc.enable()
        st.write(_stats_row(timing, r, realtime))


def apply_commands(r: ForceRenderer, c: np.ndarray, now: float) -> None:
    """Give ``r`` the model and registration of the command block ``c``; never raises. A model
    that is not a body (``Ellipsoid.problem``), a registration that is not a rigid pose within
    reach, or a bad scale is refused (counted, logged) and the last good value kept."""
    model = None
    if c[C_MODEL_ON]:
        try:
            model = Ellipsoid.from_array(c[C_MODEL : C_MODEL + 7])
            why = model.problem()
        except Exception as exc:  # noqa: BLE001 - ValueError expected; anything is refused
            why = str(exc)
        if why is not None:
            r.refuse(f"model refused: {why}")
            model = r.model
    reg = None
    if c[C_REG_ON]:
        p, q = c[C_REG_P : C_REG_P + 3], c[C_REG_Q : C_REG_Q + 4]
        n = float(np.sqrt(np.sum(q * q))) if np.all(np.isfinite(q)) else 0.0
        if np.all(np.isfinite(p)) and np.all(np.abs(p) <= MAX_REGISTRATION_M) and 1e-6 < n < 1e6:
            reg = Pose(p, q / n)
        else:
            r.refuse(f"registration refused: position {p.tolist()} m, quaternion {q.tolist()}")
            reg = r.registration
    scale = float(c[C_REG_S]) or r.config.motion_scale
    if not (math.isfinite(scale) and 0.0 < scale <= 10.0):
        r.refuse(f"motion scale {scale!r} refused")
        scale = r.scale
    try:
        r.configure(model, reg, scale, now)
    except Exception as exc:  # noqa: BLE001 - keep what ran
        r.refuse(f"configuration refused: {type(exc).__name__}: {exc}")


def _stats_row(timing: _Timing, r: ForceRenderer, realtime: bool) -> list[float]:
    c = r.counts
    vals = {
        "ticks": timing.ticks,
        "elapsed_s": (timing.t_last - timing.t_first) if timing.ticks > 1 else 0.0,
        "rate_hz": timing.rate(),
        "period_p50_us": timing.percentile(0.5),
        "period_p99_us": timing.percentile(0.99),
        "period_max_us": timing.max_us,
        "overruns": timing.overruns,
        "periods_over_2t": timing.count_over(2.0 * timing.period),
        "late_ticks": c["late"],
        "stale_ticks": c["stale"],
        "device_errors": c["device"],
        "bad_data": c["bad_data"],
        "fault_episodes": c["episodes"],
        "nonfinite_forces": c["nonfinite"],
        "clamped_forces": c["clamped"],
        "realtime": float(realtime),
        "models_refused": c["refused"],
        "tick_errors": c["tick_errors"],
    }
    return [float(vals[k]) for k in STAT_FIELDS]


# ------------------------------------------------------------------------------- daemon side
class ServoProcess:
    """The servo loop in its own process; the daemon's handle on it.

    ``start()`` returns once the device is open and the loop runs (ServoError otherwise);
    ``set_model``/``set_registration`` take effect atomically at the next tick (with a force
    crossfade); ``latest()``/``stats()`` never block on the loop. Use as a context manager.
    """

    def __init__(self, config: ServoConfig | None = None, model: Ellipsoid | None = None) -> None:
        self.config = config or ServoConfig()
        self._cmd_values = np.zeros(CMD_LEN)
        self._last_sample: ServoSample | None = None
        self._last_stats: ServoStats | None = None
        self._lock = threading.Lock()
        self._proc: mp.process.BaseProcess | None = None
        self._blocks: list[SeqlockArray] = []
        self.realtime = False
        self.exitcode: int | None = None  # of the last process, once stopped
        self.set_model(model)

    # -- lifecycle --------------------------------------------------------------------------
    def start(self, timeout_s: float = 30.0) -> None:
        if self._proc is not None:
            raise ServoError("servo process already started")
        self._cmd = SeqlockArray(CMD_LEN)
        self._out = SeqlockArray(SAMPLE_LEN)
        self._st = SeqlockArray(STATS_LEN)
        self._blocks = [self._cmd, self._out, self._st]
        with self._lock:
            self._cmd.write(self._cmd_values)
        ctx = mp.get_context("spawn")
        parent_conn, child_conn = ctx.Pipe(duplex=False)
        names = (self._cmd.name, self._out.name, self._st.name)
        self._proc = ctx.Process(
            target=_servo_main,
            args=(self.config.model_dump_json(), names, os.getpid(), child_conn),
            name="humantele-servo",
            daemon=True,
        )
        try:
            self._proc.start()
        except BaseException as exc:
            self._proc = None
            parent_conn.close()
            self.stop()  # frees the shared memory
            if isinstance(exc, Exception):
                raise ServoError(f"servo did not start: {type(exc).__name__}: {exc}") from exc
            raise
        child_conn.close()
        msg = None
        if parent_conn.poll(timeout_s):
            try:
                msg = parent_conn.recv()
            except EOFError:
                msg = None
        parent_conn.close()
        if msg is None or msg[0] != "ready":
            reason = msg[1] if msg else "the servo process exited or did not answer in time"
            self.stop()
            raise ServoError(f"servo did not start: {reason}")
        self.realtime = bool(msg[1]["realtime"])

    def stop(self, timeout_s: float = 3.0) -> None:
        """Stop the loop (force zeroed by the servo process) and free the shared memory."""
        proc = self._proc
        try:
            if proc is not None:
                with self._lock:
                    self._cmd_values[C_STOP] = 1.0
                    self._cmd.write(self._cmd_values)
                proc.join(timeout_s)
                if proc.is_alive():
                    proc.terminate()  # SIGTERM: the servo zeroes the force and exits
                    proc.join(timeout_s)
                if proc.is_alive():
                    proc.kill()
                    proc.join()
                self.exitcode = proc.exitcode
                self._proc = None
                with contextlib.suppress(ServoError):
                    self._final_stats = self._read_stats()
        finally:  # the shared memory is freed whatever happened above
            for b in self._blocks:
                with contextlib.suppress(OSError):
                    b.close()
                with contextlib.suppress(OSError):
                    b.unlink()
            self._blocks = []
            self._cmd_values[C_STOP] = 0.0

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    @property
    def returncode(self) -> int | None:
        """The servo process's exit code once it ended (None while it runs or before start)."""
        return self._proc.exitcode if self._proc is not None else self.exitcode

    def __enter__(self) -> ServoProcess:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- commands --------------------------------------------------------------------------
    def set_model(self, model: Ellipsoid | None) -> None:
        """Swap the patient model (None = free space) atomically, with a force crossfade."""
        arr = None if model is None else np.asarray(model.as_array(), dtype=float)
        if arr is not None and (arr.shape != (7,) or not np.all(np.isfinite(arr))):
            raise ValueError("model.as_array() must be 7 finite floats")
        with self._lock:
            v = self._cmd_values
            v[C_MODEL_GEN] += 1.0
            v[C_MODEL_ON] = 0.0 if arr is None else 1.0
            v[C_MODEL : C_MODEL + 7] = 0.0 if arr is None else arr
            self._push()

    def set_registration(self, T_world_device: Pose | None, scale: float | None = None) -> None:
        """Set ``T_world_device`` (None: automatic, above the model) and motion scaling."""
        s = self.config.motion_scale if scale is None else float(scale)
        if not (math.isfinite(s) and 0.0 < s <= 10.0):
            raise ValueError(f"motion scale must be in (0, 10], got {scale!r}")
        with self._lock:
            v = self._cmd_values
            v[C_REG_GEN] += 1.0
            v[C_REG_ON] = 0.0 if T_world_device is None else 1.0
            if T_world_device is not None:
                v[C_REG_P : C_REG_P + 3] = T_world_device.position
                v[C_REG_Q : C_REG_Q + 4] = T_world_device.quaternion
            v[C_REG_S] = s
            self._push()

    def _push(self) -> None:
        if self._blocks:
            self._cmd.write(self._cmd_values)

    # -- state -----------------------------------------------------------------------------
    def latest(self) -> ServoSample | None:
        """The latest tick's sample, or None before the first tick. If the servo died half-way
        through a write, the last sample read (its ``t`` shows its age)."""
        if not self._blocks:
            return None
        try:
            a = self._out.read()
        except TimeoutError:
            return self._last_sample
        if a[S_TICK] == 0:
            return None
        self._last_sample = ServoSample(
            t=float(a[S_T]),
            pose=Pose(a[S_P : S_P + 3], a[S_Q : S_Q + 4]),
            velocity=tuple(float(x) for x in a[S_V : S_V + 3]),  # type: ignore[arg-type]
            force=tuple(float(x) for x in a[S_F : S_F + 3]),  # type: ignore[arg-type]
            force_device=tuple(float(x) for x in a[S_FD : S_FD + 3]),  # type: ignore[arg-type]
            depth=float(a[S_DEPTH]),
            buttons=int(a[S_BUTTONS]),
            fault_flags=int(a[S_FAULT]),
            tick=int(a[S_TICK]),
            ramp=float(a[S_RAMP]),
        )
        return self._last_sample

    def _read_stats(self) -> ServoStats:
        try:
            a = self._st.read()
        except TimeoutError:  # the servo died half-way through a write: the last we read
            if self._last_stats is None:
                raise ServoError("servo statistics unreadable") from None
            return self._last_stats
        vals: dict[str, Any] = {}
        for k, x in zip(STAT_FIELDS, a, strict=True):
            ftype = ServoStats.__dataclass_fields__[k].type
            vals[k] = bool(x) if ftype == "bool" else int(x) if ftype == "int" else float(x)
        self._last_stats = ServoStats(**vals)
        return self._last_stats

    def stats(self) -> ServoStats:
        """Loop statistics (updated 4 times a second, and at stop)."""
        if not self._blocks:
            final = getattr(self, "_final_stats", None)
            if final is None:
                raise ServoError("servo process not started")
            return final
        return self._read_stats()

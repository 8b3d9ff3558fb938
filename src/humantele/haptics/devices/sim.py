"""A simulated Touch X held by a simulated sonographer's hand.

Dynamics (device frame, see ``base``): the stylus tip is a point mass ``spec.mass_kg`` with the
device's viscous damping and Coulomb friction, mechanical stops at the workspace box, the
commanded force held between commands (zero-order hold, clamped to the peak force), and a hand:
a spring-damper pulling toward a scripted target (a scan of the epigastric region: hover, press
into the patient, sweep, lift off) plus a seeded physiological tremor. Integrated with
semi-implicit Euler at ``sim_rate_hz`` (>= 1 kHz), so the rendered force acts back on the motion.
Readings are quantized to the encoder resolution. Deterministic for a seed and a clock.

The simulation runs on a clock: by default ``time.monotonic`` (real time, for the servo
process); tests and the stability analysis pass a :class:`ManualClock` and step it.
"""

from __future__ import annotations

import math
import random
import time
from collections.abc import Callable
from typing import Literal

from pydantic import Field

from humantele.config import ConfigModel
from humantele.haptics.devices.base import (
    DeviceError,
    DeviceSpec,
    DeviceState,
    HapticDevice,
    Quat,
    Vec3,
    safe_force,
)

STOP_STIFFNESS = 2000.0  # N/m, the mechanical stops at the workspace edge
STOP_DAMPING = 2.0  # N s/m
FRICTION_V_EPS = 1e-4  # m/s, below this the tip sticks unless the force beats friction


class ManualClock:
    """A clock a test advances by hand: ``clock()`` returns ``clock.t`` (s)."""

    def __init__(self, t: float = 0.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class SimHandConfig(ConfigModel):
    """The simulated sonographer's hand (device frame, metres).

    ``path``: ``scan`` (the scripted scan) or ``hold`` (a fixed target, ``hold_target_m``).
    The scan assumes the patient's surface is ``surface_below_m`` under the device origin (the
    default registration of the servo loop puts it there) and sends the hand target
    ``press_depth_m`` below the surface while sweeping ``sweep_m`` either side (device z).
    The default grip is light (low damping): the hard case for stability.
    """

    stiffness_n_per_m: float = Field(150.0, ge=0.0, le=5000.0)
    damping_ns_per_m: float = Field(0.2, ge=0.0, le=100.0)
    path: Literal["scan", "hold"] = "scan"
    hold_target_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    surface_below_m: float = Field(0.03, ge=0.0, le=0.06)
    press_depth_m: float = Field(0.015, ge=0.0, le=0.05)
    sweep_m: float = Field(0.04, ge=0.0, le=0.08)
    cycle_s: float = Field(10.0, gt=1.0, le=600.0)
    tremor_n: float = Field(0.02, ge=0.0, le=1.0)


class SimFault(ConfigModel):
    """An injected fault: from ``start_s`` after open, for ``duration_s``.

    ``stale``: readings stop updating (same sample repeated); ``disconnect``: ``read()`` raises
    DeviceError; ``nan``: readings carry NaN positions (garbled sensor data).
    """

    kind: Literal["stale", "disconnect", "nan"]
    start_s: float = Field(ge=0.0)
    duration_s: float = Field(gt=0.0)


class SimDeviceConfig(ConfigModel):
    """The ``sim`` backend: a simulated Touch X (``spec``) driven by a simulated hand."""

    backend: Literal["sim"] = "sim"
    seed: int = 0
    sim_rate_hz: float = Field(5000.0, ge=1000.0, le=100000.0)
    spec: DeviceSpec = DeviceSpec()
    hand: SimHandConfig = SimHandConfig()
    faults: list[SimFault] = []
    start_position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


def _smoothstep(u: float) -> float:
    u = min(1.0, max(0.0, u))
    return u * u * (3.0 - 2.0 * u)


def scan_target(hand: SimHandConfig, t: float) -> tuple[Vec3, Quat]:
    """Hand target (m, device frame) and stylus orientation of the scripted scan at time t (s).

    One cycle: hover, descend onto the patient, press while sweeping side to side (x) and a
    little along the body (z), lift off, hover back.
    """
    if hand.path == "hold":
        return tuple(hand.hold_target_m), (0.0, 0.0, 0.0, 1.0)  # type: ignore[return-value]
    u = (t % hand.cycle_s) / hand.cycle_s
    hover = -hand.surface_below_m + 0.015
    press = -hand.surface_below_m - hand.press_depth_m
    if u < 0.1:
        y = hover
    elif u < 0.2:
        y = hover + (press - hover) * _smoothstep((u - 0.1) / 0.1)
    elif u < 0.8:
        y = press
    elif u < 0.9:
        y = press + (hover - press) * _smoothstep((u - 0.8) / 0.1)
    else:
        y = hover
    # Sweep across the body (device z, the patient's lateral axis with the default
    # registration): one full side-to-side period while pressed, zero at its ends; a slow
    # drift along the body (device x).
    s = math.sin(2.0 * math.pi * (u - 0.2) / 0.6) if 0.2 <= u < 0.8 else 0.0
    z = hand.sweep_m * s
    x = 0.3 * hand.sweep_m * (1.0 - math.cos(2.0 * math.pi * u)) * 0.5
    # The stylus tilts with the sweep (about the device x axis), at most ~15 degrees.
    half = -0.5 * math.radians(15.0) * s
    return (x, y, z), (math.sin(half), 0.0, 0.0, math.cos(half))


class SimTouchX(HapticDevice):
    """The simulated Touch X; see the module docstring. ``clock`` returns seconds."""

    name = "sim"
    has_force = True

    def __init__(
        self,
        config: SimDeviceConfig | None = None,
        clock: Callable[[], float] | None = None,
        script: Callable[[float], tuple[Vec3, Quat]] | None = None,
    ) -> None:
        self.config = config or SimDeviceConfig()
        self.spec = self.config.spec
        self._clock = clock or time.monotonic
        self._script = script or (lambda t: scan_target(self.config.hand, t))
        self._dt = 1.0 / self.config.sim_rate_hz
        self._open = False
        self.reset()

    def reset(self) -> None:
        """Back to the start position at rest, zero force, fresh random generator."""
        self._rng = random.Random(self.config.seed)
        self._tremor_phase = [self._rng.uniform(0.0, 2.0 * math.pi) for _ in range(3)]
        self._tremor_hz = self._rng.uniform(8.0, 12.0)
        self._p = list(self.config.start_position_m)
        self._v = [0.0, 0.0, 0.0]
        self._f_cmd = (0.0, 0.0, 0.0)
        self._t0 = 0.0
        self._t = 0.0  # simulated time since open (s)
        self._last: DeviceState | None = None
        self.commands = 0

    # -- interface -------------------------------------------------------------------------
    def open(self) -> None:
        self.reset()
        self._t0 = self._clock()
        self._open = True

    def close(self) -> None:
        self._f_cmd = (0.0, 0.0, 0.0)
        self._open = False

    def read(self) -> DeviceState:
        if not self._open:
            raise DeviceError("sim device is not open")
        self.advance_to(self._clock())
        fault = self._fault_at(self._t)
        if fault == "disconnect":
            raise DeviceError("sim device disconnected (injected fault)")
        if fault == "stale" and self._last is not None:
            return self._last
        q = self.spec.resolution_m
        pos = tuple(round(c / q) * q for c in self._p)
        if fault == "nan":
            pos = (math.nan, math.nan, math.nan)
        _, quat = self._script(self._t)
        state = DeviceState(self._t0 + self._t, pos, quat, 0, None)  # type: ignore[arg-type]
        self._last = state
        return state

    def command_force(self, force: Vec3) -> None:
        self._f_cmd = safe_force(force, self.spec.max_force_n)
        self.commands += 1

    # -- simulation ------------------------------------------------------------------------
    @property
    def true_position(self) -> Vec3:
        """The unquantized tip position (m, device frame), for tests and analysis."""
        return tuple(self._p)  # type: ignore[return-value]

    @property
    def true_velocity(self) -> Vec3:
        return tuple(self._v)  # type: ignore[return-value]

    @property
    def applied_force(self) -> Vec3:
        """The force the motors apply now (N, device frame): the last command, clamped."""
        return self._f_cmd

    def advance_to(self, t_clock: float) -> None:
        """Integrate the dynamics up to clock time ``t_clock`` in fixed steps (at most 0.1 s)."""
        target = min(t_clock - self._t0, self._t + 0.1)
        while self._t + self._dt <= target + 1e-12:
            self._step(self._dt)

    def _fault_at(self, t: float) -> str | None:
        for f in self.config.faults:
            if f.start_s <= t < f.start_s + f.duration_s:
                return f.kind
        return None

    def _step(self, dt: float) -> None:
        spec, hand = self.spec, self.config.hand
        t = self._t
        (tx, ty, tz), _ = self._script(t)
        (tx2, ty2, tz2), _ = self._script(t + dt)
        target = (tx, ty, tz)
        target_v = ((tx2 - tx) / dt, (ty2 - ty) / dt, (tz2 - tz) / dt)
        tremor = hand.tremor_n
        w = 2.0 * math.pi * self._tremor_hz * t
        half = (spec.workspace_m[0] / 2, spec.workspace_m[1] / 2, spec.workspace_m[2] / 2)
        m = spec.mass_kg
        for i in range(3):
            p, v = self._p[i], self._v[i]
            f = self._f_cmd[i]
            f += hand.stiffness_n_per_m * (target[i] - p)
            f += hand.damping_ns_per_m * (target_v[i] - v)
            f += tremor * math.sin(w + self._tremor_phase[i])
            f -= spec.damping_ns_per_m * v
            if p > half[i]:
                f -= STOP_STIFFNESS * (p - half[i]) + STOP_DAMPING * v
            elif p < -half[i]:
                f -= STOP_STIFFNESS * (p + half[i]) + STOP_DAMPING * v
            # Coulomb friction, Karnopp's stick-slip model (per axis).
            fc = spec.coulomb_friction_n
            if abs(v) < FRICTION_V_EPS and abs(f) <= fc:
                v = 0.0
            else:
                f -= fc if (v > 0.0 or (v == 0.0 and f > 0.0)) else -fc
                v_new = v + f / m * dt
                v = 0.0 if v != 0.0 and (v_new > 0.0) != (v > 0.0) else v_new
            self._v[i] = v
            self._p[i] = p + v * dt
        self._t = t + dt

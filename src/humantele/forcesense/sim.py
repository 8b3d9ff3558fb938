"""Simulated force sensor board: true force -> Hall readings with noise, drift and hysteresis.

Drift: each pair's two sensors share a common-mode term (Hall offset drift with a slowly
varying temperature, and an outside field such as the Earth's or a nearby steel bed, which
turns with the probe), which the differential signal cancels; a small per-sensor offset and a
gain mismatch are fixed (the calibration absorbs them). Deterministic by seed.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from humantele.forcesense.base import ForceSensor
from humantele.forcesense.model import SensorModel
from humantele.forcesense.readings import ForceReading
from humantele.forcesense.sim_config import SimForceConfig


class SimForceSensor(ForceSensor):
    """``set_force`` (probe frame, N), then ``read(t)`` gives a :class:`ForceReading`."""

    name = "sim force sensor"

    def __init__(self, config: SimForceConfig | None = None):
        self.config = c = config or SimForceConfig()
        self.model = SensorModel(c.geometry)
        rng = np.random.default_rng(c.seed)
        p = self.model.n_pairs
        self._off = rng.normal(0.0, c.offset_mt, (2, p))
        self._gain = 1.0 + rng.normal(0.0, c.gain_mismatch, (2, p))
        self._rng = np.random.default_rng(c.seed + 1)
        self._phase = rng.uniform(0, 2 * math.pi, 3)
        self.force = np.zeros(3)
        self._seq = 0

    def set_force(self, force_probe: ArrayLike) -> None:
        """True force on the shell, probe frame, N."""
        self.force = np.asarray(force_probe, dtype=float).reshape(3)

    def common_mode(self, t: float) -> np.ndarray:
        """(P,) common-mode field in mT at time t: temperature offset drift + outside field."""
        c = self.config
        temp = c.temp_swing_c * math.sin(2 * math.pi * t / c.temp_period_s + self._phase[0])
        ext_dir = np.array(
            [math.cos(t / 7.0 + self._phase[1]), math.sin(t / 11.0 + self._phase[2]), 0.5]
        )
        ext = c.outside_field_mt * ext_dir / np.linalg.norm(ext_dir)
        return c.offset_tempco_mt_per_c * temp + self.model.axes @ ext

    def temperature(self, t: float) -> float:
        c = self.config
        return 25.0 + c.temp_swing_c * math.sin(2 * math.pi * t / c.temp_period_s + self._phase[0])

    def read(self, t: float | None = None) -> ForceReading:
        c = self.config
        t = self._seq / c.rate_hz if t is None else t
        a, b = self.model.fields(self.model.displacement(self.force))
        cm = self.common_mode(t)
        noise = self._rng.normal(0.0, c.noise_mt, (2, self.model.n_pairs))
        ra = self._gain[0] * (a + cm) + self._off[0] + noise[0]
        rb = self._gain[1] * (b + cm) + self._off[1] + noise[1]
        self._seq += 1
        return ForceReading(t, ra, rb, self.temperature(t), self._seq & 0xFFFF)

    def open(self) -> None:
        """Nothing to open: the simulated board is ready when made."""

    def close(self) -> None:
        pass

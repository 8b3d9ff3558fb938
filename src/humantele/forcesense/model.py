"""Physics of the sensor: a shell on a silicone suspension carries small magnets; on the probe,
a pair of Hall-effect sensors faces each magnet, one on each side along the pair's axis.

Force on the shell (probe frame, N) -> shell displacement (suspension compliance, with the
hysteresis of silicone as a play operator) -> field at each sensor (point dipoles, mT). The
two sensors of a pair see the same outside field and the same temperature offset, so their
difference cancels that common mode, while the magnet's field changes in opposite directions.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, field_validator

from humantele.config import ConfigModel

MU0_4PI = 1e-7  # T m / A


class SensorGeometry(ConfigModel):
    """Pairs (positions on the probe, m; axes, unit) and the magnets and suspension."""

    pair_positions_m: list[list[float]] = Field(
        default_factory=lambda: [
            [0.018, 0.0, 0.0],
            [0.0, 0.012, 0.0],
            [-0.018, 0.0, 0.004],
        ],
        description="centre of each pair (magnet rest position) on the probe, m",
    )
    pair_axes: list[list[float]] = Field(
        default_factory=lambda: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        description="axis of each pair (sensor a on +axis side), probe frame",
    )
    gap_m: float = Field(0.003, gt=0, description="magnet to each sensor at rest")
    magnet_moment_am2: float = Field(3e-3, gt=0)
    stiffness_n_per_m: list[float] = Field(
        default_factory=lambda: [40000.0, 40000.0, 60000.0],
        description="suspension stiffness along probe x, y, z",
    )
    hysteresis_n: float = Field(0.06, ge=0, description="play width of the silicone, N")

    @field_validator("pair_positions_m", "pair_axes")
    @classmethod
    def _vecs(cls, v: list[list[float]]) -> list[list[float]]:
        if not 3 <= len(v) <= 6 or any(len(p) != 3 for p in v):
            raise ValueError("need 3 to 6 pairs of 3 numbers each")
        return v

    @field_validator("stiffness_n_per_m")
    @classmethod
    def _stiff(cls, v: list[float]) -> list[float]:
        if len(v) != 3 or min(v) <= 0:
            raise ValueError("need 3 positive stiffnesses (x, y, z)")
        return v


def dipole_field(moment: NDArray, r: NDArray) -> NDArray:
    """Field (T) at offsets ``r`` (..., 3) m from point dipoles ``moment`` (..., 3) A m^2."""
    d = np.linalg.norm(r, axis=-1, keepdims=True)
    rh = r / d
    return MU0_4PI * (3.0 * np.sum(moment * rh, -1, keepdims=True) * rh - moment) / d**3


class SensorModel:
    """Force (probe frame, N) -> noiseless (a, b) readings in mT, with suspension hysteresis."""

    def __init__(self, geometry: SensorGeometry | None = None):
        self.geometry = g = geometry or SensorGeometry()
        if len(g.pair_positions_m) != len(g.pair_axes):
            raise ValueError("pair_positions_m and pair_axes must have the same length")
        self.pos = np.asarray(g.pair_positions_m, dtype=float)
        ax = np.asarray(g.pair_axes, dtype=float)
        self.axes = ax / np.linalg.norm(ax, axis=1, keepdims=True)
        self.compliance = 1.0 / np.asarray(g.stiffness_n_per_m, dtype=float)
        self._play = np.zeros(3)

    @property
    def n_pairs(self) -> int:
        return len(self.pos)

    def reset(self) -> None:
        self._play[:] = 0.0

    def displacement(self, force: ArrayLike) -> NDArray[np.float64]:
        """Shell displacement (m, probe frame); advances the hysteresis state."""
        f = np.asarray(force, dtype=float)
        h = self.geometry.hysteresis_n / 2.0
        self._play = np.clip(self._play, f - h, f + h)  # play operator: lags by up to h
        return self._play * self.compliance

    def fields(self, displacement: ArrayLike) -> tuple[NDArray, NDArray]:
        """(a, b) in mT of each pair for a shell displacement (m)."""
        g = self.geometry
        mag = self.pos + np.asarray(displacement, dtype=float)
        m = self.axes * g.magnet_moment_am2
        sa = self.pos + self.axes * g.gap_m
        sb = self.pos - self.axes * g.gap_m
        a = np.sum(dipole_field(m, sa - mag) * self.axes, axis=-1) * 1e3
        b = np.sum(dipole_field(m, sb - mag) * self.axes, axis=-1) * 1e3
        return a, b

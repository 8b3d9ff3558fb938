"""One sample of the force sensor board: the Hall-effect readings of every differential pair."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class ForceReading:
    """Readings at time ``t`` (s): ``a`` and ``b`` (P,) fields in mT of each pair's two
    sensors (``a`` on the +axis side of the magnet), board temperature in deg C, sequence."""

    t: float
    a: NDArray[np.float64]
    b: NDArray[np.float64]
    temperature_c: float = 25.0
    seq: int = 0

    @property
    def differential(self) -> NDArray[np.float64]:
        """a - b per pair, mT: common-mode drift (temperature, outside fields) cancels."""
        return np.asarray(self.a, dtype=float) - np.asarray(self.b, dtype=float)

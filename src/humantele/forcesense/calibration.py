"""Calibration: differential readings -> force (probe frame, N), fitted by least squares.

Features are the monomials of the scaled differential signals up to degree 3, plus 5th powers,
which absorb the dipole fields' non-linearity and the cross-talk between pairs. A
``single_ended`` calibration (sensor ``a`` alone) is kept for comparison: it cannot cancel
common-mode drift.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from humantele.forcesense.readings import ForceReading


def _features(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, F) polynomial features of scaled signals x (N, P)."""
    n, p = x.shape
    cols = [np.ones(n)]
    for deg in (1, 2, 3):
        for idx in itertools.combinations_with_replacement(range(p), deg):
            cols.append(np.prod(x[:, idx], axis=1))
    cols += [x[:, i] ** 5 for i in range(p)]
    return np.stack(cols, axis=1)


def signals(readings: list[ForceReading] | ForceReading, single_ended: bool = False) -> NDArray:
    """(N, P) signals (mT) used by the calibration: a - b, or a alone if single_ended."""
    rs = [readings] if isinstance(readings, ForceReading) else readings
    if single_ended:
        return np.array([np.asarray(r.a, dtype=float) for r in rs])
    return np.array([r.differential for r in rs])


@dataclass
class ForceCalibration:
    """Least-squares map from signals to force. ``scale`` (P,) mT normalises the signals."""

    coef: NDArray[np.float64]  # (F, 3)
    center: NDArray[np.float64]  # (P,)
    scale: NDArray[np.float64]  # (P,)
    single_ended: bool = False
    rms_fit_n: float = float("nan")

    @classmethod
    def fit(
        cls, readings: list[ForceReading], forces: ArrayLike, single_ended: bool = False
    ) -> ForceCalibration:
        """Fit from (readings, reference force (N, 3) in N) pairs."""
        s = signals(readings, single_ended)
        f = np.asarray(forces, dtype=float).reshape(-1, 3)
        if len(s) != len(f):
            raise ValueError(f"{len(s)} readings but {len(f)} reference forces")
        center = s.mean(axis=0)
        scale = np.maximum(s.std(axis=0), 1e-9)
        a = _features((s - center) / scale)
        if len(s) < 2 * a.shape[1]:
            raise ValueError(f"need at least {2 * a.shape[1]} samples, got {len(s)}")
        coef, *_ = np.linalg.lstsq(a, f, rcond=None)
        rms = float(np.sqrt(np.mean(np.sum((a @ coef - f) ** 2, axis=1))))
        return cls(coef, center, scale, single_ended, rms)

    def force(self, readings: list[ForceReading] | ForceReading) -> NDArray[np.float64]:
        """Force (3,) for one reading or (N, 3) for a list, probe frame, N."""
        s = signals(readings, self.single_ended)
        out = _features((s - self.center) / self.scale) @ self.coef
        return out[0] if isinstance(readings, ForceReading) else out

    def save(self, path: str | Path) -> None:
        data = {
            "coef": self.coef.tolist(),
            "center": self.center.tolist(),
            "scale": self.scale.tolist(),
            "single_ended": self.single_ended,
            "rms_fit_n": self.rms_fit_n,
        }
        Path(path).write_text(json.dumps(data), encoding="utf-8")

    @classmethod
    def load(cls, path: str | Path) -> ForceCalibration:
        return cls.loads(Path(path).read_text(encoding="utf-8"))

    @classmethod
    def loads(cls, text: str) -> ForceCalibration:
        """From the JSON :meth:`save` writes (a file's, or one kept in a device recording)."""
        d = json.loads(text)
        return cls(
            np.array(d["coef"]),
            np.array(d["center"]),
            np.array(d["scale"]),
            bool(d["single_ended"]),
            float(d["rms_fit_n"]),
        )


def calibration_loads(n: int, max_force: float = 20.0, seed: int = 0) -> NDArray[np.float64]:
    """(n, 3) reference loads of a calibration run: presses in random directions up to
    ``max_force`` N, ramped up and down (so the hysteresis is seen both ways)."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        d = rng.normal(size=3)
        peak = rng.uniform(0.2, 1.0) * max_force * d / np.max(np.abs(d))
        steps = int(rng.integers(8, 20))
        ramp = np.concatenate([np.linspace(0, 1, steps), np.linspace(1, 0, steps)[1:]])
        out.extend(r * peak for r in ramp)
    return np.array(out[:n])


def calibrate_sim(sensor, n: int = 1500, seed: int = 0, reference_noise_n: float = 0.01):
    """Run a calibration on a sim sensor (reference load cell with noise); returns the fit."""
    rng = np.random.default_rng(seed + 99)
    loads = calibration_loads(n, seed=seed)
    readings = []
    for i, f in enumerate(loads):
        sensor.set_force(f)
        readings.append(sensor.read(i / 100.0))
    ref = loads + rng.normal(0, reference_noise_n, loads.shape)
    return ForceCalibration.fit(readings, ref)

"""A daemon's running figures: the JSON stats file it shares with its parent, CPU use and
latency percentiles."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np


def percentile_ms(values_s: Iterable[float], q: float) -> float | None:
    """The ``q`` percentile (0-100) of durations in seconds, in ms, rounded to 1 us; None when
    there are none. The one definition the figures use: the nearest sample (numpy's
    ``method="nearest"``), so a percentile is always a latency that was measured."""
    v = np.fromiter(values_s, dtype=float)
    if v.size == 0:
        return None
    return round(float(np.percentile(v, q, method="nearest")) * 1000.0, 3)


class CpuMeter:
    """CPU use of this process (all threads) in percent of one core since it was made."""

    def __init__(self) -> None:
        self._start_wall = time.monotonic()
        self._start_cpu = time.process_time()

    def overall(self) -> float:
        """% of one core, from the meter's making until now."""
        wall = time.monotonic() - self._start_wall
        return round(100.0 * (time.process_time() - self._start_cpu) / wall, 1) if wall > 0 else 0.0


def process_cpu_seconds(pid: int | None) -> float | None:
    """CPU time (s) used so far by process ``pid`` (Linux /proc), or None."""
    if pid is None:
        return None
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def write_stats(path: str | Path | None, stats: dict[str, Any]) -> None:
    """Atomically replace the JSON stats file a daemon shares with its parent (if any)."""
    if not path:
        return
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(stats, separators=(",", ":")), encoding="utf-8")
    os.replace(tmp, path)


def read_stats(path: str | Path) -> dict[str, Any] | None:
    """A daemon's last stats (None: not written yet, or being replaced)."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None

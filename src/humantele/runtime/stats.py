"""A daemon's running figures: the JSON stats file it shares with its parent, CPU use and
latency percentiles. Other processes' CPU is read with psutil (never on the 1 kHz path)."""

from __future__ import annotations

import bisect
import itertools
import json
import math
import os
import threading
import time
from collections import deque
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import psutil


class SortedWindow:
    """The last ``maxlen`` durations (s), kept in arrival order *and* sorted.

    A daemon reports percentiles of its latencies every 0.5 s on its event loop; sorting a
    20000-sample window there took 2-17 ms (machine-dependent) each time, a stall in the
    very loop whose latency it reports. Here adding a sample costs a bisect and a short
    memmove (microseconds), and a percentile is one index. Non-finite values are ignored.
    """

    def __init__(self, maxlen: int) -> None:
        self.maxlen = maxlen
        self._order: deque[float] = deque()
        self._sorted: list[float] = []

    def append(self, value: float) -> None:
        v = float(value)
        if not math.isfinite(v):
            return
        if len(self._order) >= self.maxlen:
            old = self._order.popleft()
            del self._sorted[bisect.bisect_left(self._sorted, old)]
        self._order.append(v)
        bisect.insort(self._sorted, v)

    def __len__(self) -> int:
        return len(self._order)

    def __iter__(self) -> Iterator[float]:
        return iter(self._order)

    def last(self, n: int) -> list[float]:
        """The ``n`` most recent values, oldest first."""
        if n <= 0:
            return []
        out = list(itertools.islice(reversed(self._order), n))
        out.reverse()
        return out

    def percentile_ms(self, q: float, ndigits: int = 3) -> float | None:
        """As :func:`percentile_ms`, in O(1)."""
        v = self._sorted
        if not v:
            return None
        k = min(len(v) - 1, max(0, round(q / 100.0 * (len(v) - 1))))
        return round(v[k] * 1000.0, ndigits)


def percentile_ms(values_s: Iterable[float], q: float, ndigits: int = 3) -> float | None:
    """The ``q`` percentile (0-100) of durations in seconds, in ms rounded to ``ndigits``
    decimals (3: 1 us); None when there are none. The one definition the figures use: the
    nearest sample (numpy's ``method="nearest"``), so a percentile is always a latency that
    was measured. A :class:`SortedWindow` answers without sorting."""
    if isinstance(values_s, SortedWindow):
        return values_s.percentile_ms(q, ndigits)
    v = np.fromiter(values_s, dtype=float)
    if v.size == 0:
        return None
    return round(float(np.percentile(v, q, method="nearest")) * 1000.0, ndigits)


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
    """CPU time (s, user + system) used so far by process ``pid``, or None (no such process,
    or not ours to read). Read by psutil, off the 1 kHz path (stats every 0.5 s)."""
    if pid is None:
        return None
    try:
        t = psutil.Process(pid).cpu_times()
    except (psutil.Error, OSError):
        return None
    return t.user + t.system


def process_cpu_percent(pid: int | None) -> float | None:
    """CPU use (% of one core) of process ``pid`` over its whole life so far, or None.

    The life is the kernel's (its start time), not the caller's idea of when the process
    started: CPU spent while it was spawning over a wall time taken from later gave 13968 %
    for a servo just restarted."""
    if pid is None:
        return None
    try:
        p = psutil.Process(pid)
        with p.oneshot():
            t = p.cpu_times()
            created = p.create_time()  # s since 1970 (boot time + start ticks)
    except (psutil.Error, OSError):
        return None
    life = max(time.time() - created, 0.01)  # create_time's resolution: a clock tick
    return round(100.0 * (t.user + t.system) / life, 1)


def _encode(stats: dict[str, Any]) -> str:
    return json.dumps(stats, separators=(",", ":"))


def _replace(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


class StatsFile:
    """The stats file of a running daemon, written without its event loop waiting on the disk.

    :meth:`write` encodes the stats on the caller's thread (the loop owns the state they are
    read from) and hands the text to one writer thread, which replaces the file atomically;
    a text not yet written when a newer one comes is dropped (counted in ``superseded``). Why:
    the write itself (a temporary file and a rename) took 0.4 ms and up to 18 ms here, on the
    loop that also carries the pose stream, every 0.5 s. :meth:`close` writes the last stats
    before it returns (the demo reads them once the daemon has exited).
    """

    def __init__(self, path: str | Path | None) -> None:
        self.path = Path(path) if path else None
        self.superseded = 0
        self.errors = 0
        self._text: str | None = None
        self._closed = False
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None

    def write(self, stats: dict[str, Any]) -> None:
        """Queue ``stats`` for the file (no-op without a path, or after :meth:`close`)."""
        if self.path is None or self._closed:
            return
        text = _encode(stats)
        with self._cond:
            if self._thread is None:
                self._thread = threading.Thread(
                    target=self._run, name="humantele-stats", daemon=True
                )
                self._thread.start()
            if self._text is not None:
                self.superseded += 1
            self._text = text
            self._cond.notify()

    def close(self, stats: dict[str, Any] | None = None) -> None:
        """Stop the writer; then write ``stats`` (if given) synchronously, as the last."""
        with self._cond:
            self._closed = True
            self._cond.notify()
        if self._thread is not None:
            self._thread.join()
        if stats is not None and self.path is not None:
            _replace(self.path, _encode(stats))

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._text is None and not self._closed:
                    self._cond.wait()
                text, self._text = self._text, None
            if text is None:  # closed, nothing pending
                return
            try:
                _replace(self.path, text)  # type: ignore[arg-type]
            except OSError:
                self.errors += 1  # a full disk must not end the daemon; the next write retries


def read_stats(path: str | Path) -> dict[str, Any] | None:
    """A daemon's last stats (None: not written yet, or being replaced)."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None

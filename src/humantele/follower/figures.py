"""The follower's running figures: the expert's pose stream as it arrives (rate, age; its
latency and how long the virtual probe was stale recorded about once a second), the
alignment error of the real probe to the virtual one while following, and how late the
daemon's ticks come."""

from __future__ import annotations

import bisect
import math
from collections import deque
from typing import Any

import numpy as np

from humantele.geometry import Pose
from humantele.runtime.stats import SortedWindow, percentile_ms

REPORT_PERIOD_S = 1.0  # the pose stream's latency is recorded this often
ALIGN_KEPT = 3000  # alignment errors the RMS is over (the last ~65 s of 45 Hz frames)


RECENT_POSES = 1000  # the recent pose ages' window (10 s of the expert's 100 Hz stream)


class PoseStreamFigures:
    """Arrival times (s, monotonic) and one-way ages (s) of the expert's poses."""

    def __init__(self) -> None:
        self.received = 0
        self.ages = SortedWindow(20000)  # percentiles without sorting on the loop
        self.times: deque[float] = deque(maxlen=2000)
        self._reported = 0
        self._last_report = -math.inf
        self.stale_s = 0.0  # s the virtual probe was stale since the last report (calibrated)
        self._judged = False  # staleness judged since the last report (a calibration exists)
        self._tick_t: float | None = None

    def add(self, t_rx: float, age_s: float | None) -> None:
        self.received += 1
        self.times.append(t_rx)
        if age_s is not None and math.isfinite(age_s):
            self.ages.append(max(0.0, age_s))

    def rate_hz(self, now: float, window_s: float = 1.0) -> float:
        """Poses received per second over the last ``window_s``."""
        recent = len(self.times) - bisect.bisect_left(self.times, now - window_s)
        return round(recent / window_s, 1)

    def median_since_last(self) -> float | None:
        """The median age (s) of the poses since the last call, None if none came."""
        new = min(len(self.ages), self.received - self._reported)
        self._reported = self.received
        return float(np.median(self.ages.last(new))) if new > 0 else None

    def tick(self, t: float, stale: bool | None) -> None:
        """Each daemon tick (``t``: s): whether the virtual probe is stale now (None: not
        judged, before a calibration); the time since the last tick counts as stale."""
        if stale is not None:
            self._judged = True
            if stale and self._tick_t is not None:
                self.stale_s += t - self._tick_t
        self._tick_t = t

    def report(self, rec: Any, t: float) -> None:
        """About once a second (``t``: the daemon's clock, s), to the recording ``rec``: the
        pose stream's one-way latency, the median since the last report (``pose_one_way``),
        and how long the virtual probe was stale since then (``pose_stale_s``, s; once
        calibrated)."""
        if t - self._last_report < REPORT_PERIOD_S:
            return
        self._last_report = t
        value = self.median_since_last()
        if value is not None:
            rec.write("/follower/latency", t, {"name": "pose_one_way", "value_s": value})
        if self._judged:
            rec.write("/follower/latency", t, {"name": "pose_stale_s", "value_s": self.stale_s})
        self.stale_s, self._judged = 0.0, False

    def stats(self, now: float) -> dict:
        return {
            "poses_received": self.received,
            "pose_rate_hz": self.rate_hz(now),
            "pose_age_p50_ms": percentile_ms(self.ages, 50),
            "pose_age_p99_ms": percentile_ms(self.ages, 99),
            # the last RECENT_POSES only (10 s at 100 Hz): the tail now, start-up not in it
            "pose_age_recent_p99_ms": percentile_ms(self.ages.last(RECENT_POSES), 99),
            "pose_age_last_ms": percentile_ms(self.ages.last(1), 50),
        }


class AlignmentFigures:
    """Position (m) and angle (rad) errors of the real probe's tip to the virtual one's."""

    def __init__(self) -> None:
        self.pos: deque[float] = deque(maxlen=ALIGN_KEPT)
        self.ang: deque[float] = deque(maxlen=ALIGN_KEPT)

    def add(self, real: Pose, virtual: Pose) -> None:
        dp, da = real.distance_to(virtual)
        self.pos.append(dp)
        self.ang.append(da)

    def stats(self) -> dict:
        return {
            "alignment_mm_rms": _rms_scaled(self.pos, 1000.0),
            "alignment_deg_rms": _rms_scaled(self.ang, 180.0 / math.pi),
        }


def _rms_scaled(values: deque[float], scale: float) -> float | None:
    if not values:
        return None
    a = np.fromiter(values, dtype=float, count=len(values))
    return round(float(np.sqrt(np.mean(a * a))) * scale, 3)


class TickFigures:
    """The main loop's ticks: how many, how late each came after the previous one (s, beyond
    the period), and how many the pacing counted late."""

    def __init__(self, rate_hz: float) -> None:
        self.period = 1.0 / rate_hz
        self.ticks = 0
        self.late_ticks = 0
        self.late = SortedWindow(20000)  # s each tick came after its period
        self._prev: float | None = None

    def tick(self, t: float) -> None:
        self.ticks += 1
        if self._prev is not None:  # how late this tick came after the previous one
            self.late.append(max(0.0, t - self._prev - self.period))
        self._prev = t

    def count_late(self) -> None:
        self.late_ticks += 1

    def stats(self) -> dict:
        return {
            "ticks": self.ticks,
            "late_ticks": self.late_ticks,
            "tick_late_p99_ms": percentile_ms(self.late, 99),
            "tick_late_max_ms": percentile_ms(self.late, 100),
        }

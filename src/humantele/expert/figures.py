"""The expert daemon's stream figures: poses sent and their rate, the follower's states
received and their one-way age, and what is recorded of them about once a second (the servo
statistics, ``/expert/servo_stats``; the state stream's median one-way latency,
``/expert/latency``). Times are the daemon's clock (s)."""

from __future__ import annotations

import bisect
import time
from collections import deque
from typing import TYPE_CHECKING, Any

import numpy as np

from humantele.haptics.servo_layout import ServoError
from humantele.runtime.stats import SortedWindow, percentile_ms

if TYPE_CHECKING:
    from humantele.recording import Recorder

REPORT_PERIOD_S = 1.0  # servo statistics and latency figures are recorded this often


class ExpertFigures:
    """Counters of the pose and state streams, and their recording once a second."""

    def __init__(self) -> None:
        self.poses_sent = 0
        self.pose_send_failures = 0
        self.pose_times: deque[float] = deque(maxlen=4000)  # time.monotonic() of each sent
        self.states_received = 0
        self.state_ages = SortedWindow(20000)  # s; percentiles without sorting on the loop
        self.last_report = -np.inf
        self._late_ticks_reported = 0
        self._states_reported = 0

    def pose_sent(self, t: float, ok: bool) -> None:
        """A pose published at ``t``; ``ok``: the link took it."""
        if ok:
            self.poses_sent += 1
            self.pose_times.append(t)
        else:
            self.pose_send_failures += 1

    def state_received(self, age: float | None) -> None:
        """A follower state, with its one-way age (s; None: not known yet)."""
        self.states_received += 1
        if age is not None:
            self.state_ages.append(max(0.0, age))

    def pose_rate_hz(self, window_s: float = 1.0) -> float:
        now = time.monotonic()
        recent = len(self.pose_times) - bisect.bisect_left(self.pose_times, now - window_s)
        return round(recent / window_s, 1)

    def record(self, rec: Recorder, t: float, servo: Any) -> None:
        """About once a second: the servo's statistics (``servo``: the
        :class:`~humantele.haptics.servo.ServoProcess`) and the state stream's one-way
        latency, the median since the last report."""
        if t - self.last_report < REPORT_PERIOD_S:
            return
        self.last_report = t
        if servo.alive:
            try:
                st = servo.stats()
            except ServoError:
                st = None
            if st is not None and st.ticks > 0:
                latest = servo.latest()
                fault = "" if latest is None else latest.fault
                rec.write(
                    "/expert/servo_stats",
                    t,
                    {
                        "rate_hz": st.rate_hz,
                        "period_p99_s": st.period_p99_us * 1e-6,
                        "late_ticks": max(0, st.late_ticks - self._late_ticks_reported),
                        "state": f"fault:{fault}" if fault else "running",
                    },
                )
                self._late_ticks_reported = st.late_ticks
        else:
            rec.write("/expert/servo_stats", t, {"rate_hz": 0.0, "state": "stopped"})
        new = min(len(self.state_ages), self.states_received - self._states_reported)
        self._states_reported = self.states_received
        recent = self.state_ages.last(new)
        if recent:  # the follower's state stream, one way: median since the last report
            rec.write(
                "/expert/latency", t, {"name": "state_one_way", "value_s": float(np.median(recent))}
            )

    def stats(self) -> dict[str, Any]:
        """The streams' part of the daemon's stats."""
        return {
            "poses_sent": self.poses_sent,
            "pose_rate_hz": self.pose_rate_hz(),
            "states_received": self.states_received,
            "state_age_p50_ms": percentile_ms(self.state_ages, 50),
            "state_age_p99_ms": percentile_ms(self.state_ages, 99),
        }

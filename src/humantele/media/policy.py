"""The degradation policy: the video gives way, the POV before the US image, and the tracker
never.

What matters, in order (issue 19 §2; :data:`humantele.runtime.child.PRIORITY`): the servo,
the pose stream, the tracker and the force, the US video, the POV video. The sonographer scans
by the ultrasound image first and the POV second, so when the follower cannot keep up (the
encoder takes fewer US frames than the source gives, the follower's loop runs late) or the
link loses packets, the POV steps down one level per check. When the *tracker* runs short
(fewer frames measured than its rate, with the sensing process running: CPU contention), the
POV steps down the same way, and once the POV is at its lowest the US frame rate steps down
too (``us_level``): the tracker's rate and the pose age are never what gives. After
``recover_s`` of good checks one level comes back, the US's first. The video's own troubles
(US delivery, loss) never lower the US rate (aiortc still lowers its bit rate on congestion).

Levels: POV (size factor per side, rate factor); US (rate factor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from humantele.media.config import DegradeConfig

LEVELS: tuple[tuple[float, float], ...] = ((1.0, 1.0), (1.0, 0.5), (0.5, 0.5), (0.5, 0.25))
US_RATES: tuple[float, ...] = (1.0, 0.75, 0.5)  # the US frame rate's factor per us_level


@dataclass(frozen=True)
class Health:
    """One check's inputs: US frames encoded / captured over the window (None: no frames),
    the worst RTCP fraction lost on either track (None: no report), late ticks per second,
    tracker frames measured / due over the window (None: none measured, e.g. the sensing
    process restarting: not contention)."""

    us_delivery: float | None
    loss: float | None
    late_ticks_per_s: float
    tracker_ratio: float | None = None

    def tracker_short(self, c: DegradeConfig) -> str | None:
        """The tracker measures fewer frames than its rate: the problem the US gives way to."""
        r = self.tracker_ratio
        if r is not None and math.isfinite(r) and r < c.min_tracker_ratio:
            return f"tracker at {100 * r:.0f} % of its rate"
        return None

    def problems(self, c: DegradeConfig) -> list[str]:
        out = []
        if self.us_delivery is not None and self.us_delivery < c.min_us_delivery:
            out.append(f"us delivery {self.us_delivery:.2f}")
        if self.loss is not None and math.isfinite(self.loss) and self.loss > c.max_loss:
            out.append(f"loss {100 * self.loss:.1f} %")
        if self.late_ticks_per_s > c.max_late_ticks_per_s:
            out.append(f"{self.late_ticks_per_s:.0f} late ticks/s")
        short = self.tracker_short(c)
        if short:
            out.append(short)
        return out


class DegradationPolicy:
    """Level of the POV (0 = full) and of the US rate (``us_level``, 0 = full); :meth:`update`
    once per check with its time (s)."""

    def __init__(self, config: DegradeConfig | None = None) -> None:
        self.config = config or DegradeConfig()
        self.level = 0
        self.us_level = 0
        self.changes = 0
        self.reason = ""
        self._good_since: float | None = None

    @property
    def pov_scale(self) -> float:
        return LEVELS[self.level][0]

    @property
    def pov_rate_factor(self) -> float:
        return LEVELS[self.level][1]

    @property
    def us_rate_factor(self) -> float:
        return US_RATES[self.us_level]

    def update(self, t: float, health: Health) -> int:
        """One check; returns the POV level (``us_level`` is beside it)."""
        c = self.config
        if not c.enabled:
            return self.level
        problems = health.problems(c)
        if problems:
            self._good_since = None
            if self.level < c.max_level:
                self.level += 1
            elif health.tracker_short(c) and self.us_level < c.max_us_level:
                self.us_level += 1  # the POV is at its lowest and the tracker still short
            else:
                return self.level
            self.changes += 1
            self.reason = ", ".join(problems)
        else:
            if self._good_since is None:
                self._good_since = t
            elif (self.level or self.us_level) and t - self._good_since >= c.recover_s:
                if self.us_level:  # the US comes back first
                    self.us_level -= 1
                else:
                    self.level -= 1
                self.changes += 1
                self.reason = "recovered"
                self._good_since = t
        return self.level

"""The degradation policy: the POV gives way before the US image when CPU or bandwidth is short.

The sonographer scans by the ultrasound image first and the POV second, so when the follower
cannot keep up (the encoder takes fewer US frames than the source gives, the follower's loop
runs late) or the link loses packets, the POV steps down one level per check, and climbs back
one level after ``recover_s`` of good checks. The US track is never degraded by this policy
(aiortc still lowers its bit rate on congestion, as for any track).

Levels: (POV size factor per side, POV rate factor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from humantele.media.config import DegradeConfig

LEVELS: tuple[tuple[float, float], ...] = ((1.0, 1.0), (1.0, 0.5), (0.5, 0.5), (0.5, 0.25))


@dataclass(frozen=True)
class Health:
    """One check's inputs: US frames encoded / captured over the window (None: no frames),
    the worst RTCP fraction lost on either track (None: no report), late ticks per second."""

    us_delivery: float | None
    loss: float | None
    late_ticks_per_s: float

    def problems(self, c: DegradeConfig) -> list[str]:
        out = []
        if self.us_delivery is not None and self.us_delivery < c.min_us_delivery:
            out.append(f"us delivery {self.us_delivery:.2f}")
        if self.loss is not None and math.isfinite(self.loss) and self.loss > c.max_loss:
            out.append(f"loss {100 * self.loss:.1f} %")
        if self.late_ticks_per_s > c.max_late_ticks_per_s:
            out.append(f"{self.late_ticks_per_s:.0f} late ticks/s")
        return out


class DegradationPolicy:
    """Level of the POV (0 = full); :meth:`update` once per check with its time (s)."""

    def __init__(self, config: DegradeConfig | None = None) -> None:
        self.config = config or DegradeConfig()
        self.level = 0
        self.changes = 0
        self.reason = ""
        self._good_since: float | None = None

    @property
    def pov_scale(self) -> float:
        return LEVELS[self.level][0]

    @property
    def pov_rate_factor(self) -> float:
        return LEVELS[self.level][1]

    def update(self, t: float, health: Health) -> int:
        c = self.config
        if not c.enabled:
            return self.level
        problems = health.problems(c)
        if problems:
            self._good_since = None
            if self.level < c.max_level:
                self.level += 1
                self.changes += 1
                self.reason = ", ".join(problems)
        else:
            if self._good_since is None:
                self._good_since = t
            elif self.level > 0 and t - self._good_since >= c.recover_s:
                self.level -= 1
                self.changes += 1
                self.reason = "recovered"
                self._good_since = t
        return self.level

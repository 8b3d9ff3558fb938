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

**The link** (:func:`split_budget`, :meth:`DegradationPolicy.apply_link`): once a second the
follower sums the expert's REMB of both tracks (what the link carries) and spends it in the
same order: the US first (two thirds, never below its floor at its rate), the POV the rest,
its level set by what is left (rate, size, bit rate, then off); the US frame rate steps down
only with the POV off and the US still short of its floor. The US picture's size never
changes: the console's calipers read its pixel spacing at the configured size. The levels in
force are the lower of the stepped ones and the link's.
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
        self.link_level = 0  # the lowest POV level the link's budget allows (4: off)
        self.link_us_level = 0  # the lowest US rate level it allows
        self.link_changes = 0
        self.budget: Budget | None = None
        self._link_at = -math.inf  # when a link level last changed (s)

    @property
    def pov_level(self) -> int:
        """The POV's level in force: the lower of the stepped one and the link's (4: off)."""
        return max(self.level, self.link_level)

    @property
    def us_rate_level(self) -> int:
        return max(self.us_level, self.link_us_level)

    @property
    def pov_off(self) -> bool:
        return self.pov_level >= POV_OFF

    @property
    def pov_scale(self) -> float:
        return LEVELS[min(self.pov_level, len(LEVELS) - 1)][0]

    @property
    def pov_rate_factor(self) -> float:
        return LEVELS[min(self.pov_level, len(LEVELS) - 1)][1]

    @property
    def us_rate_factor(self) -> float:
        return US_RATES[self.us_rate_level]

    def apply_link(self, t: float, budget: Budget, short: bool = True) -> bool:
        """The link's budget at time ``t`` (s): its levels take effect at once when lower and
        the link is ``short`` (its estimate below what the tracks send, less what was lost: a
        REMB that has not yet grown to what the link carries, as at a session's start, lowers
        nothing); they come back one step per ``recover_s`` (REMB
        moves every second: no flapping). Whether a level changed."""
        self.budget = budget
        if not self.config.enabled:
            return False
        before = (self.link_level, self.link_us_level)
        climb = t - self._link_at >= self.config.recover_s
        for name, want in (("link_us_level", budget.us_level), ("link_level", budget.pov_level)):
            now = getattr(self, name)
            if want > now and short:
                setattr(self, name, want)
            elif want < now and climb:
                setattr(self, name, now - 1)
                climb = False  # one step per recover_s, the US's first
        if (self.link_level, self.link_us_level) != before:
            self._link_at = t
            self.link_changes += 1
            self.reason = f"link {budget.link_kbps:.0f} kbit/s"
            return True
        return False

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


# --- the link's budget (issue 31) ---------------------------------------------------------------

US_SHARE = 2.0 / 3.0  # of the link's budget, the US's first claim (the POV gets the rest)
# The POV's level for the budget left to it (kbit/s at or above which a level is allowed):
# its frame rate goes first, then its size, then its bit rate, then it goes off.
POV_LEVEL_KBPS: tuple[float, ...] = (700.0, 400.0, 250.0, 100.0)  # levels 0-3; below: off
POV_OFF = len(LEVELS)  # the level past the last: off (one frame every POV_OFF_PERIOD_S)
POV_OFF_PERIOD_S = 5.0  # the track stays alive and the expert sees a picture now and then
CLIMB_MARGIN = 1.2  # a level comes back only with this much more than it needs


@dataclass(frozen=True)
class Budget:
    """One split of the link's budget (kbit/s): each track's cap and floor for its encoder,
    and the lowest levels the link allows (the POV's 0-4, 4 off; the US rate's 0-2)."""

    link_kbps: float
    us_kbps: float
    us_floor_kbps: float
    pov_kbps: float
    pov_level: int
    us_level: int


def split_budget(
    link_kbps: float,
    us_min_kbps: float,
    us_max_kbps: float,
    pov_max_kbps: float,
    pov_level: int = 0,
    us_level: int = 0,
) -> Budget:
    """The link's budget (kbit/s; the expert's REMB of both tracks, summed) spent in priority
    order. The US claims ``US_SHARE`` of it, never less than its floor at its rate
    (``us_min_kbps`` at the full rate, proportionally less at x0.75 and x0.5: the same bits per
    frame, the lowest quality a sonographer reads) nor more than ``us_max_kbps``; the POV gets
    the rest (at most ``pov_max_kbps``; what it cannot use goes back to the US, and all of it
    when the POV is off: a REMB estimate grows only from what its track sends, so a share left
    unspent would hold the US where it is). The POV's
    level follows what is left for it (:data:`POV_LEVEL_KBPS`: rate, then size, then bit
    rate, then off); only once the POV is off and the US still does not get its floor does
    the US frame rate step down (x0.75, x0.5). ``pov_level`` and ``us_level`` are the current
    ones: a level comes back only with :data:`CLIMB_MARGIN` times what it needs."""
    link = max(0.0, float(link_kbps))
    us_level_out = 0
    for lvl, factor in enumerate(US_RATES):  # the POV off: does the US get its floor?
        us_level_out = lvl
        need = us_min_kbps * factor * (CLIMB_MARGIN if lvl < us_level else 1.0)
        if link >= need:
            break
    us_floor = us_min_kbps * US_RATES[us_level_out]
    us = min(us_max_kbps, max(us_floor, US_SHARE * link))
    pov = max(0.0, link - us)
    if pov > pov_max_kbps:
        us, pov = min(us_max_kbps, link - pov_max_kbps), pov_max_kbps
    level = POV_OFF
    for lvl, need in enumerate(POV_LEVEL_KBPS):
        if pov >= need * (CLIMB_MARGIN if lvl < pov_level else 1.0):
            level = lvl
            break
    if us_level_out > 0:
        level = POV_OFF
    if level == POV_OFF:  # the POV's share is the US's: its REMB grows only with what it sends
        us, pov = min(us_max_kbps, max(us_floor, link)), 0.0
    return Budget(link, us, us_floor, pov, level, us_level_out)

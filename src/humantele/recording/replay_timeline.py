"""When a replayed device recording's samples are due, so that its devices stay together.

The replays of one recording (the tracker's AHAT frames, the force board's HID reports) each
read the file on their own and pace their samples on the machine's clock. Paced each from its
own first sample (the force board's from its ``open``, the frames' from the first ``read``)
and looped each at its own length, they drift apart: a press replayed seconds before or after
the tip that made it, which the landmark calibration refuses ("only 1 mm from the xiphoid") or
never sees. A sensing process that starts slowly on a loaded machine reads its first frame
seconds after it opened the board, and that was the offset.

:func:`shared_timeline`: one :class:`ReplayTimeline` for the replays of one file on one clock
in this process (the sensing process opens the tracker's and the board's): it starts at the
first one's ``open``, at that replay's first sample; a sample received at ``t`` (s, the
recorder's ``time.monotonic``) is due ``t - origin`` after it (samples recorded before the
origin are due at once), and each loop lasts the recording's span (its first to last message,
plus :data:`LOOP_GAP_S`), so the devices meet again at each loop. A recording without its
summary (cut short) has no known span: each replay then loops from where it ends, on its own.

:class:`DeviceClock`: a sample's time from the device's own clock (the board's microseconds,
hl2ss's 100 ns ticks), anchored to the first receive time, and anchored again when a sample
would come more than ``tolerance_s`` after its own receive time (a first sample received late,
a clock that restarts): the receive times alone carry the recorder's scheduling (a recorder
starved 0.5 s received half a second of reports in one burst). Anchored again, a sample is
never before the one before it, nor with it (a first sample received 80 ms late, and the next
ones, sent from the device's queue, quicker than its clock: time does not go back, nothing is
skipped as stale); ``reanchored`` counts these.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from pathlib import Path

LOOP_GAP_S = 0.01  # between a loop's last sample and the next loop's first (s)
# A sample anchored again before the one before it comes this long after it (s): three or more
# at one time, a paced reader that skips to the newest due sample (the hl2ss client's way)
# skipped the middle ones as stale, on a clock that only its own waits move.
REANCHOR_STEP_S = 1e-6

_SHARED: weakref.WeakValueDictionary[tuple[str, int], ReplayTimeline] = (
    weakref.WeakValueDictionary()
)
_LOCK = threading.Lock()


class ReplayTimeline:
    """See the module docstring. ``period``: one loop (s; None: unknown, each replay loops on
    its own); ``clock``: the replay's clock (s). It starts now."""

    def __init__(self, period: float | None, clock: Callable[[], float]) -> None:
        self.period = period
        self.clock = clock
        self._t0 = clock()
        self._origin: float | None = None

    def due(self, t: float, loop: int = 0) -> float:
        """When a sample at ``t`` (s, the recording's clock, mapped by its device's
        :class:`DeviceClock`) of loop ``loop`` is due on the replay's clock."""
        if self._origin is None:
            self._origin = t  # the first replay's first sample
        return self._t0 + loop * (self.period or 0.0) + (t - self._origin)


def shared_timeline(
    path: str | Path, span: tuple[float, float] | None, clock: Callable[[], float]
) -> ReplayTimeline:
    """The timeline of the replays of ``path`` on ``clock`` in this process (a new one if none
    is open); ``span``: the recording's first and last message times (s), or None."""
    period = None if span is None else span[1] - span[0] + LOOP_GAP_S
    key = (str(Path(path).resolve()), id(clock))
    with _LOCK:
        timeline = _SHARED.get(key)
        if timeline is None or timeline.period != period:
            timeline = _SHARED[key] = ReplayTimeline(period, clock)
        return timeline


class DeviceClock:
    """A device's samples' times on the recording's clock, from the device's own ticks
    (``ticks_per_s``; wrapping at ``wrap``): see the module docstring."""

    def __init__(self, ticks_per_s: float, wrap: int = 1 << 64, tolerance_s: float = 0.05):
        self.ticks_per_s = ticks_per_s
        self.wrap = wrap
        self.tolerance_s = tolerance_s
        self._ticks: int | None = None
        self._t = 0.0
        self.reanchored = 0

    def time(self, t_receive: float, ticks: int | None) -> float:
        """A sample received at ``t_receive`` (s) with the device's ``ticks`` (None: unknown,
        e.g. a report that does not parse: it goes with the sample before it)."""
        if ticks is None:
            return t_receive if self._ticks is None else self._t
        t = t_receive
        if self._ticks is not None:
            ahead = self._t + ((ticks - self._ticks) % self.wrap) / self.ticks_per_s
            if ahead <= t_receive + self.tolerance_s:
                t = ahead
            else:  # after the sample before it, if only just: due at once after it, not with it
                t = max(t_receive, self._t + REANCHOR_STEP_S)
                self.reanchored += 1
        self._ticks, self._t = ticks, t
        return t

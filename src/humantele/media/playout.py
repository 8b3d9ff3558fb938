"""When the expert shows each decoded frame: on a link that repairs loss, at a steady delay
after its capture rather than as soon as it is decoded (issue 31).

A frame with a lost packet waits for the packet's retransmission (a round trip and more:
150-250 ms on the 60 ± 20 ms rural link), and the frames behind it wait with it, then leave
together. Shown as they come, every repair is a gap between two pictures longer than the
freeze threshold (WebRTC's: max(3 x the frame interval, it + 150 ms)), then a jump: at 3 %
loss, a few repairs a second froze most of the scan though every frame arrived. Shown at a
steady delay that covers the repairs, the picture moves on smoothly, later by that delay. That
is WebRTC's receiver's playout: each frame is rendered at its RTP time plus the stream's
shortest transit plus a target delay that covers the jitter (and, with NACK, the round trip).

Here: a frame's *transit* is its arrival (decoded, s) less its RTP time (s); the *base* is the
shortest transit of the last :data:`BASE_WINDOW_S` (a frame that waited for nothing); the
*delay* is the :data:`DELAY_QUANTILE` of the recent transits above the base, at most
``max_delay_s``, and only while the jitter buffer has repaired a packet in the last
:data:`REPAIR_HOLD_S` (:meth:`Playout.note_repairs`): a link that loses nothing keeps showing
each frame as soon as it is decoded (the loopback and the 750 km link: no added latency). A
frame is due at its RTP time plus the base plus the delay; one that comes later is due at once.
No threads, no sleeping: the clock is passed in.
"""

from __future__ import annotations

import math
from collections import deque

VIDEO_RATE = 90_000  # RTP video clock, Hz
MAX_DELAY_S = 0.25  # never hold a frame longer than this beyond the stream's shortest transit
DELAY_QUANTILE = 0.95  # the delay covers this share of the recent transits
TRANSITS_KEPT = 100  # recent frames the delay follows (5 s of the US at 20 fps)
BASE_WINDOW_S = 10.0  # the shortest transit of this long (clock drift, a changed route)
REPAIR_HOLD_S = 10.0  # a delay is kept this long after the last repair
DUE_RESOLUTION_S = 1e-3  # a frame due within this of now is due now (s)


class Playout:
    """See the module docstring. Times in s on one monotonic clock; ``pts`` in RTP units."""

    def __init__(self, max_delay_s: float = MAX_DELAY_S, rate_hz: int = VIDEO_RATE) -> None:
        self.max_delay_s = max_delay_s
        self.rate_hz = rate_hz
        self._transits: deque[tuple[float, float]] = deque()  # (arrival, transit)
        self._repairs = 0
        self._repair_at = -math.inf
        self.delay_s = 0.0  # the delay in force at the last frame (s)
        self.delay_max_s = 0.0  # the longest delay in force (s)

    def note_repairs(self, repairs: int, now: float) -> None:
        """The jitter buffer's count of repaired packets so far (in time or late), at ``now``."""
        if repairs > self._repairs:
            self._repair_at = now
        self._repairs = max(self._repairs, repairs)

    def due(self, pts: int | None, now: float) -> float:
        """When to show a frame of RTP time ``pts`` decoded at ``now``: at ``now`` or later."""
        if pts is None:
            return now
        t = pts / self.rate_hz
        kept = self._transits
        kept.append((now, now - t))
        while len(kept) > 1 and (kept[0][0] < now - BASE_WINDOW_S or len(kept) > TRANSITS_KEPT):
            kept.popleft()
        base = min(x for _, x in kept)
        self.delay_s = self._delay(now, base)
        self.delay_max_s = max(self.delay_max_s, self.delay_s)
        due = t + base + self.delay_s
        return due if due > now + DUE_RESOLUTION_S else now

    def _delay(self, now: float, base: float) -> float:
        if now - self._repair_at > REPAIR_HOLD_S:
            return 0.0
        extra = sorted(x - base for _, x in self._transits)
        return min(self.max_delay_s, extra[int(DELAY_QUANTILE * (len(extra) - 1))])

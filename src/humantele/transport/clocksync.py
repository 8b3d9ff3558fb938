"""NTP-style clock sync over the control channel.

The local side sends ``Ping(seq, t0)``; the remote stamps ``t1`` when the ping arrives and ``t2``
when its ``Pong`` leaves; the local side stamps ``t3`` when the pong arrives. Each exchange gives

    offset = ((t1 - t0) + (t2 - t3)) / 2      remote clock minus local clock (s)
    rtt    = (t3 - t0) - (t2 - t1)            time spent on the network (s)

The estimate is the offset of the exchange with the smallest round trip among the last
``window`` ones (the one least disturbed by queueing), as NTP's clock filter does. With it, a
remote timestamp ``t_remote`` (remote monotonic clock, s) becomes an age on the local clock:
``age = now_local - (t_remote - offset)``. All times are seconds of each side's monotonic clock.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from humantele.wire import Ping, Pong


@dataclass(frozen=True, slots=True)
class SyncSample:
    offset: float  # remote minus local (s)
    rtt: float  # network round trip (s)
    t_local: float  # local time the sample was taken (s)


class ClockSync:
    """Offset and round trip to the peer's clock; ``clock`` is the local monotonic clock (s)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic, window: int = 16) -> None:
        self.clock = clock
        self._samples: deque[SyncSample] = deque(maxlen=window)
        self._seq = 0
        self._pending: dict[int, float] = {}
        self.best: SyncSample | None = None
        self.rejected = 0

    def reset(self) -> None:
        """Forget every sample (a new peer has a new clock)."""
        self._samples.clear()
        self._pending.clear()
        self.best = None

    @property
    def synced(self) -> bool:
        return self.best is not None

    @property
    def offset(self) -> float | None:
        """Remote clock minus local clock (s), or None before the first exchange."""
        return None if self.best is None else self.best.offset

    @property
    def rtt(self) -> float | None:
        """Round trip (s) of the exchange the offset comes from, or None."""
        return None if self.best is None else self.best.rtt

    @property
    def last_rtt(self) -> float | None:
        """Round trip (s) of the latest exchange, or None."""
        return self._samples[-1].rtt if self._samples else None

    @property
    def high_rtt(self) -> float | None:
        """The longest round trip (s) of the recent exchanges (the window's), or None: what a
        retransmission may take on a jittery link (the offset's ``rtt`` is the shortest)."""
        return max(s.rtt for s in self._samples) if self._samples else None

    def make_ping(self) -> Ping:
        """A ping stamped now; send it on the control channel."""
        self._seq += 1
        t0 = self.clock()
        self._pending[self._seq] = t0
        if len(self._pending) > 64:  # unanswered pings: forget the oldest
            del self._pending[min(self._pending)]
        return Ping(seq=self._seq, t0=t0)

    def answer(self, ping: Ping, t1: float) -> Pong:
        """The pong for a ping that arrived at local time ``t1``; stamped ``t2`` now."""
        return Pong(seq=ping.seq, t0=ping.t0, t1=t1, t2=self.clock())

    def on_pong(self, pong: Pong, t3: float | None = None) -> SyncSample | None:
        """Take a pong that arrived at local time ``t3`` (now if None); returns the sample, or
        None if it answers no ping of ours or is inconsistent (counted in ``rejected``)."""
        t3 = self.clock() if t3 is None else t3
        t0 = self._pending.pop(pong.seq, None)
        if t0 is None or t0 != pong.t0:
            self.rejected += 1
            return None
        rtt = (t3 - t0) - (pong.t2 - pong.t1)
        if rtt < 0 or pong.t2 < pong.t1:
            self.rejected += 1
            return None
        sample = SyncSample(((pong.t1 - t0) + (pong.t2 - t3)) / 2.0, rtt, t3)
        self._samples.append(sample)
        self.best = min(self._samples, key=lambda s: s.rtt)
        return sample

    def to_local(self, t_remote: float) -> float | None:
        """A remote monotonic time (s) on the local clock, or None before sync."""
        return None if self.best is None else t_remote - self.best.offset

    def age_of(self, t_remote: float, now: float | None = None) -> float | None:
        """How long ago (s, local clock) the remote time ``t_remote`` was, or None before sync."""
        local = self.to_local(t_remote)
        if local is None:
            return None
        return (self.clock() if now is None else now) - local

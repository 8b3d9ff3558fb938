"""Fixed-rate ticks on the asyncio loop, for sending poses and states at their rate.

``asyncio.sleep`` cannot hold 1 kHz (the selector rounds timeouts up to whole milliseconds, so
``sleep(0.001)`` gives ~900 Hz). :func:`ticks` sleeps to absolute deadlines instead and, when a
wake-up comes late, runs the ticks that fell due at once, so the average rate is exact. A stall
longer than ``max_lag_s`` is not made up (stale poses are useless): those ticks are skipped and
counted in ``Pacer.skipped``.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable


class Pacer:
    """Deadline pacing at ``rate_hz`` (clock in s)."""

    def __init__(
        self, rate_hz: float, clock: Callable[[], float] = time.monotonic, max_lag_s: float = 0.05
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self.period = 1.0 / rate_hz
        self.clock = clock
        self.max_lag_s = max_lag_s
        self.ticks = 0
        self.skipped = 0

    async def ticks_for(self, duration_s: float | None = None) -> AsyncIterator[int]:
        """Yield the tick number at each deadline, for ``duration_s`` (forever if None)."""
        start = self.clock()
        deadline = start
        end = None if duration_s is None else start + duration_s
        while True:
            now = self.clock()
            if end is not None and now >= end:
                return
            if now < deadline:
                await asyncio.sleep(deadline - now)
                continue
            if now - deadline > self.max_lag_s:
                missed = int((now - deadline) / self.period)
                self.skipped += missed
                deadline += missed * self.period
            yield self.ticks
            self.ticks += 1
            deadline += self.period


def ticks(rate_hz: float, duration_s: float | None = None) -> AsyncIterator[int]:
    """Shorthand: ``async for i in ticks(250): link.send_pose(...)``."""
    return Pacer(rate_hz).ticks_for(duration_s)

"""Fixed-rate ticks on the asyncio loop: the one pacer for the daemons and ``bench session``.

``asyncio.sleep`` cannot hold 1 kHz (the selector rounds timeouts up to whole milliseconds, so
``sleep(0.001)`` gives ~900 Hz). :class:`Pacer` sleeps to absolute deadlines instead and, when a
wake-up comes late by up to ``max_lag_s``, runs the tick that fell due at once, so the average
rate is exact. A tick later than that is not made up (stale poses are useless): the ticks that
fell due are skipped, counted in ``Pacer.skipped``, and the schedule restarts from now.
:func:`daemon_ticks` is a daemon's main loop on top of it. Every time comes from the one
``clock`` (s), so a fake clock drives it all in tests.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import AsyncIterator, Callable

from humantele.runtime.process import parent_gone

log = logging.getLogger(__name__)

MAX_LAG_S = 0.01  # a tick later than this is skipped (one period of the daemons' 100 Hz)
REPORT_PERIOD_S = 0.5  # a daemon's stats file is rewritten this often


class Pacer:
    """Deadline pacing at ``rate_hz`` on ``clock`` (s); ``skipped`` counts ticks not made up."""

    def __init__(
        self,
        rate_hz: float,
        clock: Callable[[], float] = time.monotonic,
        max_lag_s: float = MAX_LAG_S,
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
            if now - deadline > self.max_lag_s:  # too late: skip, restart the schedule
                self.skipped += max(1, int((now - deadline) / self.period))
                deadline = now
            yield self.ticks
            self.ticks += 1
            deadline += self.period


def ticks(rate_hz: float, duration_s: float | None = None) -> AsyncIterator[int]:
    """Shorthand: ``async for i in ticks(250): link.send_pose(...)``."""
    return Pacer(rate_hz).ticks_for(duration_s)


async def daemon_ticks(
    rate_hz: float,
    duration_s: float | None,
    running: Callable[[], bool],
    report: Callable[[], None],
    clock: Callable[[], float] = time.monotonic,
    on_late: Callable[[], None] | None = None,
) -> AsyncIterator[float]:
    """A daemon's main-loop ticks at ``rate_hz`` (a :class:`Pacer`): yields ``clock()`` (s).

    Ends when ``running()`` turns false, after ``duration_s`` (None: never), or when the demo
    that started this daemon is gone (checked with ``report()`` every 0.5 s). A tick the pacer
    skips (late by more than ``MAX_LAG_S``) calls ``on_late()`` once per stall.
    """
    pacer = Pacer(rate_hz, clock)
    skipped = 0
    last_report = -math.inf
    async for _ in pacer.ticks_for(duration_s):
        if not running():
            return
        if pacer.skipped != skipped:
            skipped = pacer.skipped
            if on_late is not None:
                on_late()
        t = clock()
        yield t
        if t - last_report > REPORT_PERIOD_S:
            # What the tick sent leaves first: aiortc transmits from a task of its own, which
            # would otherwise wait behind the report (1-2 ms every 0.5 s: the pose-age p99).
            await asyncio.sleep(0)
            last_report = t
            report()
            if parent_gone():
                log.warning("the demo that started this daemon is gone; stopping")
                return

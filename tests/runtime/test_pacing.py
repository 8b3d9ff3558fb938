import asyncio

from humantele.runtime.pacing import Pacer


class StepClock:
    """A clock that only moves when the pacer sleeps (plus a fixed cost per tick)."""

    def __init__(self, cost: float):
        self.t = 0.0
        self.cost = cost


async def test_average_rate_is_exact_when_wakeups_are_late(monkeypatch):
    clock = StepClock(0.0)

    async def late_sleep(dt):  # like epoll: rounded up to whole milliseconds, plus 0.3 ms
        import math

        clock.t += math.ceil(dt * 1e3) * 1e-3 + 0.0003

    monkeypatch.setattr(asyncio, "sleep", late_sleep)
    pacer = Pacer(1000.0, clock=lambda: clock.t)
    n = 0
    async for _ in pacer.ticks_for(1.0):
        n += 1
    assert 995 <= n <= 1001  # ~1000 ticks in 1 s despite every wake-up being late
    assert pacer.skipped == 0


async def test_a_long_stall_is_skipped_not_made_up(monkeypatch):
    clock = StepClock(0.0)

    async def sleep(dt):
        clock.t += dt

    monkeypatch.setattr(asyncio, "sleep", sleep)
    pacer = Pacer(100.0, clock=lambda: clock.t)
    times = []
    async for i in pacer.ticks_for(1.0):
        times.append(clock.t)
        if i == 10:
            clock.t += 0.5  # the loop stalls for half a second
    burst = max(times.count(t) for t in set(times))
    assert burst <= 2  # no backlog of 50 ticks at once: they are skipped instead
    assert 48 <= pacer.skipped <= 49
    assert 45 <= len(times) <= 55

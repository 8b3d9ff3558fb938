"""The daemons' shared main-loop pacing (humantele.runtime.pacing.daemon_ticks), on a fake
clock: time moves only when the loop sleeps or a tick's body takes time."""

import asyncio

import pytest

from humantele.runtime.pacing import daemon_ticks
from humantele.runtime.process import PARENT_PID_ENV


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock(monkeypatch):
    c = FakeClock()

    async def sleep(dt):
        c.t += max(0.0, dt)

    monkeypatch.setattr(asyncio, "sleep", sleep)
    return c


async def test_ticks_end_after_the_duration_and_report_every_half_second(clock):
    reports, late = [], []
    ticks = [
        t
        async for t in daemon_ticks(
            100.0,
            0.7,
            lambda: True,
            lambda: reports.append(1),
            clock=clock,
            on_late=lambda: late.append(1),
        )
    ]
    assert 40 <= len(ticks) <= 75 and ticks == sorted(ticks)
    assert len(reports) == 2  # at the first tick and once past 0.5 s
    assert not late


async def test_a_late_tick_is_not_caught_up_and_is_counted(clock):
    late, times = [], []
    async for t in daemon_ticks(
        100.0, 0.3, lambda: True, lambda: None, clock=clock, on_late=lambda: late.append(1)
    ):
        times.append(t)
        if len(times) == 3:
            clock.t += 0.1  # a body that blocks for 10 periods
    assert len(late) == 1
    gaps = [b - a for a, b in zip(times, times[1:], strict=False)]
    assert sum(1 for g in gaps if g < 0.002) <= 1  # no burst of catch-up ticks after the stall


async def test_ticks_stop_when_running_turns_false_or_the_demo_is_gone(clock, monkeypatch):
    n = [0]

    def running():
        n[0] += 1
        return n[0] <= 5

    ticks = [t async for t in daemon_ticks(1000.0, None, running, lambda: None, clock=clock)]
    assert len(ticks) == 5
    monkeypatch.setenv(PARENT_PID_ENV, "1")  # not our parent: the demo is gone
    gone = [t async for t in daemon_ticks(1000.0, None, lambda: True, lambda: None, clock=clock)]
    assert len(gone) == 1


async def test_what_a_tick_sent_leaves_before_the_report():
    """aiortc transmits from a task of its own (ensure_future): that task runs before the
    tick's report, not after it (a report took 1-2 ms, the pose waited)."""
    order = []

    async def transmit():
        order.append("sent")

    ticks = 0
    async for _ in daemon_ticks(1000.0, None, lambda: True, lambda: order.append("report")):
        ticks += 1
        if ticks == 2:
            break
        asyncio.ensure_future(transmit())  # the first tick sends; its report follows
    assert order == ["sent", "report"]

"""The daemons' shared main-loop pacing (humantele.demo.daemon_ticks)."""

import time

from humantele.demo import PARENT_PID_ENV, daemon_ticks


async def test_ticks_end_after_the_duration_and_report_every_half_second():
    reports, late = [], []
    ticks = [
        t
        async for t in daemon_ticks(
            100.0, 0.7, lambda: True, lambda: reports.append(1), on_late=lambda: late.append(1)
        )
    ]
    assert 40 <= len(ticks) <= 75 and ticks == sorted(ticks)
    assert len(reports) == 2  # at the first tick and once past 0.5 s
    assert not late


async def test_a_late_tick_is_not_caught_up_and_is_counted():
    late, times = [], []
    async for t in daemon_ticks(
        100.0, 0.3, lambda: True, lambda: None, on_late=lambda: late.append(1)
    ):
        times.append(t)
        if len(times) == 3:
            time.sleep(0.1)  # a body that blocks for 10 periods
    assert len(late) == 1
    gaps = [b - a for a, b in zip(times, times[1:], strict=False)]
    assert sum(1 for g in gaps if g < 0.002) <= 1  # no burst of catch-up ticks after the stall


async def test_ticks_stop_when_running_turns_false_or_the_demo_is_gone(monkeypatch):
    n = [0]

    def running():
        n[0] += 1
        return n[0] <= 5

    assert len([t async for t in daemon_ticks(1000.0, None, running, lambda: None)]) == 5
    monkeypatch.setenv(PARENT_PID_ENV, "1")  # not our parent: the demo is gone
    assert len([t async for t in daemon_ticks(1000.0, None, lambda: True, lambda: None)]) == 1

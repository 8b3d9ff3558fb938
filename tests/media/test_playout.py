"""When the expert shows each decoded frame (humantele.media.playout): at once on a link that
repairs nothing; at a steady delay after its RTP time on one that does, so a repair (the
frame behind it waiting with it) is no gap between pictures. Times are passed in by hand."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

import av
import pytest
from aiortc.mediastreams import MediaStreamError

from humantele.media.config import ExpertVideoConfig
from humantele.media.playout import MAX_DELAY_S, REPAIR_HOLD_S, Playout
from humantele.media.receiver import VideoReceiver
from waits import until

INTERVAL = 4500  # 90 kHz ticks a frame (20 fps)


def show_times(playout: Playout, arrivals: list[float], repaired=()) -> list[float]:
    """The times frames 0, 1, ... (RTP 0, INTERVAL, ...) are shown, decoded at ``arrivals``
    (s): each when due, never before the one before it; the jitter buffer's count of repairs
    grows at each frame of ``repaired``."""
    out: list[float] = []
    for i, now in enumerate(arrivals):
        if i in repaired:
            playout.note_repairs(i, now)
        out.append(max(playout.due(i * INTERVAL, now), out[-1] if out else 0.0))
    return out


def link(n: int, transit: float, repaired: dict[int, float]) -> list[float]:
    """Arrivals of n frames 50 ms apart with a constant ``transit``; frame k of ``repaired``
    waits that much longer for a retransmission, and the frames complete behind it leave
    with it."""
    arrivals = [i * 0.05 + transit for i in range(n)]
    for k, extra in repaired.items():
        release = arrivals[k] + extra
        for i in range(k, n):
            arrivals[i] = max(arrivals[i], release) if arrivals[i] < release else arrivals[i]
    return arrivals


def gaps(times: list[float]) -> list[float]:
    return [b - a for a, b in zip(times, times[1:], strict=False)]


def test_a_link_that_repairs_nothing_shows_each_frame_as_it_comes():
    playout = Playout()
    arrivals = [i * 0.05 + 0.06 + (0.01 if i % 3 else 0.0) for i in range(200)]
    assert show_times(playout, arrivals) == arrivals
    assert playout.delay_max_s == 0.0


def test_repairs_are_no_freeze_once_the_delay_covers_them():
    """Every 7th frame waits 180 ms for a retransmission: shown as decoded, each is a 230 ms
    gap (a freeze: over 200 ms at 20 fps); at a steady delay the gaps stay 50 ms, and the
    picture is later by about the repair."""
    n = 400
    repaired = {k: 0.18 for k in range(20, n, 7)}
    arrivals = link(n, 0.06, repaired)
    assert max(gaps(arrivals[20:])) == pytest.approx(0.23)
    playout = Playout()
    shown = show_times(playout, arrivals, repaired)
    later = gaps(shown[150:])
    assert max(later) == pytest.approx(0.05, abs=0.002)
    delay = shown[-1] - (n - 1) * 0.05 - 0.06
    assert 0.17 <= delay <= 0.19 and playout.delay_s == pytest.approx(delay, abs=1e-6)


def test_the_delay_is_bounded_and_ends_when_repairs_end():
    playout = Playout()
    repaired = {k: 0.8 for k in range(10, 200, 5)}  # repairs take 0.8 s
    arrivals = link(200, 0.06, repaired)
    show_times(playout, arrivals, repaired)
    assert playout.delay_max_s == pytest.approx(MAX_DELAY_S)
    # no repair for REPAIR_HOLD_S: each frame as it comes again
    t0 = arrivals[-1] + REPAIR_HOLD_S + 0.1
    assert playout.due(200 * INTERVAL, t0) == t0 and playout.delay_s == 0.0


def test_a_frame_later_than_its_due_time_is_due_at_once_and_no_pts_is_now():
    playout = Playout()
    playout.note_repairs(3, 0.0)
    for i in range(50):
        playout.due(i * INTERVAL, i * 0.05 + 0.06 + (0.1 if i % 10 == 0 else 0.0))
    assert playout.due(50 * INTERVAL, 50 * 0.05 + 5.0) == 50 * 0.05 + 5.0
    assert playout.due(None, 9.0) == 9.0


async def test_the_receiver_shows_each_frame_when_its_playout_says():
    """The wiring (media.receiver): decoded frames are shown (timed, made the latest) at the
    playout's due time on the expert's clock, not when decoded, once the jitter buffer has
    repaired a packet. The clock is driven by hand; the loop only has to wake up."""

    class Track:
        def __init__(self):
            self._queue = asyncio.Queue()

        async def recv(self):
            frame = await self._queue.get()
            if frame is None:
                raise MediaStreamError
            return frame

    clock = {"t": 100.0}
    rx = VideoReceiver(ExpertVideoConfig(enabled=True), SimpleNamespace(to_local=lambda t: None),
                       now=lambda: clock["t"])  # fmt: skip
    rx._pc = pc = object()
    rx._jitter["us"] = SimpleNamespace(counters=SimpleNamespace(repairs=1, late_repairs=0))
    track = Track()
    task = asyncio.ensure_future(rx._consume(pc, "us", track))
    expected = Playout()
    expected.note_repairs(1, clock["t"])
    arrivals = link(12, 0.06, {8: 0.2})  # frame 8 waits 200 ms; 9 and 10 come with it
    st = rx.stats_by_track["us"]
    try:
        for i, t in enumerate(arrivals):
            frame = av.VideoFrame(width=64, height=48, format="yuv420p")
            frame.pts = i * INTERVAL
            clock["t"] = 100.0 + t
            due = expected.due(frame.pts, clock["t"])
            shown = st.frames
            await track._queue.put(frame)
            if due > clock["t"]:  # held: not shown until the clock reaches its due time
                await asyncio.sleep(0.05)
                assert st.frames == shown
                clock["t"] = due
            await until(lambda n=shown: st.frames == n + 1, 10)
            assert st.arrivals[-1] == pytest.approx(due)
        assert expected.delay_max_s > 0.1  # the repair set a delay, and frames were held
    finally:
        task.cancel()

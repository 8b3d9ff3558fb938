"""A page is judged gone on the daemon's running time, and a page lost is not a page refused
(issue 34: on a machine at load 10-17 the headset page kept reconnecting, and the feed counted
the lost connections as ``socket_error`` refusals, which the demo's test asks to be 0).

The watch on a clock the test drives; then the headset feed (plain WebSocket, in this process)
with a page whose answer to a ping comes after the whole loop stalled (the daemon starved), a
page that answers nothing (gone), and a page that breaks the protocol (refused)."""

from __future__ import annotations

import time

import aiohttp
import pytest

from humantele.follower.feed import FeedConfig, RendererFeed
from humantele.web import pagesocket
from humantele.web.liveness import PageLiveness
from waits import until


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def steps(live: PageLiveness, clock: Clock, n: int, dt: float = 0.5) -> list:
    out = []
    for _ in range(n):
        clock.t += dt
        out.append(live.step())
    return out


def test_a_quiet_page_is_pinged_then_gone_on_running_time():
    clock = Clock()
    live = PageLiveness(ping_every_s=5.0, answer_within_s=10.0, step_s=0.5, clock=clock)
    got = steps(live, clock, 10)
    assert got == [None] * 9 + ["ping"]  # 5 s quiet
    got = steps(live, clock, 20)
    assert got == [None] * 19 + ["gone"]  # 10 s more without an answer
    live.heard()
    assert steps(live, clock, 9) == [None] * 9  # an answer: quiet again from zero


def test_a_stalled_daemon_never_finds_an_answering_page_gone():
    clock = Clock()
    live = PageLiveness(ping_every_s=5.0, answer_within_s=10.0, step_s=0.5, clock=clock)
    assert steps(live, clock, 10)[-1] == "ping"
    clock.t += 60.0  # the daemon did not run for a minute (the answer waits in the socket)
    assert live.step() is None and live.late_steps == 1
    live.heard()  # read in the loop's next turn
    assert steps(live, clock, 9) == [None] * 9
    # Stalls alone never make a page gone; running time after them does.
    assert steps(live, clock, 1) == ["ping"]
    for _ in range(50):
        clock.t += 3.0  # every step late: the machine starved throughout
        assert live.step() is None
    assert steps(live, clock, 20)[-1] == "gone"  # 10 s of running time with no answer


def plain_feed() -> RendererFeed:
    feed = RendererFeed(FeedConfig(port=0, host="127.0.0.1", tls=False))
    feed.pages.ping_every_s, feed.pages.answer_within_s, feed.pages.step_s = 0.2, 1.0, 0.05
    return feed


async def next_ping(ws) -> aiohttp.WSMessage:
    while (msg := await ws.receive(timeout=30)).type != aiohttp.WSMsgType.PING:
        assert msg.type in (aiohttp.WSMsgType.TEXT, aiohttp.WSMsgType.BINARY), msg
    return msg


async def test_a_page_answering_after_the_daemon_stalled_stays(monkeypatch):
    # The old heartbeat scaled as the watch is here (a ping after 0.4 s, the pong awaited
    # 0.2 s): it closed this page in the loop turn that read its answer.
    monkeypatch.setattr(pagesocket, "HEARTBEAT_S", 0.4, raising=False)
    feed = plain_feed()
    await feed.start()
    try:
        async with (
            aiohttp.ClientSession() as s,
            s.ws_connect(feed.url, autoping=False) as ws,
        ):
            await until(lambda: len(feed.clients) == 1)
            for _ in range(3):
                ping = await next_ping(ws)
                time.sleep(1.0)  # the whole loop stalls: the daemon (and this page) starved
                await ws.pong(ping.data)
            ping = await next_ping(ws)  # still open, and pinging
            await ws.pong(ping.data)
            assert not ws.closed and len(feed.clients) == 1
        await until(lambda: not feed.clients)
        stats = feed.stats()
        assert stats["lost"] == {} and stats["refused_total"] == 0
        assert stats["disconnects"] == 1 and stats["handshake_failed"] == 0
    finally:
        await feed.stop()


async def test_a_page_that_answers_nothing_is_lost_not_refused():
    feed = plain_feed()
    await feed.start()
    try:
        async with aiohttp.ClientSession() as s, s.ws_connect(feed.url, autoping=False) as ws:
            t0 = time.monotonic()
            while True:  # reads, never answers (a tab whose network went)
                msg = await ws.receive(timeout=30)
                if msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED):
                    break
            assert msg.data == aiohttp.WSCloseCode.GOING_AWAY and msg.extra == "no answer"
            assert time.monotonic() - t0 >= 1.2  # 0.2 s quiet + 1.0 s unanswered, at least
        await until(lambda: not feed.clients)
        stats = feed.stats()
        assert stats["lost"] == {"no_answer": 1} and stats["refused_total"] == 0
    finally:
        await feed.stop()


@pytest.mark.parametrize("frame", [b"\x8f\x80\x00\x00\x00\x00"])  # opcode 0xF: reserved
async def test_a_frame_that_breaks_the_protocol_is_refused(frame):
    feed = plain_feed()
    await feed.start()
    try:
        async with aiohttp.ClientSession() as s:
            ws = await s.ws_connect(feed.url)
            await until(lambda: len(feed.clients) == 1)
            ws._response.connection.transport.write(frame)
            await until(lambda: not feed.clients)
            await ws.close()
        stats = feed.stats()
        assert stats["refused"] == {"bad_frame": 1} and stats["lost"] == {}
    finally:
        await feed.stop()

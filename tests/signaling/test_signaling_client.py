"""The signaling client against servers that do not answer or do not exist, and what a link
(the daemons' view) shows meanwhile."""

import asyncio
import contextlib
import logging
import re

import pytest
from aiohttp import web
from signaling_helpers import assert_clean_logs

from humantele.signaling.client import SignalingClient, SignalingError, SignalingRefused
from humantele.signaling.server import SignalConfig, SignalingServer
from humantele.transport import LinkConfig, PeerLink
from waits import until

TOKEN = "client-token"


@contextlib.asynccontextmanager
async def silent_endpoint():
    """A TCP server that accepts and never answers; yields (url, accepted connections)."""
    accepted: list[asyncio.StreamWriter] = []

    async def hold(reader, writer):
        accepted.append(writer)
        await reader.read()  # until the client gives up

    server = await asyncio.start_server(hold, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        yield f"ws://127.0.0.1:{port}/ws", accepted
    finally:
        for w in accepted:
            w.close()
        server.close()


async def test_join_times_out_against_a_server_that_never_answers():
    async with silent_endpoint() as (url, accepted):
        client = SignalingClient(url, "r", "expert", TOKEN, connect_timeout_s=0.3)
        with pytest.raises(SignalingError, match=r"did not answer within 0.3 s"):
            await asyncio.wait_for(client.join(), 20)  # today: hangs for ever
        assert len(accepted) == 1 and client.closed


async def test_close_ends_a_join_in_progress():
    async with silent_endpoint() as (url, _):
        client = SignalingClient(url, "r", "expert", TOKEN, connect_timeout_s=60)
        joining = asyncio.create_task(client.join())
        await asyncio.sleep(0.1)
        await client.close()
        with pytest.raises(SignalingError, match="closed while joining"):
            await asyncio.wait_for(joining, 10)


async def test_a_servers_reason_is_quoted_before_it_reaches_a_log():
    """The daemon logs what the server says: a hostile server cannot forge a line either."""

    async def hostile(request):
        ws = web.WebSocketResponse()
        await ws.prepare(request)
        await ws.receive()  # the join
        await ws.send_str('{"type": "error", "reason": "no\\n2026-01-01 FAKE: all good"}')
        await ws.close(code=4401)
        return ws

    app = web.Application()
    app.router.add_get("/ws", hostile)
    runner = web.AppRunner(app)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = runner.addresses[0][1]
    try:
        client = SignalingClient(f"ws://127.0.0.1:{port}/ws", "r", "expert", TOKEN)
        with pytest.raises(SignalingRefused) as err:
            await client.join()
        assert err.value.fatal and "\n" not in str(err.value)
        assert err.value.reason == "no\\n2026-01-01 FAKE: all good"  # visible, one line
    finally:
        await runner.cleanup()


def _retry_delays(records) -> list[float]:
    return [
        float(m.group(1))
        for r in records
        if (m := re.search(r"retrying in ([0-9.]+) s", r.getMessage()))
    ]


def _link(url: str, **settings) -> PeerLink:
    cfg = LinkConfig(
        signaling_url=url,
        token=TOKEN,
        connect_timeout_s=0.3,
        reconnect_delay_s=0.1,
        reconnect_max_delay_s=0.4,
        **settings,
    )
    return PeerLink("follower", cfg)


async def test_link_says_unreachable_retries_with_backoff_and_stops_at_once(caplog):
    caplog.set_level(logging.INFO)
    async with silent_endpoint() as (url, accepted):
        link = _link(url)
        task = asyncio.create_task(link.run())
        await link.wait_state("unreachable", timeout=20)
        await until(lambda: len(_retry_delays(caplog.records)) >= 4, 30, what="4 retries")
        await asyncio.wait_for(link.close(), 5)  # today: stuck "connecting" until killed
        await asyncio.wait_for(task, 5)
    assert link.state == "closed"
    warnings = [r for r in caplog.records if "did not answer within 0.3 s" in r.getMessage()]
    assert len(warnings) >= 4 and all(r.levelno == logging.WARNING for r in warnings)
    assert len(accepted) >= 4
    assert _retry_delays(caplog.records)[:4] == [0.1, 0.2, 0.4, 0.4]  # backoff, capped
    assert_clean_logs(caplog.records, TOKEN)


async def test_link_to_an_unresolvable_host_warns_and_retries_without_traceback(caplog):
    caplog.set_level(logging.INFO)
    link = _link("ws://signaling.invalid:8765/ws")  # RFC 2606: never resolves
    task = asyncio.create_task(link.run())
    await link.wait_state("unreachable", timeout=20)
    await until(lambda: len(_retry_delays(caplog.records)) >= 2, 30, what="a retry")
    await asyncio.wait_for(link.close(), 5)
    await asyncio.wait_for(task, 5)
    lines = [r.getMessage() for r in caplog.records if "retrying in" in r.getMessage()]
    assert all("signaling.invalid" in m for m in lines)
    assert_clean_logs(caplog.records, TOKEN)


async def test_link_leaves_unreachable_once_the_server_is_up():
    probe = SignalingServer(SignalConfig(port=0), TOKEN)
    await probe.start()
    port = probe.port
    await probe.stop()  # nothing listens there now: connection refused
    link = _link(f"ws://127.0.0.1:{port}/ws")
    task = asyncio.create_task(link.run())
    try:
        await link.wait_state("unreachable", timeout=20)
        server = SignalingServer(SignalConfig(port=port), TOKEN)
        await server.start()
        try:
            await link.wait_state("connecting", timeout=30)  # joined; waiting for the expert
            await until(lambda: "demo" in server.rooms, what="the room")
        finally:
            await link.close()
            await server.stop()
    finally:
        await asyncio.wait_for(task, 5)


async def test_a_stalled_loop_keeps_the_signaling_connection_and_a_silent_peer_is_dropped():
    """Pings judged on running time (web.liveness) on both sides: 1 s stalls of the whole loop
    (a starved process) with a 0.2 s heartbeat keep the connections, also when a stall comes
    right after the server's ping (aiohttp's heartbeat, its pong awaited 0.1 s of wall time,
    closed the connection then: its timer ran before the pong was read), while a peer that
    answers no ping is dropped and counted (``lost:no_answer``), not refused."""
    import time

    import aiohttp

    server = SignalingServer(SignalConfig(port=0, heartbeat_s=0.2), TOKEN)
    await server.start()
    try:
        client = SignalingClient(server.url, "r", "expert", TOKEN, heartbeat_s=0.2)
        await client.join()
        heard = []

        async def listen():  # as the link does: always reading (pings are answered there)
            while True:
                heard.append((await client.receive()).type)

        listening = asyncio.create_task(listen())
        for _ in range(3):
            time.sleep(1.0)  # the loop stalls: server and client alike
            await asyncio.sleep(0.5)
        assert client._ws is not None and not client._ws.closed
        assert server.counters["lost:no_answer"] == 0
        assert not any(k.startswith("refused:") for k in server.counters)
        # a follower that joins and then answers nothing (its process hung)
        async with aiohttp.ClientSession() as s, s.ws_connect(server.url, autoping=False) as ws:
            join = {"type": "join", "room": "r", "role": "follower", "token": TOKEN,
                    "protocol": 1}  # fmt: skip
            await ws.send_json(join)
            for _ in range(2):  # the server's ping comes, and the whole loop stalls at once
                while (m := await ws.receive(timeout=30)).type != aiohttp.WSMsgType.PING:
                    assert m.type == aiohttp.WSMsgType.TEXT, m  # (joined)
                time.sleep(1.0)
                await ws.pong(m.data)  # answered, after the stall: read after the timers
            await asyncio.sleep(0.3)
            assert not ws.closed and server.counters["lost:no_answer"] == 0
            while (await ws.receive(timeout=30)).type not in (
                aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED
            ):  # fmt: skip
                pass
        dropped = "the silent follower dropped"
        await until(lambda: server.counters["lost:no_answer"] == 1, 30.0, what=dropped)
        assert not any(k.startswith("refused:") for k in server.counters), server.counters
        assert not client._ws.closed  # the expert stays, told the follower came and left
        await until(lambda: heard == ["peer_joined", "peer_left"], 30.0, what="peer_left")
        listening.cancel()
        await client.close()
    finally:
        await server.stop()

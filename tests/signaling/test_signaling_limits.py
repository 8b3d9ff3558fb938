"""Connection floods: handshake deadline, per-address and total caps, EMFILE log lines, and a
slow-loris run (a legitimate pair joins while 300 half-open sockets are held)."""

import asyncio
import errno
import logging
import secrets
import tempfile

import pytest
from signaling_helpers import assert_clean_logs, running_server

from humantele.signaling.client import SignalingClient
from humantele.signaling.guard import RateLimitedLog
from humantele.signaling.messages import Offer
from humantele.signaling.slowloris import hold_sockets, measure, start_server
from waits import until

TOKEN = "limits-token"


async def _pair(server, room="r1"):
    expert = SignalingClient(server.url, room, "expert", TOKEN)
    follower = SignalingClient(server.url, room, "follower", TOKEN)
    await asyncio.wait_for(asyncio.gather(expert.join(), follower.join()), 20)
    return expert, follower


@pytest.mark.parametrize("partial", [b"", b"GET /ws HTTP/1.1\r\nHost: x\r\n"])
async def test_a_connection_without_a_websocket_handshake_is_closed_after_the_deadline(
    partial, caplog
):
    caplog.set_level(logging.INFO)
    async with running_server(TOKEN, handshake_timeout_s=0.5) as server:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(partial)

        async def trickle() -> bytes:  # one more header byte every 0.1 s, never finished
            while True:
                try:
                    return await asyncio.wait_for(reader.read(100), 0.1)
                except TimeoutError:
                    writer.write(b"X" if partial else b"")

        # the server closes it (EOF); today's server would hold it for an hour
        assert await asyncio.wait_for(trickle(), 15) == b""
        assert server.counters["closed:handshake_timeout"] == 1
        writer.close()
        await until(lambda: server.guard.open_connections == 0, what="the server to forget it")
        expert, follower = await _pair(server)  # and it still serves
        await expert.close()
        await follower.close()
    assert_clean_logs(caplog.records, TOKEN)


async def test_per_address_cap_refuses_the_excess_and_spares_other_addresses(caplog):
    caplog.set_level(logging.INFO)
    async with running_server(
        TOKEN, max_connections_per_address=3, handshake_timeout_s=60
    ) as server:
        held = await hold_sockets("127.0.0.1", server.port, 8, sources=1, interval_s=0.5)
        await until(lambda: held.closed_by_server >= 5, what="the excess to be refused")
        assert server.guard.per_address["127.0.0.2"] == 3
        expert, follower = await _pair(server)  # from 127.0.0.1: not affected
        assert held.open == 3
        await expert.close()
        await follower.close()
        await held.close()
    assert server.counters["refused:connection_cap"] == 5
    assert_clean_logs(caplog.records, TOKEN)
    assert sum("refused a connection" in r.getMessage() for r in caplog.records) == 1  # limited


async def test_total_cap_makes_room_from_handshakes_never_from_joined_peers(caplog):
    caplog.set_level(logging.INFO)
    async with running_server(TOKEN, max_connections=4, handshake_timeout_s=60) as server:
        expert, follower = await _pair(server)
        held = await hold_sockets("127.0.0.1", server.port, 6, sources=6, interval_s=0.5)
        await until(lambda: held.closed_by_server >= 4, what="the oldest handshakes to make room")
        assert server.counters["closed:evicted"] == 4 and held.open == 2
        await expert.send(Offer(sdp="v=0", id=1))  # the joined pair was spared
        assert await asyncio.wait_for(follower.receive(), 5) == Offer(sdp="v=0", id=1)
        await held.close()
        await until(lambda: server.guard.open_connections == 2, what="the held ones to go")
        # a third WebSocket when every slot is a WebSocket is refused, not the pair
        other = await _pair(server, room="r2")
        third = SignalingClient(server.url, "r3", "expert", TOKEN, connect_timeout_s=2)
        with pytest.raises(ConnectionError):
            await third.join()
        assert server.counters["refused:connection_cap"] >= 1
        for c in (expert, follower, *other):
            await c.close()
    assert_clean_logs(caplog.records, TOKEN)


async def test_accept_errors_become_one_rate_limited_line(caplog):
    caplog.set_level(logging.DEBUG)
    loop = asyncio.get_running_loop()
    original = loop.get_exception_handler()
    async with running_server(TOKEN) as server:
        for _ in range(1000):  # what asyncio reports for every failed accept() retry
            loop.call_exception_handler(
                {
                    "message": "socket.accept() out of system resource",
                    "exception": OSError(errno.EMFILE, "Too many open files"),
                }
            )
        loop.call_exception_handler({"message": "something else", "exception": ValueError()})
    assert loop.get_exception_handler() is original  # put back on stop
    lines = [r for r in caplog.records if "cannot accept connections" in r.getMessage()]
    assert len(lines) == 1 and lines[0].exc_info is None
    assert "Too many open files" in lines[0].getMessage()
    assert server.counters["accept_failed"] == 1000
    # other errors still reach asyncio's own handler
    assert sum("something else" in r.getMessage() for r in caplog.records) == 1


def test_rate_limited_log_says_how_many_lines_it_held_back(caplog):
    caplog.set_level(logging.INFO)
    now = [0.0]
    limited = RateLimitedLog(logging.getLogger("test.limited"), 10.0, clock=lambda: now[0])
    for t in (0.0, 1.0, 2.0, 9.9, 10.0, 10.5, 25.0):
        now[0] = t
        limited.log(logging.INFO, "k", "refused %s", "x")
    limited.log(logging.INFO, "other", "another kind")
    assert [r.getMessage() for r in caplog.records] == [
        "refused x",  # t=0; 1.0, 2.0, 9.9 held back
        "refused x (3 more like this in the last 10 s)",  # t=10; 10.5 held back
        "refused x (1 more like this in the last 10 s)",  # t=25
        "another kind",  # each kind has its own budget
    ]


@pytest.mark.parametrize("sources", [1, 30])
def test_a_pair_joins_while_300_half_open_sockets_are_held(sources):
    """The review's case: a server limited to 256 descriptors (a child process), 300 sockets
    sending a header byte now and then. The old server never let the pair in and logged an
    EMFILE traceback per accept retry."""
    token = secrets.token_urlsafe(12)
    with tempfile.TemporaryFile("w+") as log_file:
        proc, url = start_server(256, token, log_file)
        try:
            result = asyncio.run(measure(url, token, sockets=300, sources=sources))
        finally:
            proc.terminate()
            proc.communicate(timeout=30)
        log_file.seek(0)
        log = log_file.read()
    assert result["pair_join_s"] is not None, result
    assert result["held_when_joining"] >= 16, result  # the attack was in place
    assert "Traceback" not in log
    assert log.count("\n") < 50, log  # rate-limited lines, not one per connection

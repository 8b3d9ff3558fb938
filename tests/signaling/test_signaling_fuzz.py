"""Fuzz of the signaling input path. Whatever clients send (message types, sizes, encodings,
orders, two sockets interleaved, with and without the token, or raw bytes before the
WebSocket handshake), the server closes each bad socket with a code of the protocol, logs
only one-line printable records without traceback and without the token, leaks no room and
no connection, and a legitimate pair still joins and relays afterwards.

``HUMANTELE_FUZZ_EXAMPLES`` sets the examples per test (default 300); the counts reported in
the issue notes come from a run with a larger value.
"""

import asyncio
import contextlib
import itertools
import json
import logging
import os

import aiohttp
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from signaling_helpers import CLOSED, assert_clean_logs, raw_ws, running_server

from fuzz_examples import examples
from humantele.signaling.client import SignalingClient
from humantele.signaling.messages import Offer
from humantele.signaling.server import SignalingServer
from waits import until

TOKEN = "fuzz-token-never-logged"
WRONG = "wrong-token-never-logged-either"
MAX_BYTES = 4096
EXAMPLES = int(os.environ.get("HUMANTELE_FUZZ_EXAMPLES") or examples(300))
CLOSE_CODES = {1000, 1006, 1007, 1009, 4400, 4401, 4403, 4408, 4409, 4503}
"""What a client may see: normal, invalid UTF-8, too big, the application's refusals, and 1006
when the server closed while the client was still sending (the kernel then resets the
connection). Never 1011 (internal error) nor a malformed frame; a server that failed shows in
its log (the checks below), as the old error handler's crash did."""

FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
rooms = itertools.count()

# --- what a client can send -------------------------------------------------------------------

text = st.text(max_size=200)
# 1k-4k characters (1-16 kB of UTF-8: either side of MAX_BYTES): a random piece of text
# repeated to a random length (drawing each character of 4k was 20 ms an example, a third
# of the test's time; the content's variety is in ``text`` and ``nasty``)
long_text = st.builds(
    lambda piece, n: (piece * (n // len(piece) + 1))[:n],
    st.text(min_size=1, max_size=64),
    st.integers(MAX_BYTES // 4, MAX_BYTES),
) | st.just("x" * (2 * MAX_BYTES))
# characters that break logs, frames and encoders, alone, repeated or mixed; inside JSON
# strings may hold lone surrogates too (json.dumps writes them as \ud800 escapes)
nasty_chars = st.sampled_from(
    ["\n", "\r", "\x1b[2K", "\u2028", "\u202e", "\x00", "\ud800", "\U00018cd6", "é", "😀"]
)
nasty = st.one_of(
    st.tuples(nasty_chars, st.integers(1, 400)).map(lambda cn: cn[0] * cn[1]),
    st.lists(nasty_chars | st.characters(), max_size=60).map("".join),
)
json_text = text | nasty
json_scalar = (
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True) | json_text | long_text
)
json_value = st.recursive(
    json_scalar,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(json_text, inner, max_size=4),
    max_leaves=8,
)
types = st.sampled_from(["join", "offer", "answer", "joined", "error", "", "JOIN"]) | json_text


def _join(room: str, role) -> st.SearchStrategy[dict]:
    return st.fixed_dictionaries(
        {"type": st.just("join"), "room": st.just(room), "role": role},
        optional={
            "token": st.sampled_from([TOKEN, WRONG, ""]) | json_text,
            "protocol": st.just(1) | json_value,
        },
    )


def messages(room: str) -> st.SearchStrategy[tuple[str, object]]:
    """(how, payload): text, raw TEXT-frame bytes, binary, ping."""
    roles = st.sampled_from(["expert", "follower"]) | json_value
    objects = st.one_of(
        _join(room, roles),
        _join(room, roles).flatmap(  # one unknown key more
            lambda d: st.tuples(json_text, json_value).map(lambda kv: {**d, kv[0]: kv[1]})
        ),
        st.fixed_dictionaries(
            {"type": st.sampled_from(["offer", "answer"]), "sdp": json_text | long_text},
            optional={"id": json_value},
        ),
        st.dictionaries(st.just("type"), types).flatmap(
            lambda d: st.dictionaries(json_text, json_value, max_size=3).map(lambda e: {**e, **d})
        ),
        json_value,
    )
    as_text = objects.map(lambda o: ("text", json.dumps(o)))  # NaN/Infinity included
    return st.one_of(
        as_text,
        as_text.map(lambda m: ("text", "\ufeff" + m[1])),  # BOM
        as_text.map(lambda m: ("bytes", m[1].encode("utf-16"))),  # not UTF-8
        st.tuples(st.just("text"), text | long_text),
        st.tuples(st.just("bytes"), st.binary(max_size=300)),
        st.tuples(st.just("binary"), st.binary(max_size=300)),
        st.tuples(st.just("ping"), st.binary(max_size=100)),
    )


@st.composite
def sessions(draw) -> tuple[str, list[tuple[int, tuple[str, object]]]]:
    """A room and an interleaved plan for two sockets; each may start with a good join."""
    room = f"fuzz{next(rooms)}"
    plan = []
    for sock, role in ((0, "expert"), (1, "follower")):
        if draw(st.booleans()):
            plan.append((sock, ("text", json.dumps({"type": "join", "room": room,
                                                    "role": role, "token": TOKEN}))))  # fmt: skip
    plan += draw(st.lists(st.tuples(st.integers(0, 1), messages(room)), min_size=1, max_size=8))
    return room, plan


# --- the server and the checks ----------------------------------------------------------------


@pytest.fixture
async def server():
    settings = {"join_timeout_s": 5, "max_message_bytes": MAX_BYTES, "handshake_timeout_s": 5}
    async with running_server(TOKEN, **settings) as s:
        yield s


async def _send(ws: aiohttp.ClientWebSocketResponse, how: str, payload) -> None:
    if ws.closed:
        return
    with contextlib.suppress(ConnectionError, RuntimeError):  # the server may have closed it
        if how == "text":
            await ws.send_str(payload)
        elif how == "bytes":
            await ws.send_frame(payload, aiohttp.WSMsgType.TEXT)  # invalid UTF-8 allowed
        elif how == "binary":
            await ws.send_bytes(payload)
        else:
            await ws.ping(payload)


async def _read_until_closed(ws: aiohttp.ClientWebSocketResponse) -> int | None:
    """Every frame the server sends is valid and every error reason short; the close code."""
    while True:
        m = await ws.receive()
        if m.type == aiohttp.WSMsgType.TEXT:
            msg = json.loads(m.data)
            if msg["type"] == "error":
                assert len(msg["reason"]) <= 200 and msg["reason"].isprintable(), msg
        elif m.type == aiohttp.WSMsgType.ERROR:  # a reset is fine, a bad frame is not
            assert not isinstance(m.data, aiohttp.WebSocketError), m.data
        elif m.type in CLOSED:
            return ws.close_code


async def _still_serves_and_leaks_nothing(server: SignalingServer) -> None:
    await until(lambda: not server.rooms, 10, what="rooms and connections to be freed")
    await until(lambda: server.guard.open_connections == 0, 10, what="connections to close")
    room = f"check{next(rooms)}"
    expert = SignalingClient(server.url, room, "expert", TOKEN)
    follower = SignalingClient(server.url, room, "follower", TOKEN)
    await expert.join()
    await follower.join()
    await expert.receive()  # peer_joined
    await expert.send(Offer(sdp="v=0", id=1))
    assert await asyncio.wait_for(follower.receive(), 5) == Offer(sdp="v=0", id=1)
    await expert.close()
    await follower.close()
    await until(lambda: not server.rooms, 10, what="the check room to go")


@FUZZ
@given(session=sessions())
async def test_any_client_messages_in_any_order(server, session, caplog):
    caplog.set_level(logging.DEBUG)
    caplog.clear()
    _, plan = session
    opened = [await raw_ws(server.url), await raw_ws(server.url)]
    try:
        for sock, (how, payload) in plan:
            await _send(opened[sock][1], how, payload)
        for _, ws in opened:
            await _send(ws, "binary", b"end")  # refused in every state: the server closes now
            code = await asyncio.wait_for(_read_until_closed(ws), 10)
            assert code in CLOSE_CODES, code
    finally:
        for session_, _ in opened:
            await session_.close()
    await _still_serves_and_leaks_nothing(server)
    assert_clean_logs(caplog.records, TOKEN, WRONG)


request_lines = st.builds(
    lambda method, path, version: f"{method} {path} {version}\r\n".encode(errors="replace"),
    st.sampled_from(["GET", "POST", "OPTIONS", "G\nET"]) | text,
    st.sampled_from(["/ws", "/", "/ws?x=1", "*"]) | text,
    st.sampled_from(["HTTP/1.1", "HTTP/1.0", "HTTP/9"]) | text,
)
headers = st.lists(
    st.sampled_from(
        [b"Upgrade: websocket\r\n", b"Connection: Upgrade\r\n", b"Sec-WebSocket-Version: 13\r\n",
         b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n", b"Host: x\r\n",
         b"Content-Length: 5\r\n", b"Transfer-Encoding: chunked\r\n"]
    ) | st.binary(max_size=100),
    max_size=8,
)  # fmt: skip


@FUZZ
@given(
    chunks=st.tuples(
        request_lines, headers, st.sampled_from([b"\r\n", b""]), st.binary(max_size=50)
    )
)
async def test_any_bytes_before_the_websocket_handshake(server, chunks, caplog):
    caplog.set_level(logging.DEBUG)
    caplog.clear()
    line, head, end, body = chunks
    reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
    try:
        writer.write(line + b"".join(head) + end + body)
        writer.write_eof()
        with contextlib.suppress(ConnectionError):
            await asyncio.wait_for(reader.read(), 10)  # answered or closed, within the deadline
    finally:
        writer.close()
    await _still_serves_and_leaks_nothing(server)
    assert_clean_logs(caplog.records, TOKEN)

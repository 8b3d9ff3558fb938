import asyncio
import json
import logging

import pytest
from signaling_helpers import closed_with, raw_ws, running_server

from humantele.config import ConfigError
from humantele.signaling import (
    CLOSE_BAD_MESSAGE,
    CLOSE_JOIN_TIMEOUT,
    CLOSE_OUT_OF_ORDER,
    CLOSE_ROOM_FULL,
    CLOSE_UNAUTHORIZED,
)
from humantele.signaling.client import SignalingClient, SignalingError, SignalingRefused
from humantele.signaling.messages import (
    DEV_TOKEN,
    TOKEN_ENV,
    Answer,
    Offer,
    PeerJoined,
    PeerLeft,
    resolve_token,
)
from humantele.signaling.server import SignalConfig, SignalingServer

TOKEN = "s3cret-Token-that-must-never-be-logged"


@pytest.fixture
async def server():
    async with running_server(TOKEN, join_timeout_s=0.5, max_message_bytes=4096) as s:
        yield s


async def _client(server, role="expert", room="r1", token=TOKEN):
    c = SignalingClient(server.url, room, role, token)
    joined = await c.join()
    return c, joined


async def test_join_relay_and_presence(server):
    expert, joined = await _client(server, "expert")
    assert joined.peer_present is False
    follower, joined = await _client(server, "follower")
    assert joined.peer_present is True
    assert await expert.receive() == PeerJoined(role="follower")
    await expert.send(Offer(sdp="v=0 offer", id=4))
    assert await follower.receive() == Offer(sdp="v=0 offer", id=4)
    await follower.send(Answer(sdp="v=0 answer", id=4))
    assert await expert.receive() == Answer(sdp="v=0 answer", id=4)
    await follower.close()
    assert await expert.receive() == PeerLeft(role="follower")
    # the follower comes back (its old socket is gone) and the expert hears of it
    follower2, joined = await _client(server, "follower")
    assert joined.peer_present is True
    assert await expert.receive() == PeerJoined(role="follower")
    await expert.close()
    await follower2.close()


async def test_many_rooms_are_independent(server):
    clients = []
    for room in ("a", "b", "c"):
        for role in ("expert", "follower"):
            clients.append((await _client(server, role, room))[0])
    assert set(server.rooms) == {"a", "b", "c"}
    for c in clients:
        await c.close()
    await asyncio.sleep(0.05)
    assert server.rooms == {}


@pytest.mark.parametrize("token", ["wrong", ""])
async def test_bad_or_missing_token_is_refused_with_a_reason(server, token, caplog, capsys):
    caplog.set_level(logging.DEBUG)
    with pytest.raises(SignalingRefused) as err:
        await _client(server, token=token)
    assert err.value.code == CLOSE_UNAUTHORIZED and err.value.fatal
    assert "token" in err.value.reason
    assert server.rooms == {}
    # the good token appears nowhere in logs or output, nor does the wrong one
    out = capsys.readouterr()
    for text in (caplog.text, out.out, out.err, str(err.value), repr(err.value)):
        assert TOKEN not in text
        assert not token or token not in text.replace("wrong or missing", "")


async def test_token_never_logged_on_success(server, caplog):
    caplog.set_level(logging.DEBUG)
    c, _ = await _client(server)
    await c.close()
    assert "joined" in caplog.text and TOKEN not in caplog.text
    assert TOKEN not in repr(c)


async def test_third_peer_and_duplicate_role_are_refused(server):
    expert, _ = await _client(server, "expert")
    with pytest.raises(SignalingRefused) as err:
        await _client(server, "expert")
    assert err.value.code == CLOSE_ROOM_FULL and not err.value.fatal
    follower, _ = await _client(server, "follower")
    for role in ("expert", "follower"):
        with pytest.raises(SignalingRefused, match="room full"):
            await _client(server, role)
    # the two peers still work
    await expert.send(Offer(sdp="x"))
    assert (await follower.receive()).type == "offer"
    await expert.close()
    await follower.close()


@pytest.mark.parametrize(
    "payload, code",
    [
        ("not json at all", CLOSE_BAD_MESSAGE),
        (json.dumps({"type": "offer", "sdp": "x"}), CLOSE_OUT_OF_ORDER),  # before join
        (
            json.dumps({"type": "join", "room": "bad room!", "role": "expert", "token": TOKEN}),
            CLOSE_BAD_MESSAGE,
        ),
        (
            json.dumps({"type": "join", "room": "r1", "role": "boss", "token": TOKEN}),
            CLOSE_BAD_MESSAGE,
        ),
        (b"\x00binary", CLOSE_BAD_MESSAGE),
        ("x" * 10_000, 1009),  # oversized
    ],
)
async def test_bad_first_messages_close_only_that_connection(server, payload, code):
    expert, _ = await _client(server, "expert")
    session, ws = await raw_ws(server.url)
    if isinstance(payload, bytes):
        await ws.send_bytes(payload)
    else:
        await ws.send_str(payload)
    assert await closed_with(ws) == code
    await session.close()
    # the server still serves the room
    follower, joined = await _client(server, "follower")
    assert joined.peer_present
    await expert.close()
    await follower.close()


async def test_out_of_order_after_join_closes_that_peer_and_tells_the_other(server):
    expert, _ = await _client(server, "expert")
    session, ws = await raw_ws(server.url)
    await ws.send_str(
        json.dumps({"type": "join", "room": "r1", "role": "follower", "token": TOKEN})
    )
    assert json.loads((await ws.receive()).data)["peer_present"] is True
    assert await expert.receive() == PeerJoined(role="follower")
    await ws.send_str(json.dumps({"type": "offer", "sdp": "x"}))  # followers do not offer
    assert await closed_with(ws) == CLOSE_OUT_OF_ORDER
    assert await expert.receive() == PeerLeft(role="follower")
    await session.close()
    await expert.close()


async def test_second_join_and_silence_are_refused(server):
    session, ws = await raw_ws(server.url)
    join = json.dumps({"type": "join", "room": "r9", "role": "expert", "token": TOKEN})
    await ws.send_str(join)
    await ws.receive()
    await ws.send_str(join)
    assert await closed_with(ws) == CLOSE_OUT_OF_ORDER
    await session.close()
    session, ws = await raw_ws(server.url)  # says nothing: closed after join_timeout_s
    assert await closed_with(ws) == CLOSE_JOIN_TIMEOUT
    await session.close()
    assert server.rooms == {}


async def test_stop_tells_joined_peers_the_server_is_going_away():
    async with running_server(TOKEN) as s:
        c, _ = await _client(s)
        listening = asyncio.create_task(c.receive())  # as a link does
        session, _ = await raw_ws(s.url)  # upgraded, never joins nor reads
        await asyncio.wait_for(s.stop(), 10)
    with pytest.raises(SignalingError, match="code 1001"):
        await asyncio.wait_for(listening, 5)
    await session.close()


def test_token_resolution_and_dev_token_only_on_loopback(monkeypatch):
    monkeypatch.setenv(TOKEN_ENV, "from-env")
    assert resolve_token(None) == "from-env"
    assert resolve_token("configured") == "configured"
    monkeypatch.delenv(TOKEN_ENV)
    assert resolve_token(None) == DEV_TOKEN
    with pytest.raises(ConfigError, match="token"):
        SignalingServer(SignalConfig(host="0.0.0.0", insecure=True))
    # fine with a real token (and TLS, or insecure behind a TLS proxy)
    SignalingServer(SignalConfig(host="0.0.0.0", insecure=True), token="real")


def test_cli_runs_and_refuses_bad_config(tmp_path, capsys):
    from humantele.cli import main

    bad = tmp_path / "signal.toml"
    bad.write_text("port = 70000\n")
    assert main(["signal", "--config", str(bad)]) == 2
    assert "port" in capsys.readouterr().err


def test_shipped_config_is_the_defaults():
    from pathlib import Path

    from humantele.config import load_config

    example = Path(__file__).resolve().parents[2] / "configs" / "signal.toml"
    assert load_config(SignalConfig, example) == SignalConfig()

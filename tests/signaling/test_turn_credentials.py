"""Time-limited TURN credentials (coturn's use-auth-secret REST scheme): the HMAC, the expiry,
the refusal of a bad configuration, the wire entry a peer accepts, and that only an admitted
peer gets them. The real coturn's verdict: tests/transport/test_turn_rest.py."""

import asyncio
import base64
import binascii
import json
import logging
import os
import shutil
import subprocess
import sys

import aiohttp
import pytest

from humantele.config import ConfigError, validate_config
from humantele.signaling.messages import CLOSE_UNAUTHORIZED
from humantele.signaling.server import SignalConfig, SignalingServer
from humantele.signaling.turn import (
    MAX_ISSUED,
    TURN_SECRET_ENV,
    IssuedIceServer,
    TurnConfig,
    TurnIssuer,
    accept_issued,
    load_secret,
    rest_credential,
    rest_username,
)
from waits import until

SECRET = "north-humantele-test-secret"
URL = "turn:127.0.0.1:3478?transport=udp"
TOKEN = "turn-unit-token"

# --- the HMAC ----------------------------------------------------------------------------------


def test_credential_is_base64_hmac_sha1_of_the_username_rfc2202_vector():
    # RFC 2202 test case 2: HMAC-SHA1(key "Jefe", "what do ya want for nothing?")
    expected = binascii.unhexlify("effcdf6ae5eb2fa2d27416d5f184df9c259a7c79")
    got = rest_credential("Jefe", "what do ya want for nothing?")
    assert base64.b64decode(got) == expected


def test_credential_known_answer_made_with_openssl():
    # printf '%s' "1700000000:expert-0a1b2c3d" \
    #   | openssl dgst -sha1 -hmac north-humantele-test-secret -binary | base64
    username = rest_username(1700000000, "expert-0a1b2c3d")
    assert username == "1700000000:expert-0a1b2c3d"
    assert rest_credential(SECRET, username) == "5w2zw5UWomBhcwldPjMx2P7A/eI="


@pytest.mark.skipif(shutil.which("openssl") is None, reason="no openssl program")
def test_credential_agrees_with_openssl_on_a_fresh_username():
    issuer = TurnIssuer(TurnConfig(urls=[URL]), SECRET)
    entry = issuer.issue(issuer.new_peer_id("follower"))
    r = subprocess.run(
        ["openssl", "dgst", "-sha1", "-hmac", SECRET, "-binary"],
        input=entry.username.encode(),
        capture_output=True,
        check=True,
    )
    assert entry.credential == base64.b64encode(r.stdout).decode()


# --- expiry -----------------------------------------------------------------------------------


def test_issued_credential_expires_ttl_after_the_issuers_clock():
    issuer = TurnIssuer(TurnConfig(urls=[URL], ttl_s=600), SECRET, clock=lambda: 1_800_000_000.7)
    entry = issuer.issue("expert-00000001")
    assert entry.username == "1800000600:expert-00000001"
    assert entry.expires == 1_800_000_600
    assert entry.urls == [URL]
    assert entry.credential == rest_credential(SECRET, entry.username)
    assert issuer.refresh_after_s == 300


def test_peer_drops_an_expired_entry_and_keeps_a_fresh_one():
    now = 1_800_000_000
    issuer = TurnIssuer(TurnConfig(urls=[URL], ttl_s=600), SECRET, clock=lambda: now)
    fresh = issuer.issue("a").model_dump()
    issuer.clock = lambda: now - 601
    stale = issuer.issue("b").model_dump()
    good, problems = accept_issued([stale, fresh], now=now)
    assert [e.username for e in good] == ["1800000600:a"]
    assert len(problems) == 1 and "expired 1 s ago" in problems[0]
    assert stale["credential"] not in problems[0]


@pytest.mark.parametrize("ttl", [0, 59, 86401, float("nan")])
def test_ttl_out_of_bounds_is_refused(ttl):
    with pytest.raises(ConfigError, match="ttl_s"):
        validate_config(SignalConfig, {"turn": {"urls": [URL], "ttl_s": ttl}}, "signal.toml")


def test_ttl_defaults_to_one_hour():
    assert TurnConfig().ttl_s == 3600


# --- refusal of a bad configuration ---------------------------------------------------------


def _server(turn: dict, monkeypatch, secret: str | None) -> SignalingServer:
    if secret is None:
        monkeypatch.delenv(TURN_SECRET_ENV, raising=False)
    else:
        monkeypatch.setenv(TURN_SECRET_ENV, secret)
    return SignalingServer(SignalConfig(port=0, turn=TurnConfig(**turn)), TOKEN)


def test_no_turn_section_issues_nothing_and_needs_no_secret(monkeypatch):
    s = _server({}, monkeypatch, None)
    assert s._turn is None


@pytest.mark.parametrize(
    "secret, message",
    [
        (None, f"set turn.secret_file or ${TURN_SECRET_ENV}"),
        ("", "is empty"),
        ("   \n", "is empty"),
        ("short-secret", "is 12 characters; at least 16"),
        ("a secret with spaces in it", "printable ASCII without spaces"),
        ("s\u00e9cret-with-an-accent-here", "printable ASCII"),
    ],
)
def test_urls_without_a_usable_secret_stop_the_start(monkeypatch, secret, message):
    with pytest.raises(ConfigError, match="turn") as info:
        _server({"urls": [URL]}, monkeypatch, secret)
    assert message in str(info.value)
    if secret and len(secret.strip()) > 3:
        assert secret.strip() not in str(info.value)  # never shows the secret


def test_secret_file_unreadable_missing_or_short_stops_the_start(tmp_path, monkeypatch):
    missing = tmp_path / "nope"
    with pytest.raises(ConfigError, match="turn.secret_file .*cannot read it: No such file"):
        _server({"urls": [URL], "secret_file": missing}, monkeypatch, SECRET)  # file wins
    short = tmp_path / "short"
    short.write_text("tooshort\n")
    with pytest.raises(ConfigError, match="is 8 characters") as info:
        _server({"urls": [URL], "secret_file": short}, monkeypatch, None)
    assert "tooshort" not in str(info.value)
    with pytest.raises(ConfigError, match="not a regular file"):
        _server({"urls": [URL], "secret_file": tmp_path}, monkeypatch, None)
    if os.geteuid() != 0:  # root reads anything
        locked = tmp_path / "locked"
        locked.write_text(SECRET)
        locked.chmod(0)
        with pytest.raises(ConfigError, match="cannot read it: Permission denied"):
            _server({"urls": [URL], "secret_file": locked}, monkeypatch, None)


def test_secret_file_first_line_is_the_secret(tmp_path, monkeypatch):
    f = tmp_path / "turn_secret"
    f.write_text(SECRET + "\n")
    f.chmod(0o600)
    monkeypatch.delenv(TURN_SECRET_ENV, raising=False)
    assert load_secret(TurnConfig(urls=[URL], secret_file=f)) == SECRET


@pytest.mark.parametrize(
    "turn, field",
    [
        ({"urls": ["http://x"]}, "turn.urls.0"),
        ({"urls": ["stun:127.0.0.1:3478"]}, "turn.urls.0"),
        ({"urls": ["turn:a b"]}, "turn.urls.0"),
        ({"secret_file": "/etc/turn_secret"}, "urls is empty"),
        ({"urls": [URL], "ttl_s": "3600"}, "ttl_s"),
    ],
)
def test_bad_turn_fields_are_refused_with_their_name(turn, field):
    with pytest.raises(ConfigError) as info:
        validate_config(SignalConfig, {"turn": turn}, "signal.toml")
    assert field in str(info.value)


@pytest.mark.e2e  # runs the CLI (the fast lane leaves it out)
def test_the_cli_refuses_a_short_secret_in_one_line_exit_2(tmp_path):
    conf = tmp_path / "signal.toml"
    conf.write_text(f'port = 0\n[turn]\nurls = ["{URL}"]\n')
    env = {**os.environ, "HUMANTELE_TOKEN": "cli-token", TURN_SECRET_ENV: "abc"}
    r = subprocess.run(
        [sys.executable, "-m", "humantele", "signal", "--config", str(conf)],
        capture_output=True, text=True, timeout=120, env=env,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert "turn: the shared secret in $HUMANTELE_TURN_SECRET is 3 characters" in r.stderr


def test_the_issuer_never_shows_its_secret():
    issuer = TurnIssuer(TurnConfig(urls=[URL]), SECRET)
    entry = issuer.issue("expert-1")
    assert SECRET not in repr(issuer) and SECRET not in str(vars(issuer))
    assert entry.credential not in repr(entry) and entry.credential not in str(entry)


# --- the wire entry on the peer's side ------------------------------------------------------


def _entry(**kw) -> dict:
    e = {"urls": [URL], "username": "4000000000:expert-1", "credential": "A" * 27 + "="}
    e.update(kw)
    return e


@pytest.mark.parametrize(
    "bad, where",
    [
        ({"urls": []}, "urls"),
        ({"urls": ["http://evil"]}, "urls.0"),
        ({"urls": "turn:x"}, "urls"),
        ({"username": "expert-1"}, "username"),
        ({"username": "4000000000:a:b"}, "username"),
        ({"username": "4000000000:" + "x" * 65}, "username"),
        ({"credential": "not base64!"}, "credential"),
        ({"credential": "QUJD"}, "credential"),  # base64, but not 20 bytes
        ({"credential": None}, "credential"),
        ({"extra": 1}, "extra"),
    ],
)
def test_peer_drops_a_malformed_entry_with_a_clear_reason(bad, where):
    good, problems = accept_issued([_entry(**bad), _entry()], now=1_800_000_000)
    assert len(good) == 1  # the good one is kept
    assert len(problems) == 1 and problems[0].startswith(f"entry 0: {where}")
    assert "AAAA" not in problems[0]


def test_peer_takes_at_most_max_issued_entries():
    good, problems = accept_issued([_entry()] * (MAX_ISSUED + 3), now=1_800_000_000)
    assert len(good) == MAX_ISSUED and problems == [
        f"entries beyond the first {MAX_ISSUED} dropped"
    ]


def test_a_non_list_or_garbage_item_is_dropped_not_raised():
    good, problems = accept_issued([1, "x", None, [1]], now=0)
    assert good == [] and len(problems) == 4
    assert accept_issued(None) == ([], [])


# --- only admitted peers get credentials -----------------------------------------------------


async def _messages(ws, n_max: int = 3, timeout: float = 5.0) -> list:
    out = []
    while len(out) < n_max:
        m = await ws.receive(timeout=timeout)
        if m.type != aiohttp.WSMsgType.TEXT:
            break
        out.append(json.loads(m.data))
    return out


async def test_only_an_admitted_peer_gets_credentials(caplog):
    caplog.set_level(logging.DEBUG)
    issuer = TurnIssuer(TurnConfig(urls=[URL], ttl_s=600), SECRET)
    server = SignalingServer(SignalConfig(port=0), TOKEN, turn_issuer=issuer)
    await server.start()
    try:
        async with aiohttp.ClientSession() as http:
            # a wrong token: refused, and nothing in what it got looks like a credential
            async with http.ws_connect(server.url) as ws:
                await ws.send_str(json.dumps({"type": "join", "room": "r", "role": "expert",
                                              "token": "wrong"}))  # fmt: skip
                got = await _messages(ws)
                assert [m["type"] for m in got] == ["error"]
                assert ws.close_code == CLOSE_UNAUTHORIZED
            # an admitted peer: its joined message carries a valid credential
            async with http.ws_connect(server.url) as ws:
                await ws.send_str(json.dumps({"type": "join", "room": "r", "role": "expert",
                                              "token": TOKEN}))  # fmt: skip
                joined = json.loads((await ws.receive(timeout=5)).data)
                assert joined["type"] == "joined"
                good, problems = accept_issued(joined["ice_servers"])
                assert problems == [] and len(good) == 1
                entry = good[0]
                assert entry.urls == [URL] and entry.username.split(":")[1].startswith("expert-")
                assert entry.credential == rest_credential(SECRET, entry.username)
                # a second expert for the same room is refused: it gets none
                async with http.ws_connect(server.url) as ws2:
                    await ws2.send_str(json.dumps({"type": "join", "room": "r",
                                                   "role": "expert", "token": TOKEN}))  # fmt: skip
                    got = await _messages(ws2)
                    assert [m["type"] for m in got] == ["error"]
                    assert "ice_servers" not in json.dumps(got)
        assert server.counters["turn:issued"] == 1
        assert not any(SECRET in k for k in server.counters)
        # the server's log names the peer id, never the credential or the secret
        assert entry.username.split(":")[1] in caplog.text
        assert SECRET not in caplog.text and entry.credential not in caplog.text
    finally:
        await server.stop()


async def test_a_joined_peer_gets_a_fresh_credential_before_the_last_expires():
    t = [2_000_000_000.0]
    issuer = TurnIssuer(TurnConfig(urls=[URL], ttl_s=600), SECRET, clock=lambda: t[0])
    issuer.refresh_after_s = 0.2  # the real interval is ttl_s / 2
    server = SignalingServer(SignalConfig(port=0), TOKEN, turn_issuer=issuer)
    await server.start()
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.url) as ws:
            await ws.send_str(json.dumps({"type": "join", "room": "r", "role": "follower",
                                          "token": TOKEN}))  # fmt: skip
            joined = json.loads((await ws.receive(timeout=5)).data)
            (first,), _ = accept_issued(joined["ice_servers"], now=t[0])
            t[0] += 300
            renewed = json.loads((await ws.receive(timeout=10)).data)
        assert renewed["type"] == "ice_servers"
        (fresh,), problems = accept_issued(renewed["ice_servers"], now=t[0])
        assert problems == []
        assert (first.expires, fresh.expires) == (2_000_000_600, 2_000_000_900)
        assert fresh.username.split(":")[1] == first.username.split(":")[1]  # same peer id
        assert fresh.credential == rest_credential(SECRET, fresh.username)
        await asyncio.sleep(0.5)  # its socket closed: no more renewals (the task ended)
        issued = server.counters["turn:issued"]
        await asyncio.sleep(0.5)
        assert server.counters["turn:issued"] == issued
    finally:
        await server.stop()


async def test_without_turn_the_joined_message_is_unchanged():
    server = SignalingServer(SignalConfig(port=0), TOKEN)
    await server.start()
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.url) as ws:
            await ws.send_str(json.dumps({"type": "join", "room": "r", "role": "follower",
                                          "token": TOKEN}))  # fmt: skip
            joined = json.loads((await ws.receive(timeout=5)).data)
        assert joined == {"type": "joined", "room": "r", "role": "follower",
                          "peer_present": False}  # fmt: skip
    finally:
        await server.stop()


def test_issued_entry_round_trips_through_the_wire_model():
    issuer = TurnIssuer(TurnConfig(urls=[URL, "turns:turn.example.org:5349"]), SECRET)
    entry = issuer.issue("follower-1")
    again = IssuedIceServer.model_validate_json(entry.model_dump_json())
    assert again == entry


# --- the link takes them --------------------------------------------------------------------


async def test_a_link_takes_the_issued_credentials_and_their_renewals_and_drops_bad_ones(
    caplog,
):
    caplog.set_level(logging.DEBUG)
    from humantele.transport import LinkConfig, PeerLink

    t = [2_000_000_000.0]
    issuer = TurnIssuer(TurnConfig(urls=[URL], ttl_s=600), SECRET, clock=lambda: t[0])
    issuer.refresh_after_s = 0.2
    server = SignalingServer(SignalConfig(port=0), TOKEN, turn_issuer=issuer)
    await server.start()
    link = PeerLink("follower", LinkConfig(signaling_url=server.url, token=TOKEN, room="r"))
    link._wall_clock = lambda: t[0]
    task = asyncio.create_task(link.run())
    try:
        await until(lambda: link._issued)
        first = link._issued[0]
        assert first.expires == 2_000_000_600
        (ice,) = link._ice_servers()  # what the next RTCPeerConnection gets
        assert (ice.urls, ice.username, ice.credential) == (
            [URL],
            first.username,
            rest_credential(SECRET, first.username),
        )
        t[0] += 300
        await until(lambda: link._issued[0].expires == 2_000_000_900)
        # a renewal whose entries are all bad: dropped with an error, the last good ones kept
        good = link._issued
        link._take_issued([{"urls": ["http://x"], "username": "u", "credential": "c"}])
        assert link._issued == good and link.counters.dropped["signaling:bad_ice_server"] == 1
        # the issued ones expire and no fresh one comes: the next connection goes without
        t[0] += 10_000
        issuer.refresh_after_s = 3600
        assert link._ice_servers() == []
        assert link.counters.dropped["signaling:expired_ice_server"] >= 1
        assert "TURN server from the signaling server dropped: entry 0: urls.0" in caplog.text
        assert first.credential not in caplog.text and SECRET not in caplog.text
    finally:
        await link.close()
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        await server.stop()


def test_a_joined_message_with_garbage_ice_servers_still_parses():
    from humantele.signaling.messages import SERVER_MESSAGE, Joined, parse

    msg = parse(SERVER_MESSAGE, json.dumps({
        "type": "joined", "room": "r", "role": "expert", "peer_present": False,
        "ice_servers": [{"urls": 3}, "x", None],
    }))  # fmt: skip
    assert isinstance(msg, Joined)
    good, problems = accept_issued(msg.ice_servers, now=0)
    assert good == [] and len(problems) == 3


def test_no_shipped_config_carries_a_turn_password():
    import tomllib
    from pathlib import Path

    configs = Path(__file__).resolve().parents[2] / "configs"
    files = sorted(configs.glob("*.toml"))
    assert files
    for path in files:
        data = tomllib.loads(path.read_text())
        for role in ("expert", "follower"):
            for server in data.get(role, {}).get("link", {}).get("ice_servers", []):
                assert "credential" not in server and "username" not in server, path.name
        assert "secret" not in data.get("turn", {}), path.name  # only secret_file, or the env

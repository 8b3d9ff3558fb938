"""Who may use the pages: the console's WebSocket takes only the run's key, the headset feed
only the pairing code; a page without it is told why (close 4401) and takes no page's place,
wrong guesses are throttled, and neither secret reaches the stats."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import stat

import aiohttp
import pytest

from humantele.expert.console import ConsoleConfig, ConsoleServer
from humantele.follower.feed import FeedConfig, RendererFeed
from humantele.web.credential import (
    CLOSE_THROTTLED,
    CLOSE_UNAUTHORIZED,
    PAIRING_CODE_ENV,
    PAIRING_FILE,
    Credential,
    Verdict,
    normalize_code,
    pairing_code,
)


class Session:
    recorder = None

    def __init__(self) -> None:
        self.commands: list = []

    def snapshot(self) -> dict:
        return {"link": {"state": "connected", "pose_age_ms": 5.0}}

    def pose_at(self, t):
        return None

    def start_scan(self):
        self.commands.append("start")

    def stop_scan(self):
        self.commands.append("stop")

    def set_clutch(self, on):
        self.commands.append(("clutch", on))


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


async def refused(http: aiohttp.ClientSession, url: str) -> tuple[int | None, str]:
    """What the server says to a WebSocket it does not take: its close code and reason."""
    async with http.ws_connect(url) as ws:
        await ws.send_str(json.dumps({"type": "scan", "action": "start"}))  # too late: closed
        msg = await ws.receive(timeout=10)
        while msg.type not in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED):
            msg = await ws.receive(timeout=10)
        return ws.close_code, str(msg.extra or "")


async def test_console_takes_only_its_key_and_a_refused_page_takes_no_place(tmp_path, caplog):
    caplog.set_level(logging.DEBUG)
    session = Session()
    server = ConsoleServer(
        ConsoleConfig(port=0, captures_dir=str(tmp_path / "c")), None, session, key="k" * 22
    )
    await server.start()
    try:
        assert server.url == f"{server.address}#key={'k' * 22}"
        assert server.banner().endswith(f"#key={'k' * 22}")
        base = f"ws://127.0.0.1:{server.port}/ws"
        async with aiohttp.ClientSession() as http:
            for url in (base, f"{base}?key=", f"{base}?key={'k' * 21}x", f"{base}?key=kk"):
                code, _ = await refused(http, url)
                assert code == CLOSE_UNAUTHORIZED, url
            for _ in range(20):  # wrong keys from the page's own address lock nobody out
                assert (await refused(http, f"{base}?key=guess"))[0] == CLOSE_UNAUTHORIZED
            resp = await http.get(base)  # not a WebSocket: a plain 401 with the reason
            assert resp.status == 401 and "#key=" in await resp.text()
            # None of them took the one console's place nor drove the session.
            async with http.ws_connect(server.ws_url) as ws:
                hello = json.loads((await ws.receive(timeout=10)).data)
                assert hello["type"] == "hello"
                await ws.send_str(json.dumps({"type": "scan", "action": "start"}))
                for _ in range(200):
                    if session.commands:
                        break
                    await asyncio.sleep(0.01)
        assert session.commands == ["start"]  # the keyed page's only
        assert server.refused["unauthorized"] == 25 and server.refused["throttled"] == 0
        assert server.refused.get("second_console", 0) == 0
        stats = json.dumps(server.stats())
        assert "k" * 22 not in stats and server.stats()["url"] == server.address
    finally:
        await server.stop()
    assert "k" * 21 not in caplog.text


async def test_the_refusal_reason_reaches_the_page(tmp_path):
    server = ConsoleServer(ConsoleConfig(port=0, captures_dir=str(tmp_path)), None, Session())
    await server.start()
    try:
        async with aiohttp.ClientSession() as http:
            code, reason = await refused(http, f"ws://127.0.0.1:{server.port}/ws?key=wrong")
            assert code == CLOSE_UNAUTHORIZED
            assert "key is missing or wrong" in reason and "#key=" in reason
        assert len(server.key) >= 20  # a new key each run, from the system's randomness
        other = ConsoleServer(ConsoleConfig(port=0), None, Session())
        assert other.key != server.key
    finally:
        await server.stop()


async def test_headset_feed_takes_only_the_pairing_code(tmp_path, monkeypatch):
    monkeypatch.delenv(PAIRING_CODE_ENV, raising=False)
    feed = RendererFeed(FeedConfig(port=0, host="127.0.0.1", tls=False), tmp_path)
    await feed.start()
    try:
        code = feed.code
        assert len(code) == 8 and code.isdigit()
        assert f"pairing code {code[:4]} {code[4:]}" in feed.banner()
        async with aiohttp.ClientSession() as http:
            for url in (feed.address, f"{feed.address}?code={code[:7]}"):
                close, _ = await refused(http, url)
                assert close == CLOSE_UNAUTHORIZED
            spaced = f"{feed.address}?code={code[:4]}%20{code[4:]}"  # as typed, with a space
            async with http.ws_connect(spaced) as ws:
                feed.publish("link", {"state": "connected"})
                msg = json.loads((await ws.receive(timeout=10)).data)
                assert msg["type"] == "link"
        assert feed.refused["unauthorized"] == 2
        assert code not in json.dumps(feed.stats())
    finally:
        await feed.stop()
    # Kept in the state dir, owner-only: the headset paired once stays paired after a restart.
    path = tmp_path / PAIRING_FILE
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert pairing_code(tmp_path) == code
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    other = pairing_code(blocked / "state")  # cannot be kept: this run's code all the same
    assert len(other) == 8 and other.isdigit()
    monkeypatch.setenv(PAIRING_CODE_ENV, "1234-5678")
    assert RendererFeed(FeedConfig(port=0), tmp_path).code == "12345678"
    monkeypatch.setenv(PAIRING_CODE_ENV, "1234")
    with pytest.raises(ValueError, match="8 digits"):
        pairing_code(tmp_path)


async def test_wrong_codes_are_throttled_on_the_feed(tmp_path):
    feed = RendererFeed(FeedConfig(port=0, host="127.0.0.1", tls=False), tmp_path)
    await feed.start()
    try:
        wrong = "00000000" if feed.code != "00000000" else "11111111"
        async with aiohttp.ClientSession() as http:
            codes = []
            for _ in range(8):
                close, _ = await refused(http, f"{feed.address}?code={wrong}")
                codes.append(close)
            assert codes[:5] == [CLOSE_UNAUTHORIZED] * 5
            assert codes[-1] == CLOSE_THROTTLED
            close, _ = await refused(http, feed.url)  # even the right one waits now
            assert close == CLOSE_THROTTLED
        assert feed.refused["throttled"] >= 3
    finally:
        await feed.stop()


def test_credential_throttle_refills_and_compares_whole_codes():
    clock = Clock()
    c = Credential("12345678", rate_hz=0.2, burst=3, normalize=normalize_code, clock=clock)
    assert c.check(None, "a") is Verdict.MISSING
    assert [c.check("1234567", "a") for _ in range(3)] == [Verdict.WRONG] * 3
    assert c.check("12345678", "a") is Verdict.THROTTLED  # out of budget: not even compared
    assert c.check("1234 5678", "b") is Verdict.OK  # another address has its own budget
    clock.t += 5.0  # one guess back (0.2 a second)
    assert c.check("1234-5678", "a") is Verdict.OK
    assert c.check("123456789", "b") is Verdict.WRONG
    assert c.check("\u0661" * 8, "b") is Verdict.WRONG  # not ASCII digits: no crash, no match


def test_console_key_from_the_environment(monkeypatch):
    monkeypatch.setenv("HUMANTELE_CONSOLE_KEY", "a-key-of-twenty-chars")
    assert ConsoleServer(ConsoleConfig(port=0), None, Session()).key == "a-key-of-twenty-chars"
    monkeypatch.setenv("HUMANTELE_CONSOLE_KEY", "short")
    with pytest.raises(ValueError, match="16"):
        ConsoleServer(ConsoleConfig(port=0), None, Session())


def test_a_paired_headset_gets_through_a_flood_of_wrong_codes_from_other_addresses():
    """Issue 34 §4: 3,874 wrong codes in 26 s from 200 addresses spent the shared budget, and
    the headset with the right code from its own address was refused 13 times in 13."""
    clock = Clock()
    c = Credential("12345678", normalize=normalize_code, clock=clock)  # the feed's settings
    assert c.check("12345678", "10.0.0.50") is Verdict.OK  # the headset paired earlier
    verdicts, refused, tries = [], 0, 0
    for i in range(26 * 149):
        clock.t = i / 149
        verdicts.append(c.check("87654321", f"127.0.0.{2 + i % 200}"))
        if i % 298 == 0:  # the headset reconnects every 2 s
            tries += 1
            refused += c.check("1234 5678", "10.0.0.50") is not Verdict.OK
    assert tries == 13 and refused == 0
    # the throttle still holds the guesses: the shared budget's 50 + 2 a second
    assert verdicts.count(Verdict.WRONG) <= 50 + 2 * 26
    assert c.check("12345678", "10.0.0.99") is Verdict.THROTTLED  # a new address waits
    # the paired address's own wrong guesses still spend its own budget
    assert [c.check("0", "10.0.0.50") for _ in range(6)][-1] is Verdict.THROTTLED

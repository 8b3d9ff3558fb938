"""A user-space WAN emulator: an asyncio UDP relay that adds delay, jitter and loss.

This kernel has no ``netem``, so a long link is emulated by a relay in front of a server (the
TURN server)::

    client A --+                                  +--> upstream (TURN server)
               +--> [relay: client-facing port] --+
    client B --+      one upstream socket per client, so the server sees one 5-tuple each

Every datagram, in each direction, is held for ``delay_s + x(t)`` (never less than 0) and
dropped with probability ``loss`` (independent per datagram, from a seeded generator, so a run
is repeatable given the same arrival times). The jitter ``x(t)`` is a process in time, not a
draw per datagram: an Ornstein-Uhlenbeck process (AR(1) sampled at each arrival,
``x' = a x + jitter_s sqrt(1 - a^2) N(0, 1)`` with ``a = exp(-dt / jitter_corr_s)``) of
stationary standard deviation ``jitter_s`` and correlation time ``jitter_corr_s`` (default
50 ms): datagrams close together see nearly the same extra delay, as on a real link whose
jitter is its queues' (Wi-Fi, cellular) and as netem's ``delay X Y Z%`` correlation intends
(netem correlates successive draws per packet; this correlates them over time, so the
figures do not depend on the packet rate). ``jitter_corr_s = 0`` draws each datagram
independently (the old model: with FIFO order, a dense stream then waits for the running
maximum of its predecessors' draws, e.g. held 111-211 ms on average for 60 +- 20 ms).
With ``bandwidth_kbps`` each direction is also a link of that rate: a datagram waits for the
ones before it to be sent (its size at the rate) before its delay starts, and one that would
wait longer than ``queue_s`` for the link is dropped (a tail-drop queue; counted in
``overflow``), as netem's ``rate`` with a ``limit``. Without ``reorder`` the link is a FIFO: a
datagram never leaves before the one that arrived before it (it waits for it, as in a real
queue, whose delay falls no faster than time passes; with the correlated jitter this adds
up to about ``jitter_s^2 / jitter_corr_s`` to the mean hold: 5-8 ms at 60 +- 20 ms); with
``reorder`` jittered datagrams may overtake each other, as Linux netem does.
The model (:class:`LinkModel`) takes its clock as arguments, so it is tested by hand.

A path through a TURN server that crosses the relay once each way (only one peer uses the
relay's port, the other talks to the server directly) gets exactly one ``delay_s`` each way.
If both peers use the relay, a datagram crosses it twice and gets twice the delay.

Datagrams are read on the asyncio loop and sent, when due, by one thread per direction
(asyncio's timers wake only to the whole millisecond; a thread's timed wait to ~0.1 ms). The
counters record the hold actually given (``held_mean_s``, ``held_max_s``). A datagram's
arrival is the kernel's receive timestamp (``SO_TIMESTAMPNS``; where there is none, the time
it is read), so a loop held up for a while (the daemons' real-time threads preempt it on a
busy machine) does not turn a smooth stream into a burst the rate-limited link then drops:
the datagrams are read late but queued as they arrived (``read_lag_max_s`` says how late;
the sockets ask for a 4 MiB receive buffer to hold them meanwhile).

Usage::

    relay = UdpRelay(("127.0.0.1", 3478), NetemConfig(delay_s=0.004, jitter_s=0.001, loss=0.01))
    host, port = await relay.start()       # point clients at turn:host:port
    ...
    print(relay.counters.as_dict())
    await relay.close()
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import logging
import math
import random
import socket
import struct
import sys
import threading
import time
from dataclasses import asdict, dataclass, field

from pydantic import Field

from humantele.config import ConfigModel

log = logging.getLogger(__name__)

Address = tuple[str, int]
_MAX_DATAGRAM = 65535
_CMSG_SPACE = socket.CMSG_SPACE(16) if hasattr(socket, "CMSG_SPACE") else 0
# a datagram due within this is sent now: a timed wait cannot be shorter than its wake-up
_EARLY_S = 20e-6
_RCVBUF = 4 << 20  # bytes asked for each socket's receive buffer (the kernel caps it)
# Linux's receive timestamps (a timespec per datagram); Python does not name it: 35 on x86 and
# ARM (asm-generic/socket.h); elsewhere none (the read time stands in)
_STAMP = getattr(socket, "SO_TIMESTAMPNS", 35 if sys.platform == "linux" else None)
_TIMESPEC = struct.Struct("@qq")  # tv_sec, tv_nsec (64-bit Linux)


def timestamp_arrivals(sock: socket.socket) -> None:
    """Ask the kernel to stamp each datagram ``sock`` receives, with a large receive buffer
    (both best effort)."""
    for opt, value in ((socket.SO_RCVBUF, _RCVBUF), (_STAMP, 1)):
        if opt is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, opt, value)


def receive(sock: socket.socket) -> tuple[bytes, Address, float, float]:
    """Read one datagram: (data, source address, arrival, now) on ``time.monotonic``'s clock
    (s). The arrival is the kernel's receive timestamp (see :func:`timestamp_arrivals`)
    mapped from the wall clock, never later than now; without one, now. Raises as
    ``recvmsg``."""
    data, ancillary, _flags, addr = sock.recvmsg(_MAX_DATAGRAM, _CMSG_SPACE)
    now = time.monotonic()
    for level, kind, raw in ancillary:
        if level == socket.SOL_SOCKET and kind == _STAMP and len(raw) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(raw)
            ago = time.time() - (sec + nsec * 1e-9)
            return data, addr, now - min(max(ago, 0.0), 10.0), now
    return data, addr, now, now


class NetemConfig(ConfigModel):
    """Impairment applied to every datagram in each direction (SI units: s, probability)."""

    delay_s: float = Field(0.0, ge=0.0, le=10.0)  # one-way delay added per crossing
    jitter_s: float = Field(0.0, ge=0.0, le=10.0)  # std dev of the delay's jitter process
    jitter_corr_s: float = Field(0.05, ge=0.0, le=10.0)  # its correlation time; 0: independent
    loss: float = Field(0.0, ge=0.0, le=1.0)  # probability a datagram is dropped
    reorder: bool = False  # jittered datagrams may overtake each other
    seed: int = 0  # seeds the delay and loss generators
    max_queue: int = Field(10_000, ge=1)  # datagrams held per direction; beyond: dropped
    bandwidth_kbps: float = Field(0.0, ge=0.0, le=10_000_000.0)  # link rate each way; 0: none
    queue_s: float = Field(0.2, gt=0.0, le=10.0)  # longest wait for the link (bandwidth_kbps)
    max_clients: int = Field(64, ge=1)  # client addresses given an upstream socket


@dataclass
class DirectionCounters:
    """What one direction of the relay did with its datagrams."""

    received: int = 0
    forwarded: int = 0
    lost: int = 0  # dropped by the loss model
    overflow: int = 0  # dropped because max_queue datagrams were already held
    send_errors: int = 0  # the socket refused the datagram (buffer full, no listener)
    bytes_forwarded: int = 0
    held_sum_s: float = 0.0  # total time forwarded datagrams were held (s)
    held_max_s: float = 0.0
    read_lag_max_s: float = 0.0  # longest a datagram waited to be read after it arrived

    @property
    def held_mean_s(self) -> float | None:
        """Mean hold (arrival to send) of forwarded datagrams (s), or None if none."""
        return self.held_sum_s / self.forwarded if self.forwarded else None

    def as_dict(self) -> dict[str, object]:
        return {**asdict(self), "held_mean_s": self.held_mean_s}


@dataclass
class RelayCounters:
    """``up``: clients -> upstream; ``down``: upstream -> clients."""

    up: DirectionCounters = field(default_factory=DirectionCounters)
    down: DirectionCounters = field(default_factory=DirectionCounters)
    clients: int = 0  # client addresses seen (each got an upstream socket)
    clients_refused: int = 0  # datagrams from new clients beyond max_clients

    def as_dict(self) -> dict[str, object]:
        return {
            "up": self.up.as_dict(),
            "down": self.down.as_dict(),
            "clients": self.clients,
            "clients_refused": self.clients_refused,
        }


class LinkModel:
    """One direction's impairments as a model with its clock passed in (s, any monotonic
    origin): whether a datagram is lost, and when it is due out (see the module docstring).
    Seeded by ``config.seed`` and ``name``; no threads, no sockets."""

    def __init__(self, config: NetemConfig, name: str) -> None:
        self.config = config
        self.rng = random.Random(f"{config.seed}:{name}")
        self.jitter = 0.0  # the jitter process x(t) at jitter_t (s)
        self.jitter_t: float | None = None  # when it was last drawn (s)
        self.last_due = 0.0
        self.link_free = 0.0  # when the rate-limited link has sent all it holds (s)

    def lost(self) -> bool:
        """Draw whether the next datagram is lost (probability ``config.loss``)."""
        return self.config.loss > 0.0 and self.rng.random() < self.config.loss

    def delay(self, t: float) -> float:
        """The delay (s, >= 0) of a datagram leaving the link at ``t`` (s): ``delay_s`` plus
        the jitter process at ``t``, advanced from its last draw (exact for any step)."""
        cfg = self.config
        if cfg.jitter_s <= 0.0:
            return cfg.delay_s
        tau, last = cfg.jitter_corr_s, self.jitter_t
        if tau <= 0.0 or last is None:
            self.jitter = self.rng.gauss(0.0, cfg.jitter_s)
        else:
            a = math.exp(-max(0.0, t - last) / tau)
            self.jitter = a * self.jitter + cfg.jitter_s * math.sqrt(1.0 - a * a) * self.rng.gauss(
                0.0, 1.0
            )
        self.jitter_t = t if last is None else max(t, last)
        return max(0.0, cfg.delay_s + self.jitter)

    def due(self, t: float, size: int) -> float | None:
        """When a datagram of ``size`` bytes that arrived at ``t`` (s) leaves the relay, or
        None if the rate-limited link's queue would hold it longer than ``queue_s`` (it is
        dropped). Call only for datagrams not lost; arrivals in order of ``t``."""
        cfg = self.config
        sent = t
        if cfg.bandwidth_kbps > 0.0:  # wait for the link, then the datagram's own time on it
            start = max(t, self.link_free)
            if start - t > cfg.queue_s:
                return None
            self.link_free = sent = start + size * 8.0 / (cfg.bandwidth_kbps * 1e3)
        due = sent + self.delay(sent)
        if not cfg.reorder:
            due = max(due, self.last_due)
            self.last_due = due
        return due


class _Direction:
    """One direction: draws the fate of each datagram (on the event loop, :class:`LinkModel`)
    and sends it when it is due (from its own thread: asyncio timers wake only to the
    millisecond, a thread's timed wait to ~0.1 ms)."""

    def __init__(self, config: NetemConfig, counters: DirectionCounters, name: str) -> None:
        self.config = config
        self.counters = counters
        self.model = LinkModel(config, name)
        self.heap: list[tuple[float, int, float, bytes, socket.socket, Address | None]] = []
        self.seq = 0
        self.cond = threading.Condition()
        self.stopped = False
        self.thread = threading.Thread(target=self._run, name=f"netem-{name}", daemon=True)
        self.thread.start()

    def push(self, data: bytes, sock: socket.socket, addr: Address | None, t: float) -> None:
        """Take a datagram that arrived at ``t`` (time.monotonic, s); send it on ``sock`` (to
        ``addr``, or connected when None) once due, unless it is lost."""
        c = self.counters
        c.received += 1
        if self.model.lost():
            c.lost += 1
            return
        with self.cond:
            due = None if len(self.heap) >= self.config.max_queue else self.model.due(t, len(data))
            if due is None:
                c.overflow += 1
                return
            self.seq += 1
            heapq.heappush(self.heap, (due, self.seq, t, data, sock, addr))
            if self.heap[0][1] == self.seq:  # the new datagram is the next to leave
                self.cond.notify()

    def _run(self) -> None:
        c = self.counters
        while True:
            with self.cond:
                while not self.stopped:
                    if not self.heap:
                        self.cond.wait()
                        continue
                    wait = self.heap[0][0] - time.monotonic()
                    if wait <= _EARLY_S:
                        break
                    self.cond.wait(wait)
                if self.stopped:
                    return
                now = time.monotonic()
                due = []
                while self.heap and self.heap[0][0] <= now + _EARLY_S:
                    due.append(heapq.heappop(self.heap))
            for _due, _seq, t, data, sock, addr in due:  # in order, outside the lock
                try:
                    if addr is None:
                        sock.send(data)
                    else:
                        sock.sendto(data, addr)
                except OSError as exc:  # buffer full, nobody listening, closed
                    log.debug("relay send failed: %s", exc)
                    c.send_errors += 1
                    continue
                held = time.monotonic() - t
                c.forwarded += 1
                c.bytes_forwarded += len(data)
                c.held_sum_s += held
                c.held_max_s = max(c.held_max_s, held)

    def stop(self) -> None:
        """Stop the sender thread; held datagrams are discarded."""
        with self.cond:
            self.stopped = True
            self.heap.clear()
            self.cond.notify()
        self.thread.join(timeout=5.0)


class UdpRelay:
    """A UDP relay between a client-facing port and ``upstream`` that impairs both directions
    with ``config`` (see the module docstring). Counters in ``counters``."""

    def __init__(
        self,
        upstream: Address,
        config: NetemConfig | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
    ) -> None:
        self.upstream = upstream
        self.config = config or NetemConfig()
        self.host = host
        self.port = port
        self.counters = RelayCounters()
        self._sock: socket.socket | None = None
        self._clients: dict[Address, socket.socket] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._up: _Direction | None = None
        self._down: _Direction | None = None

    @property
    def address(self) -> Address:
        """The client-facing (host, port); valid after :meth:`start`."""
        if self._sock is None:
            raise RuntimeError("the relay is not started")
        return self._sock.getsockname()[:2]

    async def start(self) -> Address:
        """Bind the client-facing port and start relaying; returns its (host, port)."""
        if self._sock is not None:
            return self.address
        loop = asyncio.get_running_loop()
        self._loop = loop
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setblocking(False)
            timestamp_arrivals(sock)
            sock.bind((self.host, self.port))
        except OSError:
            sock.close()
            raise
        self._up = _Direction(self.config, self.counters.up, "up")
        self._down = _Direction(self.config, self.counters.down, "down")
        self._sock = sock
        loop.add_reader(sock.fileno(), self._on_client_readable)
        log.info("udp relay %s -> %s, %s", self.address, self.upstream, self.config)
        return self.address

    async def close(self) -> None:
        """Stop relaying; held datagrams are discarded."""
        for d in (self._up, self._down):
            if d is not None:
                d.stop()
        self._up = self._down = None
        for sock in [*self._clients.values(), self._sock]:
            if sock is not None and self._loop is not None:
                self._loop.remove_reader(sock.fileno())
                sock.close()
        self._clients.clear()
        self._sock = None

    async def __aenter__(self) -> UdpRelay:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _on_client_readable(self) -> None:
        sock, loop, up = self._sock, self._loop, self._up
        assert sock is not None and loop is not None and up is not None
        while True:
            try:
                data, addr, t, now = receive(sock)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # e.g. ICMP port unreachable reported on this socket
                log.debug("relay client socket: %s", exc)
                return
            addr = addr[:2]
            upstream = self._clients.get(addr)
            if upstream is None:
                upstream = self._new_client(addr)
                if upstream is None:
                    continue
            up.counters.read_lag_max_s = max(up.counters.read_lag_max_s, now - t)
            up.push(data, upstream, None, t)

    def _new_client(self, addr: Address) -> socket.socket | None:
        if len(self._clients) >= self.config.max_clients:
            self.counters.clients_refused += 1
            return None
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setblocking(False)
            timestamp_arrivals(sock)
            sock.bind((self.host, 0))
            sock.connect(self.upstream)
        except OSError as exc:
            log.warning("relay: no upstream socket for %s: %s", addr, exc)
            sock.close()
            self.counters.clients_refused += 1
            return None
        self._clients[addr] = sock
        self.counters.clients += 1
        assert self._loop is not None
        self._loop.add_reader(sock.fileno(), self._on_upstream_readable, sock, addr)
        return sock

    def _on_upstream_readable(self, sock: socket.socket, client: Address) -> None:
        loop, down, front = self._loop, self._down, self._sock
        assert loop is not None and down is not None and front is not None
        while True:
            try:
                data, _addr, t, now = receive(sock)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # ECONNREFUSED: a datagram sent up found no listener
                log.debug("relay upstream socket: %s", exc)
                self.counters.up.send_errors += 1
                return
            down.counters.read_lag_max_s = max(down.counters.read_lag_max_s, now - t)
            down.push(data, front, client, t)

"""The daemons' guard against connection floods, shared by the signaling server and the two
pages (the expert's console, the follower's headset page): caps on open connections (in total
and per client address), a deadline from TCP accept to the end of the request's headers (the
TLS handshake included), and rate-limited log lines (never a traceback per connection, per
malformed HTTP request, per failed request or per failed ``accept()``).

It hooks aiohttp's low-level :class:`aiohttp.web.Server`, which hears of every connection
(``connection_made`` / ``connection_lost``) before any byte of HTTP is parsed, so a slow or
partial handshake is timed and an excess connection dropped without parsing HTTP ourselves.
With TLS, :meth:`GuardedServer.listen` accepts plain TCP and admits the connection *before*
the TLS handshake (:class:`_TlsGate`): a socket that never finishes its handshake is counted
and timed like any other, where asyncio's own TLS server would hold it unseen for a minute.

For the pages (``pages=True``): a connection over the per-address cap closes the oldest one
from that address still in its handshake instead of being refused (on loopback every client
shares one address, the sonographer's browser too); a connection whose WebSocket is
established with the page's credential (:meth:`GuardedServer.established`) leaves the caps
(it is held back for the credentialed pages, whose number the page server caps itself); and
after each plain HTTP request the deadline runs again for the response to be read
(:data:`RESPONSE_TIMEOUT_S`), aiohttp's keep-alive timer timing the next request's headers.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import os
import resource
import ssl
import time
from collections import Counter
from collections.abc import Callable, Iterable
from typing import Any

from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError
from aiohttp.web import RequestHandler

from humantele.web.text import printable

ACCEPT_BACKLOG = 32
"""Listen backlog; asyncio also accepts up to this many connections at once, before the guard
hears of any of them."""
PAGE_LISTEN_BACKLOG = 1024
"""The pages' queue of connections the kernel has completed and the daemon not yet accepted
(capped by net.core.somaxconn): in a flood of connects the page's own is queued, not dropped
to come back after the client's SYN retry (1, 3, 7 s...). asyncio still accepts at most
``ACCEPT_BACKLOG`` at a time, so the descriptors taken before the guard hears of them stay
bounded."""
RESPONSE_TIMEOUT_S = 60.0
"""A page's client has this long to read a response (three.js, 1.3 MB, on a slow headset
link) before its connection is closed (a slow reader holding a place)."""
FD_RESERVE = 2 * ACCEPT_BACKLOG + 16
"""Descriptors kept free beyond ``max_connections``: one accept burst, the connections being
closed to make room, and the process's own (listening socket, logs...)."""
_ACCEPT_ERRNOS = frozenset({errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM})


class RateLimitedLog:
    """At most one line per ``key`` every ``interval_s`` seconds; the next line of that key says
    how many were held back meanwhile."""

    def __init__(
        self,
        logger: logging.Logger,
        interval_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._log = logger
        self.interval_s = interval_s
        self._clock = clock
        self._last: dict[object, float] = {}
        self._held: Counter[object] = Counter()

    def log(self, level: int, key: object, msg: str, *args: object) -> None:
        """Log ``msg % args`` unless ``key`` logged less than ``interval_s`` ago."""
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self.interval_s:
            self._held[key] += 1
            return
        self._last[key] = now
        held = self._held.pop(key, 0)
        if held:
            msg += f" ({held} more like this in the last {self.interval_s:.0f} s)"
        self._log.log(level, msg, *args)


class HttpErrorLog(logging.LoggerAdapter):
    """The logger given to aiohttp's request handlers. aiohttp logs every malformed request
    (no Host header, bad line...) at ERROR with a traceback, and every request whose handler
    failed (a static file not opened: out of descriptors) too; here each is one rate-limited
    line with the client's address and the reason, quoted, counted in ``counters``
    (``bad_http``, ``handler_error``). Everything else passes unchanged."""

    def __init__(
        self, logger: logging.Logger, name: str = "signaling", counters: Counter[str] | None = None
    ) -> None:
        super().__init__(logger, {})
        self._limited = RateLimitedLog(logger)
        self.server_name = name
        self.counters = counters if counters is not None else Counter()

    def log(self, level: int, msg: object, *args: object, **kwargs: Any) -> None:
        exc = kwargs.get("exc_info")
        if isinstance(exc, HttpProcessingError):
            self.counters["bad_http"] += 1
            where = printable(str(args[0])) if args else "?"
            self._limited.log(
                logging.INFO, "bad_http", "%s: bad HTTP request from %s: %s %s",
                self.server_name, where, exc.code, printable(exc.message),
            )  # fmt: skip
            return
        if isinstance(exc, Exception) and level >= logging.ERROR:
            self.counters["handler_error"] += 1
            self._limited.log(
                logging.WARNING, ("error", type(exc).__name__), "%s: %s: %s: %s",
                self.server_name, printable(str(msg) % args if args else str(msg)),
                type(exc).__name__, printable(str(exc)),
            )  # fmt: skip
            return
        super().log(level, msg, *args, **kwargs)


def fd_soft_limit() -> int | None:
    """This process's soft limit on open descriptors (RLIMIT_NOFILE), None if unlimited."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    return None if soft == resource.RLIM_INFINITY else soft


def open_descriptors() -> int:
    """Descriptors this process has open now (0 where /proc is not there)."""
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return 0


def page_connection_cap(configured: int, held_back: int, logger: logging.Logger, name: str) -> int:
    """A page server's ``max_connections``: ``configured``, lowered so that it, the
    ``held_back`` credentialed pages and :data:`FD_RESERVE` take at most half of the
    descriptors this process has left (the daemon's other work needs the rest)."""
    limit = fd_soft_limit()
    if limit is None:
        return configured
    free = limit - open_descriptors() - FD_RESERVE - held_back
    cap = max(8, min(configured, free // 2))
    if cap < configured:
        logger.warning(
            "%s: max_connections lowered from %d to %d to fit the descriptor limit "
            "(ulimit -n %d)", name, configured, cap, limit,
        )  # fmt: skip
    return cap


def _address(transport: asyncio.BaseTransport) -> str:
    peer = transport.get_extra_info("peername")
    return str(peer[0]) if isinstance(peer, tuple) and peer else str(peer)


class GuardedServer(web.Server):
    """aiohttp's low-level server with connection caps and a handshake deadline.

    A connection beyond ``max_per_address`` open ones from one client address is aborted at
    once (with ``pages``: it closes the oldest one from that address still in its handshake,
    if there is one). When ``max_connections`` are open, a new connection closes the oldest
    one still in its handshake (a legitimate handshake takes milliseconds, a slow loris holds
    on), or is aborted if every open one is past it. A connection not past its handshake
    (:meth:`handshake_done`, :meth:`established`) ``handshake_timeout_s`` seconds after accept
    is closed. ``counters`` counts each case; ``logger`` gets the log lines (and aiohttp's,
    through :class:`HttpErrorLog`), each starting with ``name``; ``kwargs`` go to aiohttp's
    request handler.
    """

    def __init__(
        self,
        handler: Callable[[web.BaseRequest], Any],
        *,
        max_connections: int,
        max_per_address: int,
        handshake_timeout_s: float,
        counters: Counter[str],
        logger: logging.Logger,
        name: str = "signaling",
        pages: bool = False,
        **kwargs: Any,
    ) -> None:
        super().__init__(handler, logger=HttpErrorLog(logger, name, counters), **kwargs)
        self.max_connections = max_connections
        self.max_per_address = max_per_address
        self.handshake_timeout_s = handshake_timeout_s
        self.counters = counters
        self.name = name
        self.pages = pages
        self.per_address: Counter[str] = Counter()
        self.held_back: set[RequestHandler] = set()  # established: outside the caps
        self._admitted: dict[RequestHandler, str] = {}
        self._deadlines: dict[RequestHandler, asyncio.TimerHandle] = {}
        self._tls_pending: dict[RequestHandler, asyncio.Transport] = {}
        self._log = RateLimitedLog(logger)

    @property
    def open_connections(self) -> int:
        """Connections admitted under the caps and not yet closed."""
        return len(self._admitted)

    @property
    def in_handshake(self) -> int:
        """Connections whose deadline runs (TLS, headers, or idle between requests)."""
        return len(self._deadlines)

    def connection_made(self, handler: RequestHandler, transport: asyncio.Transport) -> None:
        super().connection_made(handler, transport)
        if self._tls_pending.pop(handler, None) is not None:
            return  # admitted at TCP accept (:class:`_TlsGate`); its deadline runs on
        self.admit(handler, transport)

    def admit(self, handler: RequestHandler, transport: asyncio.Transport) -> bool:
        """Count a new connection in, or refuse it (aborted); whether it was admitted."""
        where = _address(transport)
        if self.per_address[where] >= self.max_per_address:
            oldest = self._oldest_in_handshake(where) if self.pages else None
            if oldest is None:
                self._refuse(
                    transport, where, "address", f"{self.max_per_address} connections open from it"
                )
                return False
            self._close_handshake(oldest, "evicted", "to make room for its address")
        if len(self._admitted) >= self.max_connections:
            oldest = self._oldest_in_handshake()
            if oldest is None:
                self._refuse(transport, where, "total", f"{self.max_connections} open")
                return False
            self._close_handshake(oldest, "evicted", "to make room")
        self._admitted[handler] = where
        self.per_address[where] += 1
        self._arm(handler)
        return True

    def _oldest_in_handshake(self, where: str | None = None) -> RequestHandler | None:
        for h in self._deadlines:  # insertion order: oldest first
            if where is None or self._admitted.get(h) == where:
                return h
        return None

    def _arm(self, handler: RequestHandler, timeout_s: float | None = None) -> None:
        self._deadlines[handler] = asyncio.get_running_loop().call_later(
            max(self.handshake_timeout_s, timeout_s or 0.0), self._expire, handler
        )

    def connection_lost(self, handler: RequestHandler, exc: BaseException | None = None) -> None:
        super().connection_lost(handler, exc)
        self.release(handler)

    def release(self, handler: RequestHandler) -> None:
        """Forget a connection (closed, or its TLS handshake failed)."""
        self.handshake_done(handler)
        self._tls_pending.pop(handler, None)
        self.held_back.discard(handler)
        where = self._admitted.pop(handler, None)
        if where is not None:
            self.per_address[where] -= 1
            if self.per_address[where] <= 0:
                del self.per_address[where]

    def handshake_done(self, handler: RequestHandler) -> None:
        """``handler``'s connection is a WebSocket now (or a request is being handled, or it
        closed): its handshake deadline no longer applies."""
        deadline = self._deadlines.pop(handler, None)
        if deadline is not None:
            deadline.cancel()

    def request_done(self, handler: RequestHandler) -> None:
        """A plain HTTP request on ``handler`` has its answer, about to be sent: the deadline
        runs again, :data:`RESPONSE_TIMEOUT_S` for the client to read it (a slow reader is
        closed then; a closed connection is not re-armed). The next request's headers are
        timed by aiohttp's keep-alive timer (``keepalive_timeout``: the header timeout) from
        the end of the response."""
        if handler in self._admitted and handler not in self._deadlines:
            self._arm(handler, RESPONSE_TIMEOUT_S)

    def established(self, handler: RequestHandler) -> None:
        """``handler`` is a credentialed page's WebSocket: no deadline, and it no longer counts
        against the caps (the page server caps those pages itself)."""
        self.handshake_done(handler)
        where = self._admitted.pop(handler, None)
        if where is not None:
            self.per_address[where] -= 1
            if self.per_address[where] <= 0:
                del self.per_address[where]
            self.held_back.add(handler)

    def _refuse(self, transport: asyncio.Transport, where: str, key: str, why: str) -> None:
        self.counters["refused:connection_cap"] += 1
        # not now: aiohttp's handler must start before it hears the connection is lost
        asyncio.get_running_loop().call_soon(transport.abort)
        self._log.log(
            logging.WARNING, ("cap", key), "%s: refused a connection from %s: %s",
            self.name, printable(where), why,
        )  # fmt: skip

    def _expire(self, handler: RequestHandler) -> None:
        self._deadlines.pop(handler, None)
        what = "request" if self.pages else "WebSocket"
        self._close_handshake(
            handler, "handshake_timeout", f"no {what} within {self.handshake_timeout_s:g} s"
        )

    def _close_handshake(self, handler: RequestHandler, what: str, why: str) -> None:
        """Close a connection still in its handshake."""
        self.handshake_done(handler)
        self.counters[f"closed:{what}"] += 1
        where = self._admitted.get(handler, "?")
        self._log.log(
            logging.INFO, what, "%s: closed a connection from %s in its handshake: %s",
            self.name, printable(where), why,
        )  # fmt: skip
        raw = self._tls_pending.get(handler) or self._connections.get(handler)
        self.release(handler)  # its place is free now (closing it takes a loop turn)
        if handler not in self._tls_pending:
            handler.force_close()
        if raw is not None:  # abort: a close would wait for a slow reader to take the rest
            raw.abort()

    async def listen(
        self,
        host: str,
        port: int,
        ssl_context: ssl.SSLContext | None = None,
        backlog: int = ACCEPT_BACKLOG,
    ) -> asyncio.Server:
        """Listen on ``host:port``; with ``ssl_context``, TLS after admission (see the
        module docstring). With ``pages``, the kernel's queue is :data:`PAGE_LISTEN_BACKLOG`
        long while asyncio accepts ``backlog`` at a time. The listening server (close it to
        stop)."""
        loop = asyncio.get_running_loop()
        if ssl_context is None:
            server = await loop.create_server(self, host, port, backlog=backlog)
        else:
            server = await loop.create_server(
                lambda: _TlsGate(self, ssl_context), host, port, backlog=backlog
            )
        if self.pages:
            for ts in server.sockets:  # listen() again: only the kernel's queue grows
                with ts.dup() as sock:  # a new descriptor of the same socket
                    sock.listen(PAGE_LISTEN_BACKLOG)
        return server

    def tls_admit(self, handler: RequestHandler, transport: asyncio.Transport) -> bool:
        """Admit a TCP connection whose TLS handshake is to come (:class:`_TlsGate`)."""
        if not self.admit(handler, transport):
            return False
        self._tls_pending[handler] = transport
        return True

    def tls_failed(self, handler: RequestHandler, exc: BaseException) -> None:
        if handler not in self._admitted:
            return  # closed by us (deadline, eviction): counted there
        self.counters["closed:tls_failed"] += 1
        where = self._admitted.get(handler, "?")
        self.release(handler)
        self._log.log(
            logging.INFO, "tls", "%s: TLS handshake with %s failed: %s",
            self.name, printable(where), printable(str(exc) or type(exc).__name__),
        )  # fmt: skip


class _TlsGate(asyncio.Protocol):
    """A TCP connection admitted by the guard before its TLS handshake; once the handshake is
    done it hands the TLS transport to aiohttp's request handler."""

    def __init__(self, guard: GuardedServer, ctx: ssl.SSLContext) -> None:
        self.guard = guard
        self.ctx = ctx
        self.handler: RequestHandler | None = None
        self.task: asyncio.Task | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        transport.pause_reading()  # the ClientHello waits for start_tls
        self.handler = self.guard()
        if self.guard.tls_admit(self.handler, transport):
            self.task = asyncio.get_running_loop().create_task(self._handshake(transport))

    async def _handshake(self, transport: asyncio.Transport) -> None:
        assert self.handler is not None
        loop = asyncio.get_running_loop()
        try:
            tls = await loop.start_tls(
                transport, self.handler, self.ctx, server_side=True,
                ssl_handshake_timeout=self.guard.handshake_timeout_s,
            )  # fmt: skip
        except asyncio.CancelledError:
            transport.abort()
            self.guard.release(self.handler)
            raise
        except Exception as exc:  # noqa: BLE001 - bad TLS, resets, timeouts: all counted
            transport.abort()
            self.guard.tls_failed(self.handler, exc)
            return
        if tls is None or tls.is_closing():
            self.guard.release(self.handler)
            return
        self.handler.connection_made(tls)

    def connection_lost(self, exc: BaseException | None) -> None:
        if self.task is None and self.handler is not None:
            self.guard.release(self.handler)


class GuardedAppRunner(web.AppRunner):
    """An :class:`aiohttp.web.AppRunner` whose server is a :class:`GuardedServer`
    (``guard_kwargs``); ``guard`` is that server once set up."""

    def __init__(self, app: web.Application, guard_kwargs: dict[str, Any], **kwargs: Any) -> None:
        super().__init__(app, **kwargs)
        self._guard_kwargs = guard_kwargs
        self.guard: GuardedServer | None = None

    async def _make_server(self) -> web.Server:
        loop = asyncio.get_event_loop()
        app = self.app
        app._set_loop(loop)
        app.on_startup.freeze()
        await app.startup()
        app.freeze()
        kwargs = {k: v for k, v in self._kwargs.items() if k != "access_log_class"}
        self.guard = GuardedServer(
            app._handle,  # type: ignore[arg-type]
            request_factory=app._make_request,
            **self._guard_kwargs,
            **kwargs,
        )
        return self.guard


def page_middleware(get_guard: Callable[[], GuardedServer | None]):
    """An aiohttp middleware for a page server: the header deadline stops while a request is
    handled, and runs again once a plain HTTP request has its answer (keep-alive)."""

    @web.middleware
    async def middleware(request: web.Request, handler):
        guard = get_guard()
        if guard is not None:
            guard.handshake_done(request.protocol)  # type: ignore[arg-type]
        try:
            return await handler(request)
        finally:
            if guard is not None and request.protocol not in guard.held_back:
                guard.request_done(request.protocol)  # type: ignore[arg-type]

    return middleware


class AcceptErrorLog:
    """An event-loop exception handler that turns asyncio's "socket.accept() out of system
    resource" (EMFILE and the like, one traceback per retry) into one rate-limited warning; it
    passes every other error to the handler it replaced (and counts them in ``counters``).
    With ``sockets`` (a listener's), only the failures of those sockets are taken (several
    servers may share a loop, each with its handler). :meth:`remove` puts that one back."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        logger: logging.Logger,
        counters: Counter[str],
        name: str = "signaling",
        sockets: Iterable[Any] | None = None,
    ) -> None:
        self._loop = loop
        self._previous = loop.get_exception_handler()
        self._log = RateLimitedLog(logger)
        self.counters = counters
        self.name = name
        self._fds = None if sockets is None else {s.fileno() for s in sockets}
        loop.set_exception_handler(self)

    def _ours(self, context: dict[str, Any]) -> bool:
        if self._fds is None:
            return True
        sock = context.get("socket")
        try:
            return sock is not None and sock.fileno() in self._fds
        except OSError:
            return False

    def __call__(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        exc = context.get("exception")
        if (
            isinstance(exc, OSError)
            and exc.errno in _ACCEPT_ERRNOS
            and "accept" in str(context.get("message", ""))
            and self._ours(context)
        ):
            self.counters["accept_failed"] += 1
            self._log.log(
                logging.WARNING, "accept",
                "%s: cannot accept connections: %s (out of descriptors? lower "
                "max_connections or raise the limit, ulimit -n)", self.name, exc.strerror,
            )  # fmt: skip
        elif self._previous is not None:
            self._previous(loop, context)
        else:
            loop.default_exception_handler(context)

    def remove(self) -> None:
        if self._loop.get_exception_handler() is self:
            self._loop.set_exception_handler(self._previous)


class GuardedPages:
    """A page server (the console's, the headset page's) behind a :class:`GuardedServer`:
    ``start(routes, ...)`` builds the aiohttp app (``routes(app)`` adds its routes), sizes
    the caps from the config (``max_connections``, ``max_clients`` held back,
    ``max_connections_per_address``, ``header_timeout_s``) and listens; ``stop()`` undoes it.
    ``guard``, ``listener`` (its sockets) and ``accept_errors`` are there once started."""

    def __init__(self, name: str, logger: logging.Logger, counters: Counter[str]) -> None:
        self.name, self.logger, self.counters = name, logger, counters
        self.runner: GuardedAppRunner | None = None
        self.listener: asyncio.Server | None = None
        self.accept_errors: AcceptErrorLog | None = None

    @property
    def guard(self) -> GuardedServer | None:
        return None if self.runner is None else self.runner.guard

    async def start(
        self,
        routes: Callable[[web.Application], None],
        cfg: Any,
        middlewares: tuple[Any, ...] = (),
        ssl_context: Any = None,
    ) -> int:
        """Serve; returns the port."""
        app = web.Application(middlewares=[page_middleware(lambda: self.guard), *middlewares])
        routes(app)
        guard = {
            "max_connections": page_connection_cap(
                cfg.max_connections, cfg.max_clients, self.logger, self.name
            ),
            "max_per_address": cfg.max_connections_per_address,
            "handshake_timeout_s": cfg.header_timeout_s,
            "counters": self.counters,
            "logger": self.logger,
            "name": self.name,
            "pages": True,
        }
        self.runner = GuardedAppRunner(
            app, guard, handle_signals=False, access_log=None,
            keepalive_timeout=cfg.header_timeout_s, max_headers=64,
        )  # fmt: skip
        await self.runner.setup()
        assert self.guard is not None
        self.listener = await self.guard.listen(cfg.host, cfg.port, ssl_context)
        self.accept_errors = AcceptErrorLog(
            asyncio.get_running_loop(), self.logger, self.counters, self.name,
            self.listener.sockets,
        )  # fmt: skip
        return self.listener.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        if self.listener is not None:
            self.listener.close()
        if self.runner is not None:
            await self.runner.cleanup()
            self.runner = None
        if self.listener is not None:
            await self.listener.wait_closed()
            self.listener = None
        if self.accept_errors is not None:
            self.accept_errors.remove()
            self.accept_errors = None

"""The signaling server's guard against connection floods: caps on open connections (in total
and per client address), a deadline from TCP accept to the WebSocket upgrade, and rate-limited
log lines (never a traceback per connection, per malformed HTTP request or per failed
``accept()``).

It hooks aiohttp's low-level :class:`aiohttp.web.Server`, which hears of every connection
(``connection_made`` / ``connection_lost``) before any byte of HTTP is parsed, so a slow or
partial handshake is timed and an excess connection dropped without parsing HTTP ourselves.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import resource
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError
from aiohttp.web import RequestHandler

from humantele.signaling.messages import printable

ACCEPT_BACKLOG = 32
"""Listen backlog; asyncio also accepts up to this many connections at once, before the guard
hears of any of them."""
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
    (no Host header, bad line...) at ERROR with a traceback; here that is one rate-limited INFO
    line with the client's address and the reason, quoted. Everything else passes unchanged."""

    def __init__(self, logger: logging.Logger) -> None:
        super().__init__(logger, {})
        self._limited = RateLimitedLog(logger)

    def log(self, level: int, msg: object, *args: object, **kwargs: Any) -> None:
        exc = kwargs.get("exc_info")
        if isinstance(exc, HttpProcessingError):
            where = printable(str(args[0])) if args else "?"
            self._limited.log(
                logging.INFO, "bad_http", "signaling: bad HTTP request from %s: %s %s",
                where, exc.code, printable(exc.message),
            )  # fmt: skip
            return
        super().log(level, msg, *args, **kwargs)


def fd_soft_limit() -> int | None:
    """This process's soft limit on open descriptors (RLIMIT_NOFILE), None if unlimited."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    return None if soft == resource.RLIM_INFINITY else soft


def _address(transport: asyncio.BaseTransport) -> str:
    peer = transport.get_extra_info("peername")
    return str(peer[0]) if isinstance(peer, tuple) and peer else str(peer)


class GuardedServer(web.Server):
    """aiohttp's low-level server with connection caps and a handshake deadline.

    A connection beyond ``max_per_address`` open ones from one client address is aborted at
    once. When ``max_connections`` are open, a new connection closes the oldest one still in
    its handshake (a legitimate handshake takes milliseconds, a slow loris holds on), or is
    aborted if every open one is a WebSocket. A connection not upgraded to a WebSocket (see
    :meth:`handshake_done`) ``handshake_timeout_s`` seconds after accept (TLS handshake done) is
    closed. ``counters`` counts each case; ``logger`` gets the log lines (and aiohttp's, through
    :class:`HttpErrorLog`); ``kwargs`` go to aiohttp's request handler.
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
        **kwargs: Any,
    ) -> None:
        super().__init__(handler, logger=HttpErrorLog(logger), **kwargs)
        self.max_connections = max_connections
        self.max_per_address = max_per_address
        self.handshake_timeout_s = handshake_timeout_s
        self.counters = counters
        self.per_address: Counter[str] = Counter()
        self._admitted: dict[RequestHandler, str] = {}
        self._deadlines: dict[RequestHandler, asyncio.TimerHandle] = {}
        self._log = RateLimitedLog(logger)

    @property
    def open_connections(self) -> int:
        """Connections admitted and not yet closed."""
        return len(self._admitted)

    def connection_made(self, handler: RequestHandler, transport: asyncio.Transport) -> None:
        super().connection_made(handler, transport)
        where = _address(transport)
        if self.per_address[where] >= self.max_per_address:
            self._refuse(
                transport, where, "address", f"{self.max_per_address} connections open from it"
            )
            return
        if len(self._admitted) >= self.max_connections:
            if not self._deadlines:
                self._refuse(transport, where, "total", f"{self.max_connections} open")
                return
            self._close_handshake(next(iter(self._deadlines)), "evicted", "to make room")
        self._admitted[handler] = where
        self.per_address[where] += 1
        self._deadlines[handler] = asyncio.get_running_loop().call_later(
            self.handshake_timeout_s, self._expire, handler
        )

    def connection_lost(self, handler: RequestHandler, exc: BaseException | None = None) -> None:
        super().connection_lost(handler, exc)
        self.handshake_done(handler)
        where = self._admitted.pop(handler, None)
        if where is not None:
            self.per_address[where] -= 1
            if self.per_address[where] <= 0:
                del self.per_address[where]

    def handshake_done(self, handler: RequestHandler) -> None:
        """``handler``'s connection is a WebSocket now (or closed): its handshake deadline no
        longer applies (the join timeout and heartbeats take over)."""
        deadline = self._deadlines.pop(handler, None)
        if deadline is not None:
            deadline.cancel()

    def _refuse(self, transport: asyncio.Transport, where: str, key: str, why: str) -> None:
        self.counters["refused:connection_cap"] += 1
        # not now: aiohttp's handler must start before it hears the connection is lost
        asyncio.get_running_loop().call_soon(transport.abort)
        self._log.log(
            logging.WARNING, ("cap", key), "signaling: refused a connection from %s: %s",
            printable(where), why,
        )  # fmt: skip

    def _expire(self, handler: RequestHandler) -> None:
        self._close_handshake(
            handler, "handshake_timeout", f"no WebSocket within {self.handshake_timeout_s:g} s"
        )

    def _close_handshake(self, handler: RequestHandler, what: str, why: str) -> None:
        """Close a connection still in its handshake."""
        self.handshake_done(handler)
        self.counters[f"closed:{what}"] += 1
        where = self._admitted.get(handler, "?")
        self._log.log(
            logging.INFO, what, "signaling: closed a connection from %s in its "
            "handshake: %s", printable(where), why,
        )  # fmt: skip
        handler.force_close()


class AcceptErrorLog:
    """An event-loop exception handler that turns asyncio's "socket.accept() out of system
    resource" (EMFILE and the like, one traceback per retry) into one rate-limited warning; it
    passes every other error to the handler it replaced (and counts them in ``counters``).
    :meth:`remove` puts that one back."""

    def __init__(
        self, loop: asyncio.AbstractEventLoop, logger: logging.Logger, counters: Counter[str]
    ) -> None:
        self._loop = loop
        self._previous = loop.get_exception_handler()
        self._log = RateLimitedLog(logger)
        self.counters = counters
        loop.set_exception_handler(self)

    def __call__(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        exc = context.get("exception")
        if (
            isinstance(exc, OSError)
            and exc.errno in _ACCEPT_ERRNOS
            and "accept" in str(context.get("message", ""))
        ):
            self.counters["accept_failed"] += 1
            self._log.log(
                logging.WARNING, "accept",
                "signaling: cannot accept connections: %s (out of descriptors? lower "
                "max_connections or raise the limit, ulimit -n)", exc.strerror,
            )  # fmt: skip
        elif self._previous is not None:
            self._previous(loop, context)
        else:
            loop.default_exception_handler(context)

    def remove(self) -> None:
        if self._loop.get_exception_handler() is self:
            self._loop.set_exception_handler(self._previous)

"""Checks on what a browser page sends a daemon: its Origin, and how fast it may send.

Whatever fails a check is dropped and counted by the caller; nothing here raises into a
daemon's loop.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable

from aiohttp import web


def origin_allowed(request: web.Request, also: Iterable[str] = ()) -> bool:
    """True for a request with no ``Origin`` header (a tool, not a browser page), or from the
    page's own origin (``scheme://host[:port]`` as the request's ``Host``), or from ``also``.

    A browser always sends ``Origin`` on a WebSocket upgrade, so this refuses other sites'
    pages (cross-site WebSocket hijacking) without hindering command-line tools."""
    origin = request.headers.get("Origin")
    if origin is None:
        return True
    own = f"{request.scheme}://{request.host}".lower()
    return origin.lower() in {own, *(o.lower() for o in also)}


class MessageBudget:
    """A token bucket: ``rate_hz`` messages a second on average, bursts of up to ``burst``.
    :meth:`take` says whether one more message may be used now."""

    def __init__(
        self, rate_hz: float, burst: int, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.rate_hz = float(rate_hz)
        self.burst = float(burst)
        self.clock = clock
        self.tokens = self.burst
        self.t = clock()

    def take(self) -> bool:
        now = self.clock()
        self.tokens = min(self.burst, self.tokens + (now - self.t) * self.rate_hz)
        self.t = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False

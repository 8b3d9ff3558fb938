"""The signaling server's guard against connection floods: caps on open connections (in total
and per client address), a deadline from TCP accept to the WebSocket upgrade, and rate-limited
log lines. The guard itself is shared with the daemons' pages: :mod:`humantele.web.connguard`.
"""

from humantele.web.connguard import (
    ACCEPT_BACKLOG,
    FD_RESERVE,
    AcceptErrorLog,
    GuardedServer,
    HttpErrorLog,
    RateLimitedLog,
    fd_soft_limit,
)

__all__ = [
    "ACCEPT_BACKLOG",
    "FD_RESERVE",
    "AcceptErrorLog",
    "GuardedServer",
    "HttpErrorLog",
    "RateLimitedLog",
    "fd_soft_limit",
]

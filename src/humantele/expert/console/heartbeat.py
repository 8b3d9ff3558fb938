"""The console's heartbeat: the page pings twice a second and is answered at once with the
expert's clock (a page tells a slow daemon from a lost one by it; docs/console.md, "Slow is
not lost"), and says in each ping how late it reads what it is sent.

A page that reads this late (:data:`PAGE_BEHIND_S`) gets the state and each track's frames
once every :data:`PAGE_BEHIND_EVERY_S` only (the newest) until it catches up: a busy
browser's queue never grows to seconds, it still sees something, and the answers to its
clicks (never held) reach it. A page that stops pinging is released.
"""

from __future__ import annotations

import json
import math

from humantele.expert.console.messages import Ping

PAGE_BEHIND_S = 1.0
PAGE_BEHIND_FOR_S = 2.0
PAGE_BEHIND_EVERY_S = 1.0


class PageLag:
    """How late one page reads what it is sent, from its pings (``time.monotonic``)."""

    def __init__(self) -> None:
        self.behind_s = 0.0  # how late the page read our newest message, at its last ping
        self.behind_at = -math.inf  # when that ping came
        self.trickle: dict[str, float] = {}  # message key -> when last sent while behind

    def on_ping(self, m: Ping, expert_now: float, now: float) -> str:
        """Note the ping's lag (``now``: when it came, ``time.monotonic``); the ``pong`` to
        send back at once (``t``: the expert's clock)."""
        if m.behind_ms is not None:
            self.behind_s, self.behind_at = m.behind_ms / 1000.0, now
        return json.dumps({"type": "pong", "n": m.n, "t": expert_now})

    def behind(self, now: float) -> bool:
        """Whether the page is reading what it is sent more than PAGE_BEHIND_S late."""
        return self.behind_s > PAGE_BEHIND_S and now - self.behind_at < PAGE_BEHIND_FOR_S

    def holds(self, key: str, now: float) -> bool:
        """Whether a state or frame message ``key`` waits because the page is behind (the
        newest is let through once every PAGE_BEHIND_EVERY_S)."""
        if not (key == "state" or key.startswith("frame:")) or not self.behind(now):
            return False
        if now - self.trickle.get(key, -math.inf) < PAGE_BEHIND_EVERY_S:
            return True
        self.trickle[key] = now
        return False

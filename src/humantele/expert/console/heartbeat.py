"""The console's heartbeat: the page pings twice a second and is answered at once with the
expert's clock (a page tells a slow daemon from a lost one by it; docs/console.md, "Slow is
not lost"), and says in each ping how late it reads what it is sent.

A page that reads this late (:data:`PAGE_BEHIND_S`) gets the state and each track's frames
once every :data:`PAGE_BEHIND_EVERY_S` only (the newest) until it catches up: a busy
browser's queue never grows to seconds, it still sees something, and the answers to its
clicks (never held) reach it. A page that stops pinging is released.
"""

from __future__ import annotations

import asyncio
import json
import math
import time

from humantele.expert.console.messages import Ping

PAGE_BEHIND_S = 1.0
PAGE_BEHIND_FOR_S = 2.0
PAGE_BEHIND_EVERY_S = 1.0
STALL_TICK_S = 0.05
STALL_WINDOW_S = 1.0


class PageLag:
    """How late one page reads what it is sent, from its pings (``time.monotonic``)."""

    def __init__(self) -> None:
        self.behind_s = 0.0  # how late the page read our newest message, at its last ping
        self.behind_at = -math.inf  # when that ping came
        self.trickle: dict[str, float] = {}  # message key -> when last sent while behind

    def on_ping(self, m: Ping, expert_now: float, now: float, stall_s: float = 0.0) -> str:
        """Note the ping's lag (``now``: when it came, ``time.monotonic``); the ``pong`` to
        send back at once (``t``: the expert's clock; ``stall_ms``: the longest the daemon's
        event loop was held up of the last STALL_WINDOW_S, :class:`LoopStalls`)."""
        if m.behind_ms is not None:
            self.behind_s, self.behind_at = m.behind_ms / 1000.0, now
        pong = {"type": "pong", "n": m.n, "t": expert_now, "stall_ms": round(stall_s * 1000.0)}
        return json.dumps(pong)

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


class LoopStalls:
    """How long the daemon's event loop was held up (s), as the loop itself sees it: a task
    wakes every STALL_TICK_S and notes how late it woke. A page's pings sample the loop only
    twice a second, and a hold that falls between two of them looks short to the page; the
    pong carries this instead, so a daemon held 0.7 s of every 1 s reads "slow" whatever the
    pings' phase. ``monotonic``: the clock (s), injectable for tests."""

    def __init__(self, monotonic=time.monotonic, tick_s: float = STALL_TICK_S) -> None:
        self.monotonic = monotonic
        self.tick_s = tick_s
        self.due = math.inf  # when the watching task should wake next
        self.stalls: list[tuple[float, float]] = []  # (when noted, how long held, s)

    def note(self, held_s: float, now: float) -> None:
        """The loop was held ``held_s`` up to ``now`` (negative or zero: not held)."""
        if held_s > 0.0:
            self.stalls.append((now, held_s))
        while self.stalls and now - self.stalls[0][0] > STALL_WINDOW_S:
            self.stalls.pop(0)

    def longest(self, now: float) -> float:
        """The longest hold of the last STALL_WINDOW_S (s), the one going on now included."""
        self.note(0.0, now)
        held_now = max(0.0, now - self.due)
        return max([held_now, *(held for _, held in self.stalls)])

    async def run(self) -> None:
        """Watch the loop until cancelled."""
        while True:
            self.due = self.monotonic() + self.tick_s
            await asyncio.sleep(self.tick_s)
            now = self.monotonic()
            self.note(now - self.due, now)

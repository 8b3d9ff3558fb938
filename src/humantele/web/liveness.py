"""Whether a page is still there, judged on the daemon's own running time.

A page that has said nothing (no message, no ping, no pong) for ``ping_every_s`` is pinged (a
WebSocket ping, which the browser answers itself); it is gone when it then says nothing for
``answer_within_s``. Both are counted in the watch's steps (``step_s``), and a step that came
late (more than ``2 * step_s`` after the one before: the daemon's loop or process did not run,
a loaded machine or the host's steal) counts as one step and judges nothing: the answer that
waited in the socket meanwhile is read first. So a daemon that was not running never finds a
page silent, and a page that is really gone (a closed laptop, Wi-Fi lost without a close) is
found within about ``ping_every_s + answer_within_s`` of the daemon's running time.

aiohttp's own heartbeat (``heartbeat=5``: a ping after 5 s, the pong awaited 2.5 s of wall
time) closed answering pages on a loaded machine: after a loop stall its pong timer runs in
the same loop turn as the read of the pong that had come, before the pong resets it, and a
browser starved for 2.5 s is not gone either.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import Counter
from collections.abc import Callable
from typing import Any, Literal

from aiohttp import WSCloseCode, WSMsgType

PING_EVERY_S = 5.0
ANSWER_WITHIN_S = 10.0
STEP_S = 0.5


class PageLiveness:
    """One page's watch (module docstring); ``clock``: monotonic seconds (tests drive it)."""

    def __init__(
        self,
        ping_every_s: float = PING_EVERY_S,
        answer_within_s: float = ANSWER_WITHIN_S,
        step_s: float = STEP_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.ping_every_s = ping_every_s
        self.answer_within_s = answer_within_s
        self.step_s = step_s
        self.clock = clock
        self.late_steps = 0  # steps that came late: the daemon did not run meanwhile
        self.pings = 0
        self._quiet_s = 0.0  # running time since the page last said something
        self._waiting_s: float | None = None  # running time since the ping, if unanswered
        self._last_step = clock()

    def heard(self) -> None:
        """The page said something (any message, a ping or a pong)."""
        self._quiet_s = 0.0
        self._waiting_s = None

    def step(self) -> Literal["ping", "gone"] | None:
        """One step of the watch, every ``step_s``: whether to ping the page, or it is gone."""
        now = self.clock()
        dt, self._last_step = now - self._last_step, now
        late = dt > 2.0 * self.step_s
        if late:
            self.late_steps += 1
            dt = self.step_s
        if self._waiting_s is not None:
            self._waiting_s += dt
            if self._waiting_s >= self.answer_within_s and not late:
                return "gone"
            return None
        self._quiet_s += dt
        if self._quiet_s >= self.ping_every_s and not late:
            self._waiting_s = 0.0
            self.pings += 1
            return "ping"
        return None


async def receive_answering(ws: Any, live: PageLiveness) -> Any:
    """The next message of ``ws`` (an aiohttp WebSocket opened with ``autoping=False``) that is
    not a ping or a pong: pings are answered, and anything from the peer is noted in ``live``."""
    while True:
        msg = await ws.receive()
        if msg.type in (WSMsgType.TEXT, WSMsgType.BINARY, WSMsgType.PING, WSMsgType.PONG):
            live.heard()
        if msg.type == WSMsgType.PING:
            with contextlib.suppress(ConnectionError, RuntimeError):
                await ws.pong(msg.data)
            continue
        if msg.type != WSMsgType.PONG:
            return msg


async def watch_socket(ws: Any, live: PageLiveness, counters: Counter[str] | None = None) -> None:
    """Ping ``ws``'s peer when quiet, close it when it answers nothing (counted in
    ``counters["lost:no_answer"]``), as ``live`` judges; until ``ws`` closes."""
    try:
        while not ws.closed:
            await asyncio.sleep(live.step_s)
            verdict = live.step()
            if verdict == "ping":  # (a peer that reads nothing may hold the drain)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(ws.ping(), live.step_s)
            elif verdict == "gone":
                if counters is not None:
                    counters["lost:no_answer"] += 1
                await ws.close(code=WSCloseCode.GOING_AWAY, message=b"no answer")
                return
    except (ConnectionError, RuntimeError):
        pass

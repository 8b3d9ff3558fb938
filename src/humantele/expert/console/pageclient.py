"""One open console page: what it was sent and has drawn, per track, and how late it reads.

The transports keep their per-page state here (:mod:`.transport_jpeg`: the frames in flight;
:mod:`.transport_webcodecs`: the keyframe it waits for, the newest it was sent); the
heartbeat its lag (:class:`~humantele.expert.console.heartbeat.PageLag`).
"""

from __future__ import annotations

from collections import deque

from aiohttp import web

from humantele.expert.console.frames import TRACKS
from humantele.expert.console.heartbeat import PageLag
from humantele.web.guard import MessageBudget
from humantele.web.pagesocket import PageClient

IN_FLIGHT = 2  # JPEG frames of a track sent to a page and not yet drawn; more wait


class ConsolePage(PageClient):
    """A console page: the frames it was sent and has drawn (``seq`` per track)."""

    def __init__(self, ws: web.WebSocketResponse, budget: MessageBudget) -> None:
        super().__init__(ws, budget)
        self.transport = "jpeg"
        self.lag = PageLag()
        self.last_drawn: dict[str, int] = {}
        self.echo_at: dict[str, float] = {}  # when the page last said it drew (monotonic)
        # JPEG frames sent and not yet drawn, per track (seq, when sent): a page that draws
        # slower than frames come gets the newest when it is ready, not a queue in its socket.
        self.in_flight: dict[str, deque[tuple[int, float]]] = {t: deque() for t in TRACKS}
        self.need_key = dict.fromkeys(TRACKS, True)  # encoded: waiting for a keyframe
        self.encoded_sent = 0  # numbers the encoded frames' message keys (never coalesced)
        self.sent_seq: dict[str, int] = {}  # the newest encoded frame sent, per track

    def can_take(self, track: str, now: float, timeout_s: float) -> bool:
        """Whether a JPEG frame of ``track`` may go now (fewer than IN_FLIGHT not drawn; one
        sent more than ``timeout_s`` ago counts as drawn)."""
        q = self.in_flight[track]
        while q and now - q[0][1] > timeout_s:
            q.popleft()
        return len(q) < IN_FLIGHT

    def drawn(self, track: str, seq: int) -> None:
        q = self.in_flight[track]
        while q and q[0][0] <= seq:
            q.popleft()

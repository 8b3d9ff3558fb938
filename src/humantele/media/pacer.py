"""A pacer for the follower's outgoing RTP: a frame's packets leave spread at a rate, not in
one burst (aiortc has none; WebRTC's paces at 2.5 times its estimate).

Why (issue 31): libvpx's real-time rate control over- and undershoots a frame when the picture
changes (the sim US from dark to the first image in contact: one 53 kB frame at a 500 or
1000 kbit/s target, where a frame's budget is 3-6 kB). Sent at once, such a frame and the
other track's packets overflow a thin link's queue (a 1500 kbit/s link with a 0.2 s tail-drop
queue holds 37.5 kB): measured on the emulated link, 43-100 kB of one track in 100 ms before
each run of tail drops, then bursts of retransmissions asked for them, dropped in turn. Paced
at 2.5 times the tracks' summed target, a 53 kB frame leaves in 0.14-0.23 s and the link's queue
grows by what the link cannot carry meanwhile (11-28 kB at a 750-1250 kbit/s target), which
it holds.

Only new media packets wait. Retransmissions (an RTP packet whose sequence number is not
newer than the last one of its stream: the expert offers no RTX, so a retransmission is the
original packet) and RTCP leave at once (they are late already, and aiortc sends them from
its receive path, which must not wait), but their size counts against the rate. A packet
never waits more than ``max_delay_s``: a pacer that falls that far behind sends at once
rather than add latency without bound.

A packet retransmitted less than :data:`RESEND_RTT_SHARE` of a round trip ago (``rtt_s()``,
the sender's smoothed RTCP estimate; at least :data:`MIN_RESEND_S`) is not sent again (as
WebRTC's sender, which waits a whole round trip; less here, since the expert asks again a
round trip of its own measure after its last request, which may be shorter): aiortc's
receiver lists every packet still missing in each NACK it sends, one at each new gap, so on
a lossy link of 120 ms or more each lost packet was asked for, and sent, several times in
one round trip, all at once and unpaced (a 12 s run at 60 ms, 3 % loss, 1500 kbit/s: 773
packets sent at once against 253 paced, and 915 tail drops).

On a lossy link (within the last :data:`DUP_HOLD_S`, the expert asked for :data:`DUP_LOSS` or
more of the packets sent again, averaged over about :data:`DUP_WINDOW` packets, or its RTCP
receiver reports, ``loss()``, said it lost that much: they count a repaired packet as
received, so on a link whose repairs arrive they say little), each retransmission is sent
twice, the copy :data:`DUP_AFTER_S` after the first (through the send
:func:`~humantele.media.aiortc_hooks.pace_sender` gives :meth:`Pacer.after_send`), so that a
repair is lost only if both copies are (3 % of 3 % of a packet's: a lost repair is a gap given
up, a keyframe asked for and a freeze, where a second round trip of asking does not fit the
playout delay). New media packets and RTCP are never repeated; the copies' bytes count against
the rate and in ``dup_bytes``.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable

from humantele.media.rtp import rtp_fields, seq_newer

PACE_FACTOR = 2.5  # the pacing rate over the tracks' summed target bit rate (WebRTC's)
MIN_RATE_BPS = 300_000.0  # never pace slower than this (a dark track's low target)
BURST_S = 0.005  # packets due within this leave together (a sleep is ~1 ms at best)
MAX_DELAY_S = 0.5
MIN_RESEND_S = 0.02  # a retransmission is not repeated within this, whatever the round trip
RESEND_RTT_SHARE = 0.75  # nor within this share of the round trip
RESENT_KEPT = 1024  # retransmissions remembered (per pacer)
DUP_LOSS = 0.02  # a link reported losing this share or more gets every retransmission twice
DUP_AFTER_S = 0.005  # the second copy leaves this long after the first (s)
DUP_HOLD_S = 5.0  # a link stays lossy this long after it last looked so (s)
DUP_WINDOW = 200  # the share of packets asked for again: averaged over about this many


def _rtp_stream(data: bytes) -> tuple[int, int] | None:
    """(ssrc, sequence number) of an RTP packet (before SRTP protection), None for RTCP or
    anything not RTP version 2."""
    fields = rtp_fields(data)
    return None if fields is None else (fields[0], fields[1])


class Pacer:
    """Spreads new RTP packets at ``rate_bps()`` (bit/s, read per packet); see the module
    docstring. ``clock`` (s) and ``sleep`` are injectable for tests."""

    def __init__(
        self,
        rate_bps: Callable[[], float],
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], Awaitable[object]] = asyncio.sleep,
        max_delay_s: float = MAX_DELAY_S,
        rtt_s: Callable[[], float | None] = lambda: None,
        loss: Callable[[], float | None] = lambda: None,
        duplicate: bool = True,
    ) -> None:
        self.rate_bps = rate_bps
        self.rtt_s = rtt_s
        self.loss = loss
        self.duplicate = duplicate  # repeat retransmissions on a lossy link
        self.clock = clock
        self.sleep = sleep
        self.max_delay_s = max_delay_s
        self.free_at = 0.0  # when the paced link has sent all it was given (clock, s)
        self._last_seq: dict[int, int] = {}
        self._resent: dict[tuple[int, int], float] = {}  # (ssrc, seq) -> when last resent
        self.resends_skipped = 0  # retransmissions not repeated within a round trip
        self.paced = 0  # new media packets that waited
        self.waited_s = 0.0  # their total wait (s)
        self.immediate = 0  # retransmissions and RTCP, sent at once
        self.overdue = 0  # packets sent at once because they would have waited too long
        self.resent_bytes = 0  # retransmissions sent (first copies), bytes
        self.dups = 0  # second copies of retransmissions sent (a lossy link)
        self.dup_bytes = 0
        self._lossy_until = -float("inf")  # (clock, s)
        self.asked_share = 0.0  # retransmissions asked for per new packet (moving average)
        self._dup_due: set[tuple[int, int]] = set()  # resends after_send is to repeat
        self._dup_tasks: set[asyncio.Task] = set()

    def _rate(self) -> float:
        try:
            rate = float(self.rate_bps())
        except Exception:  # noqa: BLE001 - a rate that cannot be read paces at the floor
            rate = 0.0
        return max(MIN_RATE_BPS, rate) if rate == rate else MIN_RATE_BPS

    def _kind(self, data: bytes) -> tuple[str, tuple[int, int] | None]:
        """``new`` (media), ``resend`` (with its (ssrc, seq)) or ``other`` (RTCP)."""
        stream = _rtp_stream(data)
        if stream is None:
            return "other", None
        ssrc, seq = stream
        last = self._last_seq.get(ssrc)
        if last is not None and not seq_newer(seq, last):
            return "resend", stream  # not newer than the last: a retransmission
        self._last_seq[ssrc] = seq
        return "new", stream

    def _resend_wanted(self, stream: tuple[int, int], now: float) -> bool:
        """Whether to send this retransmission: not if sent again less than
        :data:`RESEND_RTT_SHARE` of a round trip ago (the receiver asked before the last one
        could arrive)."""
        try:
            rtt = self.rtt_s()
        except Exception:  # noqa: BLE001 - no round trip known: the floor
            rtt = None
        known = isinstance(rtt, float | int) and rtt == rtt
        every = max(MIN_RESEND_S, RESEND_RTT_SHARE * rtt) if known else 0.1
        last = self._resent.get(stream)
        if last is not None and now - last < every:
            self.resends_skipped += 1
            return False
        self._resent.pop(stream, None)
        self._resent[stream] = now
        while len(self._resent) > RESENT_KEPT:
            del self._resent[next(iter(self._resent))]
        return True

    def lossy(self, now: float) -> bool:
        """Whether the link loses :data:`DUP_LOSS` or more: the share of packets asked for
        again or the expert's report said so within :data:`DUP_HOLD_S`."""
        try:
            loss = self.loss()
        except Exception:  # noqa: BLE001 - no report read: as none
            loss = None
        reported = isinstance(loss, float | int) and loss == loss and loss >= DUP_LOSS
        if reported or self.asked_share >= DUP_LOSS:
            self._lossy_until = now + DUP_HOLD_S
        return now < self._lossy_until

    async def before_send(self, data: bytes) -> bool:
        """Wait, if ``data`` is a new media packet, until its turn; count its size. False:
        do not send it (a retransmission repeated within a round trip)."""
        now = self.clock()
        kind, stream = self._kind(data)
        if kind == "resend" and stream is not None:
            if not self._resend_wanted(stream, now):
                return False
            self.asked_share += 1.0 / DUP_WINDOW
            self.resent_bytes += len(data)
            if self.duplicate and self.lossy(now):
                if len(self._dup_due) > RESENT_KEPT:  # sends that failed: never after_send
                    self._dup_due.clear()
                self._dup_due.add(stream)
        elif kind == "new":
            self.asked_share *= 1.0 - 1.0 / DUP_WINDOW
        start = max(now, self.free_at)
        self.free_at = start + len(data) * 8.0 / self._rate()
        if kind != "new":
            self.immediate += 1
            return True
        wait = start - now
        if wait > self.max_delay_s:
            self.overdue += 1
            self.free_at = now + len(data) * 8.0 / self._rate()
            return True
        if wait > BURST_S:
            self.paced += 1
            self.waited_s += wait
            await self.sleep(wait)
        return True

    def after_send(self, data: bytes, send: Callable[[bytes], Awaitable[object]]) -> None:
        """After ``data`` was sent: if :meth:`before_send` found it a retransmission on a
        lossy link, send it again with ``send`` :data:`DUP_AFTER_S` later (in a task: the
        receive path that sent it does not wait)."""
        if not self._dup_due:  # (every packet passes here: nothing to parse when none is due)
            return
        stream = _rtp_stream(data)
        if stream is None or stream not in self._dup_due:
            return
        self._dup_due.discard(stream)
        task = asyncio.ensure_future(self._send_copy(data, send))
        self._dup_tasks.add(task)
        task.add_done_callback(self._dup_tasks.discard)

    async def _send_copy(self, data: bytes, send: Callable[[bytes], Awaitable[object]]) -> None:
        await self.sleep(DUP_AFTER_S)
        now = self.clock()
        self.free_at = max(now, self.free_at) + len(data) * 8.0 / self._rate()
        try:
            await send(data)
        except Exception:  # noqa: BLE001 - a closed transport: the copy is only a copy
            return
        self.dups += 1
        self.dup_bytes += len(data)

    def figures(self) -> dict[str, float | int]:
        return {"paced": self.paced, "waited_ms": round(1e3 * self.waited_s, 1),
                "immediate": self.immediate, "overdue": self.overdue,
                "resends_skipped": self.resends_skipped, "resent_bytes": self.resent_bytes,
                "dups": self.dups, "dup_bytes": self.dup_bytes}  # fmt: skip

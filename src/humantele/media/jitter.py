"""A video jitter buffer whose delay is bounded in time, in place of aiortc's.

aiortc's video ``JitterBuffer`` (aiortc 1.16, ``aiortc/jitterbuffer.py``, 512 packets) has two
faults measured here (docs/video.md, "Loss"):

- it releases a frame only when the first packet of the *next* frame arrives: every frame
  waits one frame interval (50 ms at 20 fps) for nothing;
- a frame with a lost packet holds back every later frame until 512 packets have piled up
  behind it; then it drops just enough to fit, and so stays 512 packets behind for good (26 s
  of the US track at ~20 packets/s), long after the loss has ended.

This buffer (same interface: ``add(packet) -> (pli, frame or None)``, called by the receiver
for every RTP packet, the payload already depayloaded into ``packet._data``):

- releases a frame as soon as its last packet (RTP marker bit) is in and no packet since the
  previous frame is missing;
- lets a missing packet be waited for ``max_wait_s`` after the first later packet arrived (time
  for a NACK and its retransmission), or longer when the repairs it measures (late ones
  too) take longer (or, until it has measured some, the given round trip ``rtt``), plus a
  margin: at 60 ms each way
  a retransmission takes ~130 ms and a fixed 100 ms gave up on every one of them; waiting for
  a keyframe, it skips the frames before one that has started to arrive; after the wait, or
  beyond ``capacity`` packets, it
  drops the frames up to the next keyframe, asks the sender for one (``pli``, again every
  ``pli_interval_s`` while waiting) and releases nothing in between: a frame decoded without
  its reference would show a corrupt picture, a freeze is honest;
- asks again for a packet still missing a round trip after the last request (on a packet's
  arrival or :meth:`poll`; :meth:`take_nacks`, sent by the receiver as an RTCP NACK): aiortc
  NACKs a gap once, and again only when a later gap shows; the packets it gave up on are
  handed out too (:meth:`take_given_up`), so the receiver stops asking for them (aiortc's
  NACKs list every packet still missing, given up or not, until 128 later packets have
  come);
- at most one frame per ``add`` (the receiver's interface): frames completed together leave
  on the next packets; if that backlog does not drain (one-packet frames), it asks for a
  keyframe, whose many packets drain it.

Sequence numbers are unwrapped from 16 bits; duplicates and packets older than the last
released frame are ignored. Frames: consecutive packets with one RTP timestamp; a frame starts
after the previous frame's marker packet (or where the timestamp changes).
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

from aiortc.jitterbuffer import JitterFrame

KeyframeTest = Callable[[bytes], bool]
_SEQ_MOD = 1 << 16
# Frames released one per packet added: after a repaired gap, complete frames queue behind the
# released one and a stream of one-packet frames never catches up. After this many releases
# in a row with another complete frame waiting, a keyframe is asked for (it has many packets).
BEHIND_RELEASES = 3
RTX_MARGIN_S = 0.04  # beyond the round trip: the sender's turn and the link's jitter (s)
MAX_WAIT_S = 1.0  # never wait longer for a lost packet, whatever the round trip (s)
MIN_RENACK_S = 0.025  # a missing packet asked for again at most this often (s)
RENACK_MARGIN_S = 0.015  # beyond the round trip before asking again (s)
MAX_RENACK_SPAN = 512  # packets between the head and the newest: past it, no re-asking
# The round trip of a repair, measured here: from a gap's first sight (when aiortc NACKs it)
# to its retransmission's arrival, within the wait or after it (a late repair: the packets
# given up are taken out of aiortc's NACK list, so it answers a request made before the give
# up). Measured only within the wait, the wait never grew to a thin link's repair time (the
# rural link: 25 repairs in time, 83 late); late ones over LATE_REPAIR_MAX_S are not timed.
REPAIRS_KEPT = 32  # the recent repair times the waits follow
MIN_REPAIRS = 3  # repairs measured before they set the waits (until then: the given rtt)
REPAIR_WAIT_QUANTILE = 0.9  # the wait covers this share of recent repairs (and a margin)
GONE_KEPT = 256  # given-up packets remembered, so a late retransmission is counted
LATE_REPAIR_MAX_S = 0.6  # a late repair slower than this sets no wait (the freeze budget, s)


def vp8_is_keyframe(data: bytes) -> bool:
    """A VP8 key frame: frame tag bit 0 clear and the start code 9d 01 2a (RFC 6386 9.1)."""
    return len(data) >= 10 and not data[0] & 1 and data[3:6] == b"\x9d\x01\x2a"


def h264_is_keyframe(data: bytes) -> bool:
    """An H.264 access unit (Annex B, as aiortc depayloads it) with an IDR slice or an SPS."""
    i = data.find(b"\x00\x00\x01")
    while i != -1 and i + 3 < len(data):
        if data[i + 3] & 0x1F in (5, 7):
            return True
        i = data.find(b"\x00\x00\x01", i + 3)
    return False


KEYFRAME_TESTS: dict[str, KeyframeTest] = {"vp8": vp8_is_keyframe, "h264": h264_is_keyframe}


@dataclass
class JitterCounters:
    """What the buffer did: frames released and dropped, gaps given up, keyframes asked."""

    frames: int = 0  # frames released to the decoder
    dropped_frames: int = 0  # complete frames dropped while waiting for a keyframe
    gaps_given_up: int = 0  # missing packets waited for max_wait_s in vain (or overflow)
    plis: int = 0  # keyframe requests
    behind_plis: int = 0  # of them, for frames leaving later than they could (no loss)
    late_packets: int = 0  # packets older than the last released frame (ignored)
    duplicates: int = 0
    renacks: int = 0  # missing packets asked for again (their NACK or retransmission lost)
    nacks_repeated: int = 0  # NACKs sent a second time (the receiver's, a few ms later)
    repairs: int = 0  # missing packets that came (a retransmission) within the wait
    late_repairs: int = 0  # missing packets that came after their frame was given up
    plis_held: int = 0  # give-ups while the keyframe asked for was still on its way
    skipped_to_keyframe: int = 0  # waiting for a keyframe, older frames skipped when it came
    repair_ms: float = 0.0  # the round trip of a repair in force (ms; 0: none known)
    wait_ms: float = 0.0  # the wait for a lost packet in force at the last look (ms)
    wait_ms_max: float = 0.0  # the longest wait in force (ms)
    fec_parity: int = 0  # parity packets received for this stream (humantele.media.fec)
    fec_recovered: int = 0  # lost packets rebuilt from a parity (no round trip; no repair)
    fec_unrecoverable: int = 0  # parities whose frame missed 2+ packets when they came
    fec_nacks_spared: int = 0  # lost packets not asked for: rebuilt while their NACK waited

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


class BoundedJitterBuffer:
    """See the module docstring. ``is_keyframe`` judges a frame's bytes (see
    :data:`KEYFRAME_TESTS`); ``clock`` gives s (monotonic)."""

    def __init__(
        self,
        is_keyframe: KeyframeTest,
        max_wait_s: float = 0.1,
        capacity: int = 1024,
        pli_interval_s: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
        rtt: Callable[[], float | None] | None = None,
    ) -> None:
        self.is_keyframe = is_keyframe
        self.max_wait_s = max_wait_s
        self.rtt = rtt  # the link's round trip (s; its shortest recent sample) or None
        # how long a NACK is held before it leaves (s; the receiver's hold for a frame's
        # parity): part of a repair's time, so of the wait the round trip sets
        self.nack_hold: Callable[[], float] | None = None
        self._capacity = capacity
        self.pli_interval_s = pli_interval_s
        self.clock = clock
        self.counters = JitterCounters()
        self._packets: dict[int, Any] = {}  # extended sequence number -> RtpPacket
        self._arrived: dict[int, float] = {}
        self._next: int | None = None  # the first sequence number not released or dropped
        self._max: int | None = None  # the highest extended sequence number seen
        self._want_key = True  # the decoder needs a keyframe (at start, after a drop)
        self._pli_at: float | None = None  # when a keyframe was last asked for
        self._started: float | None = None  # the first packet's arrival
        self._behind = 0  # releases in a row after which the backlog did not shrink
        self._backlog = 0  # complete frames waiting when that run of releases began
        self._missing_since: dict[int, float] = {}  # extended seq -> when first seen missing
        self._nacked: dict[int, float] = {}  # extended seq -> when we last asked for it
        self._nack_out: list[int] = []  # 16-bit sequence numbers to ask for (take_nacks)
        self._given_up_out: list[int] = []  # 16-bit sequence numbers given up (take_given_up)
        self._repairs: deque[float] = deque(maxlen=REPAIRS_KEPT)  # repair times (s)
        self._gone: OrderedDict[int, float] = OrderedDict()  # given up: seq -> first missing
        self._key_starts: set[int] = set()  # packets that start a keyframe (while wanted)
        self._rebuilt: set[int] = set()  # 16-bit seqs about to come rebuilt from a parity

    def _given_rtt(self) -> float | None:
        rtt = self.rtt() if self.rtt is not None else None
        return rtt if rtt is not None and rtt > 0 and rtt < MAX_WAIT_S * 10 else None

    def _repair_quantile(self, q: float) -> float | None:
        """The ``q`` quantile of the recent repair times (s), None until enough."""
        if len(self._repairs) < MIN_REPAIRS:
            return None
        xs = sorted(self._repairs)
        return xs[min(len(xs) - 1, int(q * len(xs)))]

    def round_trip_s(self) -> float | None:
        """A repair's round trip (s): the median of the recent repairs measured here, else
        the given ``rtt`` (the link's shortest recent round trip), else None."""
        median = self._repair_quantile(0.5)
        rtt = self._given_rtt()
        if median is None:
            return rtt
        return median if rtt is None else max(median, rtt)

    def wait_s(self) -> float:
        """How long a missing packet is waited for (s): ``max_wait_s``, or longer on a link
        whose repairs take longer: :data:`REPAIR_WAIT_QUANTILE` of the repairs measured
        here (re-asks and late repairs included) or the given round trip (and ``nack_hold``,
        a NACK's hold for a frame's parity), plus
        :data:`RTX_MARGIN_S`; at most :data:`MAX_WAIT_S`. A clock-sync exchange over the
        reliable control channel is no measure of it: one lost ping waits for SCTP's
        retransmission (at least 1 s)."""
        wait = self.max_wait_s
        rtt, high = self._given_rtt(), self._repair_quantile(REPAIR_WAIT_QUANTILE)
        if rtt is not None and self.nack_hold is not None:  # (measured repairs include it)
            rtt += self.nack_hold()
        for r in (rtt, high):
            if r is not None:
                wait = max(wait, min(MAX_WAIT_S, r + RTX_MARGIN_S))
        c = self.counters
        c.wait_ms = round(wait * 1e3, 1)
        c.wait_ms_max = max(c.wait_ms_max, c.wait_ms)
        return wait

    def pli_every_s(self) -> float:
        """Keyframe requests while waiting: every ``pli_interval_s``, or every round trip plus
        :data:`RTX_MARGIN_S` when that is longer (the keyframe asked for is still on its way)."""
        rtt = self.round_trip_s()
        if rtt is None:
            return self.pli_interval_s
        return max(self.pli_interval_s, min(MAX_WAIT_S, rtt + RTX_MARGIN_S))

    def renack_every_s(self) -> float:
        """A missing packet is asked for again this long after the last request (s): a round
        trip and a little (its NACK or its retransmission was lost), at least 25 ms."""
        rtt = self.round_trip_s() or 0.0
        return max(MIN_RENACK_S, rtt + RENACK_MARGIN_S)

    def _repaired(self, took_s: float) -> None:
        self._repairs.append(took_s)
        self.counters.repairs += 1
        rtt = self.round_trip_s()
        self.counters.repair_ms = 0.0 if rtt is None else round(rtt * 1e3, 1)

    def note_rebuilt(self, seq16: int) -> None:
        """Packet ``seq16`` is about to be added rebuilt from a parity (``humantele.media.fec``):
        counted in ``fec_recovered``, not as a repair (its time is no retransmission's)."""
        if len(self._rebuilt) > GONE_KEPT:
            self._rebuilt.clear()
        self._rebuilt.add(seq16 % _SEQ_MOD)

    def take_nacks(self) -> list[int]:
        """The 16-bit sequence numbers to ask the sender for again (a NACK), once each."""
        out, self._nack_out = self._nack_out, []
        return out

    def take_given_up(self) -> list[int]:
        """The 16-bit sequence numbers of missing packets given up since the last call (the
        frames they belonged to were dropped): not to be asked for any more."""
        out, self._given_up_out = self._given_up_out, []
        return out

    def _renack(self, now: float) -> None:
        """aiortc's receiver NACKs a missing packet when the gap first shows, and again only
        when a later gap shows; this asks again every :meth:`renack_every_s` while the
        packet is still waited for (at 15 % loss a NACK or its retransmission is lost about
        one time in four)."""
        if self._next is None or self._max is None or self._max - self._next > MAX_RENACK_SPAN:
            return
        every = None
        for seq in range(self._next, self._max):
            if seq in self._packets:
                continue
            first = self._missing_since.setdefault(seq, now)
            if every is None:
                every = self.renack_every_s()
            if now - self._nacked.get(seq, first) >= every:
                self._nacked[seq] = now
                self._nack_out.append(seq % _SEQ_MOD)
                self.counters.renacks += 1

    def poll(self) -> None:
        """Between packets (the receiver calls it every few ms): ask again for the missing
        packets whose request is due. Run only from :meth:`add`, a request waited for the
        next packet, 50-160 ms on the US at 15 % loss, and a lost retransmission was asked
        for again once or not at all within the wait."""
        self._renack(self.clock())

    @property
    def capacity(self) -> int:
        return self._capacity

    @property
    def waiting_for_keyframe(self) -> bool:
        return self._want_key

    def __len__(self) -> int:
        return len(self._packets)

    def add(self, packet: Any) -> tuple[bool, JitterFrame | None]:
        """Take one RTP packet; (ask for a keyframe?, the next frame to decode or None)."""
        now = self.clock()
        seq = self._extend(packet.sequence_number)
        rebuilt = bool(self._rebuilt) and seq % _SEQ_MOD in self._rebuilt
        if rebuilt:
            self._rebuilt.discard(seq % _SEQ_MOD)
            self.counters.fec_recovered += 1
        if self._next is None:
            self._next, self._started = seq, now
        if seq < self._next:
            self.counters.late_packets += 1
            first = self._gone.pop(seq, None)
            if first is not None and not rebuilt:  # after its frame was given up: timed too
                self.counters.late_repairs += 1
                if now - first <= LATE_REPAIR_MAX_S:
                    self._repairs.append(now - first)
        elif seq in self._packets:
            self.counters.duplicates += 1
        else:
            self._packets[seq] = packet
            self._arrived[seq] = now
            first = self._missing_since.pop(seq, None)
            self._nacked.pop(seq, None)
            if first is not None and not rebuilt:  # a missing packet came: its retransmission
                self._repaired(now - first)
            if self._want_key and self.is_keyframe(getattr(packet, "_data", b"")):
                self._key_starts.add(seq)
        self._renack(now)
        frame = self._pop(now)
        return self._pli(now), frame

    # --- internals ----------------------------------------------------------------------------

    def _extend(self, seq16: int) -> int:
        """The 16-bit sequence number as the nearest value to the highest seen so far."""
        if self._max is None:
            self._max = seq16
            return seq16
        delta = (seq16 - self._max) % _SEQ_MOD
        if delta >= _SEQ_MOD // 2:
            delta -= _SEQ_MOD
        seq = self._max + delta
        self._max = max(self._max, seq)
        return seq

    def _pli(self, now: float) -> bool:
        """Ask for a keyframe while waiting for one (at once, then every pli_interval_s) or
        while frames keep leaving later than they could (:meth:`_pop`)."""
        if not (self._want_key or self._behind >= BEHIND_RELEASES) or self._started is None:
            return False
        if self._pli_at is not None and now - self._pli_at < self.pli_every_s():
            return False
        if self.counters.frames == 0 and now - self._started <= self.wait_s():
            return False  # the stream's start: its first frame is a keyframe, unless late
        self._pli_at = now
        self.counters.plis += 1
        self.counters.behind_plis += not self._want_key
        return True

    def _head(self, start: int | None = None) -> tuple[int, int | None]:
        """The head frame from ``_next`` (or the frame from ``start``): (its start, its last
        sequence number), the last None while incomplete (a packet missing or its marker not
        yet in)."""
        start = self._next if start is None else start
        assert start is not None
        p = self._packets.get(start)
        if p is None:
            return start, None
        ts, seq = p.timestamp, start
        while True:
            q = self._packets.get(seq)
            if q is None:
                return start, None
            if q.timestamp != ts:  # no marker on the previous packet: the frame ended there
                return start, seq - 1
            if q.marker:
                return start, seq
            seq += 1

    def _first_missing(self) -> int:
        assert self._next is not None
        seq = self._next
        while seq in self._packets:
            seq += 1
        return seq

    def _gap_age(self, now: float) -> float:
        """How long the first missing packet has been known missing (s): since the first packet
        after it arrived; 0 while none has (the frame may still be arriving)."""
        gap = self._first_missing()
        later = [t for s, t in self._arrived.items() if s > gap]
        return now - min(later) if later else 0.0

    def _drop_through(self, last: int) -> None:
        for seq in [s for s in self._packets if s <= last]:
            del self._packets[seq]
            del self._arrived[seq]
        for seq in [s for s in self._missing_since if s <= last]:
            self._gone[seq] = self._missing_since.pop(seq)  # a late repair is counted
            self._nacked.pop(seq, None)
            self._given_up_out.append(seq % _SEQ_MOD)
        del self._given_up_out[:-GONE_KEPT]  # bounded if nobody takes them
        while len(self._gone) > GONE_KEPT:
            self._gone.popitem(last=False)
        self._key_starts = {s for s in self._key_starts if s > last}
        self._next = last + 1

    def _skip_to_keyframe(self) -> bool:
        """Waiting for a keyframe, one has started to arrive: drop everything before it (the
        frames there cannot be decoded, so waiting for their lost packets only delays the
        keyframe). Whether anything was dropped."""
        assert self._next is not None
        later = [s for s in self._key_starts if s > self._next]
        if not later or self._next in self._key_starts:
            return False
        self._drop_through(min(later) - 1)
        self.counters.skipped_to_keyframe += 1
        return True

    def _skip_to_next_start(self) -> None:
        """Drop the head (incomplete) up to the next packet known to start a frame: one after
        a marker packet or where the timestamp changes; without one, drop everything."""
        assert self._next is not None
        for seq in sorted(self._packets):
            prev = self._packets.get(seq - 1)
            if (
                seq > self._next
                and prev is not None
                and (prev.marker or prev.timestamp != self._packets[seq].timestamp)
            ):
                self._drop_through(seq - 1)
                return
        self._drop_through(self._max if self._max is not None else self._next)

    def _complete_waiting(self) -> int:
        """Complete frames waiting at the head, one behind another."""
        assert self._next is not None
        n, start = 0, self._next
        while True:
            _, last = self._head(start)
            if last is None:
                return n
            n, start = n + 1, last + 1

    def _count_backlog(self) -> None:
        """After a release: complete frames left waiting are a backlog (they leave one per
        packet added). One that drains (frames of two or more packets: each brings more
        releases than frames) is no fault; one that does not (one-packet frames) makes
        ``_pli`` ask for a keyframe, whose many packets drain it."""
        waiting = self._complete_waiting()
        if waiting == 0:
            self._behind = 0
        elif self._behind == 0 or waiting < self._backlog:
            self._behind, self._backlog = 1, waiting  # a new backlog, or it is draining
        else:
            self._behind += 1

    def _give_up(self) -> None:
        """Drop the head frame (its gap waited for in vain) and wait for a keyframe: asked for
        at once, unless one asked for is still on its way (waiting already, the frame given up
        older than any keyframe seen starting): then at the next repeat (:meth:`pli_every_s`).
        Asked again at once, the encoder made a second keyframe behind the first, a burst that
        a thin link's queue drops, and so on (a PLI storm)."""
        self.counters.gaps_given_up += 1
        if self._want_key and self._pli_at is not None and self._next not in self._key_starts:
            self.counters.plis_held += 1
        else:
            self._pli_at = None
        self._want_key = True
        self._skip_to_next_start()
        self._key_starts = {s for s, p in self._packets.items()
                            if self.is_keyframe(getattr(p, "_data", b""))}  # fmt: skip

    def _pop(self, now: float) -> JitterFrame | None:
        while self._packets:
            if self._want_key and self._skip_to_keyframe():
                continue
            start, last = self._head()
            if last is None:
                if len(self._packets) <= self._capacity and self._gap_age(now) <= self.wait_s():
                    return None
                self._give_up()
                continue
            packets = [self._packets[s] for s in range(start, last + 1)]
            data = b"".join(p._data for p in packets)
            self._drop_through(last)
            if self._want_key and not self.is_keyframe(data):
                self.counters.dropped_frames += 1
                continue
            if self._want_key:
                self._want_key, self._behind, self._pli_at = False, 0, None
                self._key_starts.clear()
            else:
                self._count_backlog()
            self.counters.frames += 1
            return JitterFrame(data=data, timestamp=packets[0].timestamp)
        return None

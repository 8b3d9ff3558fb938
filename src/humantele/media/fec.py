"""Parity per frame: one XOR parity packet after each group of a protected stream's RTP
packets, from which the receiver rebuilds any one lost packet of the group with no round trip
(issue 31, docs/video.md "Sixth pass").

Why: on the rural link (60 +- 20 ms each way, 3 % loss) a packet repaired by NACK and
retransmission comes ~190 ms after its neighbours, past the playout delay; at 3-4 packets a US
frame one frame in ten loses a packet, and each such frame was a freeze. With one parity per
frame a frame is lost to the round trip only when two of its packets (parity included) are.

The idea is RFC 5109's ULPFEC (level 0, one mask covering consecutive packets); the format is
our own, sent on its own SSRC (so the media stream's sequence numbers see no gap and aiortc's
receiver reports are untouched) with a payload type no one negotiates (:data:`PARITY_PT`; an
expert without :class:`ParityDecoder` drops it in aiortc's RTP router, unknown SSRC and type).
A parity packet is an RTP packet (version 2, no padding, extension or CSRC, marker clear;
its own sequence number; the timestamp of the group's first packet) whose payload is::

    0      version (:data:`VERSION`)
    1      count: packets protected, consecutive sequence numbers (1 .. MAX_GROUP)
    2-3    first sequence number protected
    4-7    SSRC of the protected stream
    8      XOR of the protected packets' first header bytes (V, P, X, CC)
    9      XOR of their second header bytes (marker, payload type)
    10-11  XOR of their lengths after the 12-byte fixed header
    12-15  XOR of their timestamps
    16-    XOR of their bytes after the fixed header (CSRCs, extensions, payload, padding),
           each zero-filled to the longest

so that XOR-ing the other packets of the group into it gives the missing one, byte for byte
(sequence number and SSRC are known). Frames are the groups: a group ends at a packet with
the marker bit (a frame's last) or after ``group`` packets (a keyframe's many packets get a
parity per ``group``; see the doc for why 8). A frame of one packet gets a parity too: a copy.
"""

from __future__ import annotations

import random
import struct
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import asdict, dataclass

from humantele.media.rtp import RTP_HEADER, SEQ_MOD, rtp_fields, seq_newer

PARITY_PT = 127  # not negotiated by either side (aiortc's video codecs take 96 up to ~102)
VERSION = 1
HEADER = 16  # parity header bytes before the XOR of the bodies
MAX_GROUP = 48  # a parity says it covers at most this many packets (more: malformed)
DEFAULT_GROUP = 8  # packets per parity within a frame (see docs/video.md, "Sixth pass")
PACKETS_KEPT = 512  # media packets kept per stream to rebuild from (the last ~15 s of the US)
PARITIES_KEPT = 16  # parities kept per stream while their group still misses 2+ packets
STREAMS_KEPT = 8  # streams (SSRCs) whose packets are kept
RECOVERED_KEPT = 256  # rebuilt sequence numbers remembered per stream (a NACK leaves them out)
PROTECTED_HOLD_S = 2.0  # a stream is protected this long after its last parity (s)


def is_parity(data: bytes) -> bool:
    """Whether a plain RTP packet carries our payload type (a parity, or garbage)."""
    return len(data) >= 2 and data[0] >> 6 == 2 and data[1] & 0x7F == PARITY_PT


class _Group:
    __slots__ = ("first", "count", "ts", "b0", "b1", "length", "tsx", "body")

    def __init__(self, first: int, ts: int) -> None:
        self.first, self.count, self.ts = first, 0, ts
        self.b0 = self.b1 = self.length = self.tsx = 0
        self.body = bytearray()

    def add(self, data: bytes) -> None:
        self.count += 1
        self.b0 ^= data[0]
        self.b1 ^= data[1]
        self.length ^= len(data) - RTP_HEADER
        self.tsx ^= int.from_bytes(data[4:8], "big")
        _xor_into(self.body, memoryview(data)[RTP_HEADER:])


def _xor_into(acc: bytearray, data: bytes | memoryview) -> None:
    """``acc ^= data``, ``acc`` grown with zeros to ``data``'s length."""
    n = len(data)
    if len(acc) < n:
        acc.extend(bytes(n - len(acc)))
    x = int.from_bytes(acc[:n], "big") ^ int.from_bytes(data, "big")
    acc[:n] = x.to_bytes(n, "big")


@dataclass
class ParityCounters:
    """The sender's parity (per encoder)."""

    parities: int = 0  # parity packets made
    parity_bytes: int = 0  # their size (RTP, before SRTP)
    protected: int = 0  # media packets covered
    protected_bytes: int = 0
    broken_groups: int = 0  # groups left without parity (a sequence number skipped)

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class ParityEncoder:
    """The follower's side: :meth:`protect` takes each plain RTP packet after it was sent and
    returns the parity packets to send after it (none, or one at a group's end). Only streams
    whose SSRC ``protects(ssrc)`` are covered; retransmissions (a sequence number not newer
    than the last) are not."""

    def __init__(
        self,
        protects: Callable[[int], bool],
        group: int = DEFAULT_GROUP,
        ssrc: int | None = None,
    ) -> None:
        if not 1 <= group <= MAX_GROUP:
            raise ValueError(f"group must be 1..{MAX_GROUP}, not {group}")
        self.protects = protects
        self.group = group
        self.ssrc = random.getrandbits(32) if ssrc is None else ssrc
        self._seq = random.getrandbits(16)
        self._groups: dict[int, _Group] = {}
        self._last: dict[int, int] = {}  # ssrc -> last new sequence number
        self.counters = ParityCounters()

    def protect(self, data: bytes) -> list[bytes]:
        fields = rtp_fields(data)
        if fields is None or is_parity(data):
            return []
        ssrc, seq, ts, marker = fields
        try:
            if not self.protects(ssrc):
                return []
        except Exception:  # noqa: BLE001 - a stream that cannot be judged is not protected
            return []
        last = self._last.get(ssrc)
        if last is not None and not seq_newer(seq, last):
            return []  # a retransmission: its group's parity is out already
        self._last[ssrc] = seq
        out: list[bytes] = []
        g = self._groups.get(ssrc)
        if g is not None and (seq != (g.first + g.count) % SEQ_MOD or ts != g.ts):
            if seq == (g.first + g.count) % SEQ_MOD:  # a new frame without a marker before it
                out.append(self._parity(ssrc, g))
            else:
                self.counters.broken_groups += 1
            g = None
        if g is None:
            g = self._groups[ssrc] = _Group(seq, ts)
        g.add(data)
        self.counters.protected += 1
        self.counters.protected_bytes += len(data)
        if marker or g.count >= self.group:
            out.append(self._parity(ssrc, g))
            del self._groups[ssrc]
        return out

    def _parity(self, ssrc: int, g: _Group) -> bytes:
        header = struct.pack("!BBHII", 0x80, PARITY_PT, self._seq, g.ts, self.ssrc)
        self._seq = (self._seq + 1) % SEQ_MOD
        payload = struct.pack(
            "!BBHIBBHI", VERSION, g.count, g.first, ssrc, g.b0, g.b1, g.length, g.tsx
        )
        data = header + payload + bytes(g.body)
        self.counters.parities += 1
        self.counters.parity_bytes += len(data)
        return data


def make_parity(packets: list[bytes], ssrc: int = 0, seq: int = 0) -> bytes:
    """The parity of ``packets`` (plain RTP, consecutive sequence numbers of one stream, as
    they are), sent on SSRC ``ssrc`` with sequence number ``seq`` (tests, the model)."""
    fields = rtp_fields(packets[0])
    if fields is None:
        raise ValueError("not an RTP packet")
    g = _Group(fields[1], fields[2])
    for p in packets:
        g.add(p)
    enc = ParityEncoder(lambda s: True, ssrc=ssrc)
    enc._seq = seq
    return enc._parity(fields[0], g)


@dataclass
class Parity:
    """A parsed parity packet."""

    ssrc: int  # the protected stream's
    first: int
    count: int
    b0: int
    b1: int
    length: int
    tsx: int
    body: bytes

    def seqs(self) -> list[int]:
        return [(self.first + i) % SEQ_MOD for i in range(self.count)]


class ParityError(ValueError):
    """A packet with our payload type that is not a well-formed parity."""


def parse_parity(data: bytes) -> Parity:
    """Parse a parity packet (plain RTP); :class:`ParityError` if it is malformed."""
    if not is_parity(data):
        raise ParityError("not our payload type")
    if data[0] & 0x3F:  # padding, extension or CSRC: we never send them
        raise ParityError("parity with padding, extension or CSRC")
    if len(data) < RTP_HEADER + HEADER:
        raise ParityError(f"parity of {len(data)} bytes, shorter than its header")
    version, count, first, ssrc, b0, b1, length, tsx = struct.unpack_from(
        "!BBHIBBHI", data, RTP_HEADER
    )
    if version != VERSION:
        raise ParityError(f"parity version {version}")
    if not 1 <= count <= MAX_GROUP:
        raise ParityError(f"parity covering {count} packets")
    body = data[RTP_HEADER + HEADER :]
    if b0 >> 6 != (2 if count % 2 else 0):  # the XOR of count version-2 bytes' top bits
        raise ParityError("parity whose header XOR cannot come from RTP packets")
    return Parity(ssrc, first, count, b0, b1, length, tsx, body)


@dataclass
class DecoderCounters:
    """What the receiver's parity did (all streams)."""

    parities: int = 0  # well-formed parity packets received
    recovered: int = 0  # lost packets rebuilt from a parity
    unrecoverable: int = 0  # parities whose group missed 2+ packets when they came
    not_needed: int = 0  # parities whose group was complete
    malformed: int = 0  # packets of our payload type that do not parse (dropped)
    unknown_ssrc: int = 0  # parities for a stream whose packets are not kept (dropped)
    corrupt: int = 0  # rebuilt packets that are not RTP (dropped: a wrong parity)
    late: int = 0  # parities of a group whose packets are no longer kept (dropped)

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class _Stream:
    __slots__ = ("packets", "pending", "recovered", "covered", "parity_at")

    def __init__(self) -> None:
        self.packets: OrderedDict[int, bytes] = OrderedDict()  # seq -> plain RTP
        self.pending: OrderedDict[int, Parity] = OrderedDict()  # first seq -> parity
        self.recovered: OrderedDict[int, None] = OrderedDict()
        self.covered: int | None = None  # the newest sequence number a parity covered
        self.parity_at = -float("inf")


class ParityDecoder:
    """The expert's side: every plain RTP packet received goes to :meth:`packet` (kept, a
    bounded number per stream), every parity packet to :meth:`parity`; both return the lost
    packets they rebuilt (plain RTP, to feed to the receive path as if they had arrived).
    A parity whose group misses two or more packets is kept (:data:`PARITIES_KEPT`) and tried
    again as packets of the group come (a retransmission of one of two lost). ``on_event(
    ssrc, what, seq)`` (``parity`` and ``unrecoverable`` with the group's first sequence
    number, ``recovered`` with the rebuilt one's, called before it is returned) lets the
    caller count per stream. Never raises on bad input: it is dropped and counted."""

    def __init__(
        self,
        clock: Callable[[], float] = time.monotonic,
        on_event: Callable[[int, str, int], object] | None = None,
    ) -> None:
        self.clock = clock
        self.on_event = on_event
        self.counters = DecoderCounters()
        self._streams: OrderedDict[int, _Stream] = OrderedDict()

    def _event(self, ssrc: int, what: str, seq: int) -> None:
        if self.on_event is not None:
            try:
                self.on_event(ssrc, what, seq)
            except Exception:  # noqa: BLE001 - counting must not stop the video
                pass

    def packet(self, data: bytes) -> list[bytes]:
        """A media packet arrived: keep it; the packets it lets a kept parity rebuild."""
        fields = rtp_fields(data)
        if fields is None:
            return []
        ssrc, seq = fields[0], fields[1]
        st = self._streams.get(ssrc)
        if st is None:
            st = self._streams[ssrc] = _Stream()
            while len(self._streams) > STREAMS_KEPT:
                self._streams.popitem(last=False)
        if seq in st.packets:
            return []
        st.packets[seq] = data
        while len(st.packets) > PACKETS_KEPT:
            st.packets.popitem(last=False)
        out: list[bytes] = []
        for first, par in list(st.pending.items()):
            if (seq - first) % SEQ_MOD < par.count:
                out += self._try(ssrc, st, par, again=True)
        return out

    def parity(self, data: bytes) -> list[bytes]:
        """A packet of our payload type arrived: the packet it rebuilds, if its group misses
        exactly one."""
        try:
            par = parse_parity(data)
        except ParityError:
            self.counters.malformed += 1
            return []
        st = self._streams.get(par.ssrc)
        if st is None:
            self.counters.unknown_ssrc += 1
            return []
        self.counters.parities += 1
        self._event(par.ssrc, "parity", par.first)
        st.parity_at = self.clock()
        last = (par.first + par.count - 1) % SEQ_MOD
        if st.covered is None or seq_newer(last, st.covered):
            st.covered = last
        return self._try(par.ssrc, st, par, again=False)

    def _try(self, ssrc: int, st: _Stream, par: Parity, again: bool) -> list[bytes]:
        """Rebuild the one packet ``par``'s group misses (``again``: a kept parity retried as
        a packet of its group came)."""
        seqs = par.seqs()
        if not again and len(st.packets) >= PACKETS_KEPT:
            oldest = next(iter(st.packets))
            if seq_newer(oldest, seqs[-1]):
                self.counters.late += 1  # its group's packets are no longer kept
                return []
        missing = [s for s in seqs if s not in st.packets]
        if len(missing) > 1:
            if not again:
                self.counters.unrecoverable += 1
                self._event(ssrc, "unrecoverable", par.first)
                st.pending[par.first] = par
                while len(st.pending) > PARITIES_KEPT:
                    st.pending.popitem(last=False)
            return []
        st.pending.pop(par.first, None)
        if not missing:
            self.counters.not_needed += not again
            return []
        lost = missing[0]
        b0, b1, length, tsx = par.b0, par.b1, par.length, par.tsx
        body = bytearray(par.body)
        for s in seqs:
            if s == lost:
                continue
            p = st.packets[s]
            if len(p) - RTP_HEADER > len(body):
                self.counters.corrupt += 1  # a packet longer than the parity's body
                return []
            b0 ^= p[0]
            b1 ^= p[1]
            length ^= len(p) - RTP_HEADER
            tsx ^= int.from_bytes(p[4:8], "big")
            _xor_into(body, memoryview(p)[RTP_HEADER:])
        if b0 >> 6 != 2 or length > len(body) or 4 * (b0 & 0x0F) > length:
            self.counters.corrupt += 1
            return []
        data = struct.pack("!BBHII", b0, b1, lost, tsx, ssrc) + bytes(body[:length])
        if b0 & 0x20 and (length == 0 or data[-1] == 0 or data[-1] > length):
            self.counters.corrupt += 1  # padding that does not fit
            return []
        st.packets[lost] = data
        st.recovered[lost] = None
        while len(st.recovered) > RECOVERED_KEPT:
            st.recovered.popitem(last=False)
        self.counters.recovered += 1
        self._event(ssrc, "recovered", lost)
        return [data]

    # --- what the NACK hold asks ------------------------------------------------------------

    def recovered(self, ssrc: int, seq: int) -> bool:
        """Whether packet ``seq`` of stream ``ssrc`` was rebuilt (not to be asked for)."""
        st = self._streams.get(ssrc)
        return st is not None and seq in st.recovered

    def awaits_parity(self, ssrc: int, seq: int) -> bool:
        """Whether a parity covering ``seq`` of stream ``ssrc`` may still come: the stream
        had a parity within :data:`PROTECTED_HOLD_S` and none yet covered ``seq``."""
        st = self._streams.get(ssrc)
        if st is None or self.clock() - st.parity_at > PROTECTED_HOLD_S:
            return False
        return st.covered is None or seq_newer(seq, st.covered)

    def figures(self) -> dict[str, int]:
        return self.counters.as_dict()

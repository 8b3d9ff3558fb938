"""The per-frame record the follower sends beside each video frame, on the ``video`` channel.

``FrameInfo(track, seq, t_capture)``: the frame's number in its track (the counter drawn in
its top-left corner, :mod:`humantele.video.counter`) and its capture time (s, the follower's
clock, the one its ClockSync uses). The expert reads the counter from the decoded frame, looks
the capture time up here and maps it onto its own clock, so every frame's age is known.

Wire format, 15 bytes little-endian: ``b"V"``, version 1, track (0 us, 1 pov), seq (u32),
t_capture (f64). Anything else raises :class:`FrameInfoError` (the receiver counts and drops).
The channel is unordered with no retransmissions (a late record is useless): a frame whose
record was lost has an unknown age, counted at the expert.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from humantele.media.config import TRACKS

_FORMAT = struct.Struct("<cBBId")
_MAGIC, _VERSION = b"V", 1
SIZE = _FORMAT.size


class FrameInfoError(ValueError):
    """A ``video`` channel message that is not a valid :class:`FrameInfo`."""


@dataclass(frozen=True, slots=True)
class FrameInfo:
    track: str  # "us" or "pov"
    seq: int  # frame number in the track, 1, 2, ... (u32)
    t_capture: float  # s, the follower's monotonic clock

    def encode(self) -> bytes:
        if self.track not in TRACKS:
            raise FrameInfoError(f"unknown track {self.track!r}")
        if not (0 <= self.seq <= 0xFFFFFFFF) or not math.isfinite(self.t_capture):
            raise FrameInfoError("seq out of range or capture time not finite")
        return _FORMAT.pack(_MAGIC, _VERSION, TRACKS.index(self.track), self.seq, self.t_capture)

    @classmethod
    def decode(cls, data: bytes) -> FrameInfo:
        if not isinstance(data, bytes | bytearray) or len(data) != SIZE:
            raise FrameInfoError("wrong size")
        magic, version, track, seq, t = _FORMAT.unpack(data)
        if magic != _MAGIC or version != _VERSION:
            raise FrameInfoError("not a frame record of this version")
        if track >= len(TRACKS) or not math.isfinite(t):
            raise FrameInfoError("unknown track or capture time not finite")
        return cls(TRACKS[track], seq, t)

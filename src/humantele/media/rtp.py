"""Plain RTP packets as the media hooks see them (before SRTP protection, after it on the way
in): the fixed header's fields and the order of 16-bit sequence numbers (RFC 3550)."""

from __future__ import annotations

import struct

RTP_HEADER = 12  # the fixed header's bytes
SEQ_MOD = 1 << 16  # sequence numbers wrap here


def rtp_fields(data: bytes) -> tuple[int, int, int, bool] | None:
    """(ssrc, sequence number, timestamp, marker) of a plain RTP packet, None for RTCP
    (packet types 192-208 where RTP has its marker and payload type) or anything not RTP
    version 2."""
    if len(data) < RTP_HEADER or data[0] >> 6 != 2 or 192 <= data[1] <= 208:
        return None
    seq, ts, ssrc = struct.unpack_from("!HII", data, 2)
    return ssrc, seq, ts, bool(data[1] & 0x80)


def seq_newer(a: int, b: int) -> bool:
    """16-bit sequence number ``a`` comes after ``b`` (within half the sequence space)."""
    return 0 < (a - b) % SEQ_MOD < SEQ_MOD // 2

"""Parity per frame (``humantele.media.fec``): any one lost packet of a group rebuilt byte for
byte, two lost rebuild nothing (until one comes again), bad parity dropped and counted; the
follower's hook sends a parity after each protected frame through the pacer; the expert's
hooks, on a real aiortc receiver, rebuild a lost packet, release its frame and ask no NACK
for it."""

from __future__ import annotations

import asyncio
import random
import struct

import pytest
from aiortc import RTCPeerConnection
from aiortc.rtcrtpparameters import (
    RTCRtcpParameters,
    RTCRtpCodecParameters,
    RTCRtpDecodingParameters,
    RTCRtpReceiveParameters,
)
from aiortc.rtcrtpreceiver import RemoteStreamTrack
from aiortc.rtp import RtcpPacket, RtcpRtpfbPacket
from media_helpers import two_senders_sending

from humantele.media import fec
from humantele.media.aiortc_hooks import (
    hold_nacks,
    pace_sender,
    protect_sender,
    sender_ssrc,
)
from humantele.media.config import ExpertVideoConfig
from humantele.media.fec import (
    PARITY_PT,
    ParityDecoder,
    ParityEncoder,
    is_parity,
    make_parity,
    parse_parity,
)
from humantele.media.pacer import Pacer
from humantele.media.receiver import VideoReceiver
from humantele.transport.clocksync import ClockSync

SSRC = 0x1234ABCD


def rtp(
    seq: int,
    payload: bytes,
    *,
    ts: int = 9000,
    marker: bool = False,
    pt: int = 96,
    ssrc: int = SSRC,
    ext: bytes = b"",
) -> bytes:
    """A plain RTP packet; ``ext``: a header extension's body (X bit set, profile 0xBEDE)."""
    b0 = 0x80 | (0x10 if ext else 0)
    header = struct.pack("!BBHII", b0, pt | (0x80 if marker else 0), seq & 0xFFFF, ts, ssrc)
    if ext:
        header += struct.pack("!HH", 0xBEDE, len(ext) // 4) + ext
    return header + payload


def frame(first: int, sizes: list[int], rng: random.Random, ts: int = 9000) -> list[bytes]:
    """One frame's packets: payloads of the given sizes, the marker on the last."""
    return [
        rtp(
            first + i,
            rng.randbytes(n),
            ts=ts,
            marker=i == len(sizes) - 1,
            ext=b"\x22\x01\x02\x03" if i == 1 else b"",
        )  # fmt: skip
        for i, n in enumerate(sizes)
    ]


def test_any_one_lost_packet_is_rebuilt_byte_for_byte():
    rng = random.Random(7)
    packets = frame(65533, [1187, 40, 1200, 3, 977], rng)  # sequence numbers wrap in it
    parity = make_parity(packets, ssrc=99, seq=5)
    assert is_parity(parity) and parse_parity(parity).count == 5
    assert len(parity) == 12 + fec.HEADER + 1200  # as long as the longest body
    for lost in range(len(packets)):
        dec = ParityDecoder()
        for i, p in enumerate(packets):
            if i != lost:
                assert dec.packet(p) == []
        assert dec.parity(parity) == [packets[lost]]
        seq = (65533 + lost) % 65536
        assert dec.recovered(SSRC, seq) and dec.counters.recovered == 1
        assert dec.parity(parity) == [] and dec.counters.not_needed == 1  # a copy: nothing


def test_a_one_packet_frame_gets_a_copy():
    p = rtp(10, b"abc", marker=True)
    dec = ParityDecoder()
    dec.packet(rtp(9, b"x"))  # the stream is known
    assert dec.parity(make_parity([p])) == [p]


def test_two_lost_rebuild_nothing_until_one_comes_again():
    rng = random.Random(1)
    packets = frame(100, [500, 600, 700, 800], rng)
    dec = ParityDecoder()
    dec.packet(packets[0])
    dec.packet(packets[3])
    assert dec.parity(make_parity(packets)) == []
    assert dec.counters.unrecoverable == 1 and dec.counters.recovered == 0
    assert dec.packet(packets[1]) == [packets[2]]  # a retransmission of one: the other rebuilt
    assert dec.counters.recovered == 1


def test_the_encoder_makes_a_parity_per_frame_and_per_group():
    rng = random.Random(2)
    enc = ParityEncoder(lambda ssrc: ssrc == SSRC, group=8, ssrc=77)
    key = frame(0, [1100] * 12, rng, ts=0)  # a keyframe of 12 packets: 8 + 4
    out = [p for pkt in key for p in enc.protect(pkt)]
    assert [parse_parity(p).seqs() for p in out] == [list(range(8)), list(range(8, 12))]
    seq = struct.unpack_from("!H", out[0], 2)[0]
    assert out == [make_parity(key[:8], 77, seq), make_parity(key[8:], 77, seq + 1)]
    delta = frame(12, [300, 200], rng, ts=3000)
    assert enc.protect(delta[0]) == []
    out += enc.protect(delta[1])
    assert out[-1] == make_parity(delta, 77, seq + 2)
    assert enc.protect(key[3]) == []  # a retransmission: no parity
    assert enc.protect(rtp(5, b"x" * 50, ssrc=1, marker=True)) == []  # not protected
    assert enc.protect(out[0]) == []  # its own parity
    assert enc.protect(b"\x81\xc8" + bytes(30)) == []  # RTCP
    # a frame that ends without a marker: its parity leaves with the next frame's first packet
    a, b = rtp(14, b"a" * 10, ts=6000), rtp(15, b"b" * 10, ts=9000, marker=True)
    out += enc.protect(a) + enc.protect(b)
    assert [parse_parity(p).seqs() for p in out[-2:]] == [[14], [15]]
    c = enc.counters
    assert c.parities == len(out) == 5 and c.protected == 16
    assert c.parity_bytes == sum(len(p) for p in out)


@pytest.mark.parametrize(
    "bad",
    [
        b"\x80\x7f",  # short
        rtp(1, b"", pt=PARITY_PT),  # no header
        rtp(1, bytes([2, 3]) + bytes(14), pt=PARITY_PT),  # another version
        rtp(1, bytes([1, 0]) + bytes(14), pt=PARITY_PT),  # count 0
        rtp(1, bytes([1, 200]) + bytes(14), pt=PARITY_PT),  # count absurd
        bytes([0xA0]) + make_parity([rtp(3, b"ab", marker=True)])[1:],  # padding bit
        make_parity([rtp(3, b"ab", marker=True)])[:27],  # cut inside its header
    ],
)
def test_a_malformed_parity_is_dropped_and_counted(bad: bytes):
    dec = ParityDecoder()
    dec.packet(rtp(2, b"x"))
    assert dec.parity(bad) == [] and dec.counters.malformed == 1 and dec.counters.parities == 0


def test_a_parity_for_an_unknown_stream_or_a_wrong_one_is_dropped_and_counted():
    dec = ParityDecoder()
    dec.packet(rtp(2, b"x" * 20))
    assert dec.parity(make_parity([rtp(3, b"ab", marker=True, ssrc=5)])) == []
    assert dec.counters.unknown_ssrc == 1
    good = make_parity([rtp(2, b"x" * 20), rtp(3, b"y" * 20, marker=True)])
    wrong = good[:22] + b"\xff\xff" + good[24:]  # the lengths' XOR: longer than the body
    assert dec.parity(wrong) == [] and dec.counters.corrupt == 1
    assert dec.parity(good) == [rtp(3, b"y" * 20, marker=True)]


def test_random_bytes_of_our_payload_type_never_raise():
    rng = random.Random(3)
    dec = ParityDecoder()
    for seq in range(40):
        dec.packet(rtp(seq, rng.randbytes(rng.randrange(0, 300)), marker=seq % 4 == 3))
    for _ in range(3000):
        n = rng.randrange(0, 120)
        body = bytes([1, rng.randrange(0, 60)]) + struct.pack("!HI", rng.randrange(0, 50), SSRC)
        data = struct.pack("!BBHII", 0x80, PARITY_PT, 1, 0, 5) + body + rng.randbytes(n)
        for p in dec.parity(data):
            assert p[0] >> 6 == 2 and struct.unpack_from("!I", p, 8)[0] == SSRC
    c = dec.counters
    assert c.malformed + c.parities == 3000


async def test_the_follower_hook_sends_a_parity_after_each_frame_through_the_pacer():
    async with two_senders_sending() as (us, pov, sent):
        pacer = Pacer(lambda: 1e9)
        pace_sender(us, pacer)
        enc = ParityEncoder({sender_ssrc(us)}.__contains__)
        protect_sender(us, enc)
        pace_sender(pov, pacer)  # one transport: still wrapped once
        rng = random.Random(4)
        packets = frame(1, [900, 901, 50], rng, ts=0)
        packets = [p[:8] + struct.pack("!I", sender_ssrc(us)) + p[12:] for p in packets]
        for p in packets:
            await us.transport._send_rtp(p)
        other = rtp(1, b"pov", marker=True, ssrc=sender_ssrc(pov))
        await us.transport._send_rtp(other)
        assert sent[:3] == packets and is_parity(sent[3]) and sent[4] == other
        assert len(sent) == 5 and parse_parity(sent[3]).ssrc == sender_ssrc(us)
        assert enc.ssrc in pacer._last_seq  # the pacer saw the parity: its size counted


class FakeNackReceiver:
    """Stands in for an RTCRtpReceiver: what its ``_send_rtcp_nack`` sent."""

    def __init__(self) -> None:
        self.sent: list[tuple[int, list[int]]] = []

    async def _send_rtcp_nack(self, ssrc: int, lost: list[int]) -> None:
        self.sent.append((ssrc, list(lost)))


async def test_a_nack_waits_for_the_parity_and_leaves_out_what_it_rebuilt():
    now = [0.0]

    async def sleep(s: float) -> None:
        now[0] += s
        await asyncio.sleep(0)

    rng = random.Random(5)
    dec = ParityDecoder(clock=lambda: now[0])
    rx = FakeNackReceiver()
    spared: list[int] = []
    hold_nacks(rx, dec, 0.05, spared.append, sleep=sleep)
    # an unprotected stream (no parity seen): asked at once
    dec.packet(rtp(1, b"a"))
    await rx._send_rtcp_nack(SSRC, [2])
    assert rx.sent == [(SSRC, [2])]
    rx.sent.clear()
    f1 = frame(3, [100, 100], rng)
    for p in f1:
        dec.packet(p)
    dec.parity(make_parity(f1))  # the stream is protected from now on
    f2 = frame(5, [100, 100, 100], rng, ts=12000)
    dec.packet(f2[0])
    dec.packet(f2[2])
    await rx._send_rtcp_nack(SSRC, [2, 6])  # aiortc at the gap: 2 still missing, 6 just lost
    assert rx.sent == [(SSRC, [2])]  # 2 was covered by a parity already: at once
    assert dec.parity(make_parity(f2)) == [f2[1]]
    await asyncio.gather(*rx._send_rtcp_nack.held_tasks)
    assert rx.sent == [(SSRC, [2])] and spared == [1]  # 6 rebuilt: never asked for
    # the frame's parity lost: asked for when the next frame's parity covers it, or at the cap
    f3 = frame(8, [100, 100], rng, ts=15000)
    dec.packet(f3[1])
    t0 = now[0]
    await rx._send_rtcp_nack(SSRC, [8])
    await asyncio.gather(*rx._send_rtcp_nack.held_tasks)
    assert rx.sent[-1] == (SSRC, [8]) and now[0] - t0 == pytest.approx(0.05)


async def test_on_a_real_receiver_a_lost_packet_is_rebuilt_released_and_not_asked_for():
    """The expert's hooks on aiortc's own receive path (its router, NACK generator and our
    jitter buffer): a frame with one packet lost is released whole when its parity comes,
    no NACK leaves for the packet, and the counters say so."""
    rx = VideoReceiver(ExpertVideoConfig(enabled=True), ClockSync())
    pc = RTCPeerConnection()
    try:
        rx.prepare(pc)
        receiver = rx._receivers["us"]
        receiver._RTCRtpReceiver__rtcp_ssrc = 99  # as after negotiation
        rtcp: list[bytes] = []

        async def fake_send_rtcp(packet) -> None:  # in place of the transport
            rtcp.append(bytes(packet))

        receiver._send_rtcp = fake_send_rtcp
        receiver._track = RemoteStreamTrack(kind="video")  # as setRemoteDescription makes it
        vp8 = RTCRtpCodecParameters(mimeType="video/VP8", clockRate=90000, payloadType=96)
        await receiver.receive(
            RTCRtpReceiveParameters(
                codecs=[vp8],
                encodings=[RTCRtpDecodingParameters(ssrc=SSRC, payloadType=96)],
                rtcp=RTCRtcpParameters(ssrc=SSRC),
            )  # fmt: skip
        )
        released: list = []
        rx._taps["us"].on_release = released.append
        key = b"\x10" + b"\x00\x00\x00\x9d\x01\x2a" + bytes(200)  # VP8 descriptor S=1 + key
        f1 = [rtp(1, key, ts=0), rtp(2, b"\x00" + b"k" * 300, ts=0, marker=True)]
        delta = [b"\x10\x01" + b"d" * 400, b"\x00" + b"e" * 401, b"\x00" + b"f" * 90]
        f2 = [rtp(3 + i, d, ts=3000, marker=i == 2) for i, d in enumerate(delta)]
        transport = receiver.transport
        for p in [*f1, make_parity(f1, ssrc=7), f2[0], f2[2]]:  # f2[1] lost
            await transport._handle_rtp_data(p, 0)
        assert len(released) == 1  # the keyframe; the delta waits for its lost packet
        await transport._handle_rtp_data(make_parity(f2, ssrc=7, seq=1), 0)
        assert len(released) == 2 and released[1].data == b"".join(d[1:] for d in delta)
        await asyncio.gather(*receiver._send_rtcp_nack.held_tasks)
        lost = [p.lost for d in rtcp for p in RtcpPacket.parse(d)
                if isinstance(p, RtcpRtpfbPacket)]  # fmt: skip
        assert lost == []
        c = rx.stats()["us"]["jitter"]
        assert c["fec_recovered"] == 1 and c["fec_parity"] == 2 and c["repairs"] == 0
        assert c["fec_nacks_spared"] == 1 and c["gaps_given_up"] == 0
        assert rx.stats()["fec"]["recovered"] == 1
    finally:
        await pc.close()
        await rx.close()


async def test_an_expert_without_fec_drops_parity_as_aiortc_does():
    rx = VideoReceiver(ExpertVideoConfig(enabled=True, fec=False), ClockSync())
    pc = RTCPeerConnection()
    try:
        rx.prepare(pc)
        receiver = rx._receivers["us"]
        assert "fec" not in rx.stats()
        # aiortc's router: an unknown SSRC with a payload type no one registered is dropped
        router = receiver.transport._rtp_router
        from aiortc.rtp import RtpPacket

        assert router.route_rtp(RtpPacket.parse(make_parity([rtp(1, b"a", marker=True)]))) is None
        assert receiver._send_rtcp_nack.__name__ == "_send_rtcp_nack"
    finally:
        await pc.close()
        await rx.close()


async def test_a_failing_parity_coder_never_stops_the_media():
    """An encoder or decoder that raises is logged once and counted; the media packets still
    go out and come in."""
    from humantele.media.aiortc_hooks import receive_parity

    class Broken:
        def protect(self, data: bytes) -> list[bytes]:
            raise RuntimeError("boom")

        def parity(self, data: bytes) -> list[bytes]:
            raise RuntimeError("boom")

        packet = parity

    pc = RTCPeerConnection()
    try:
        transceiver = pc.addTransceiver("video")
        sent: list[bytes] = []
        handled: list[bytes] = []

        async def fake_send(data: bytes) -> None:
            sent.append(data)

        async def fake_handle(data: bytes, arrival_time_ms: int) -> None:
            handled.append(data)

        transport = transceiver.sender.transport
        transport._send_rtp = fake_send
        transport._handle_rtp_data = fake_handle
        broken = Broken()
        protect_sender(transceiver.sender, broken)
        receive_parity(transceiver.receiver, broken)
        media = rtp(1, b"m", marker=True)
        await transport._send_rtp(media)
        await transport._send_rtp(media[:2] + b"\x00\x02" + media[4:])
        await transport._handle_rtp_data(media, 0)
        await transport._handle_rtp_data(make_parity([media]), 0)
        assert sent == [media, media[:2] + b"\x00\x02" + media[4:]] and handled == [media]
        assert broken.errors == 4  # two sends, one packet, one parity
    finally:
        await pc.close()

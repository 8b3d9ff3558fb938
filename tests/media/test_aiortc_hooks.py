"""humantele.media.aiortc_hooks, the one module that touches aiortc's private state: these
fail if aiortc renames or retypes what it relies on. That aiortc really uses what the hooks
install is checked on a live link (test_video_link: our encoders' and jitter buffers'
counters move)."""

from __future__ import annotations

import asyncio

import av
import numpy as np
import pytest
from aiortc import RTCPeerConnection
from aiortc.codecs.vpx import Vp8Encoder as AiortcVp8Encoder
from aiortc.jitterbuffer import JitterBuffer
from aiortc.rtcrtpreceiver import RemoteStreamTrack

from humantele.media import aiortc_hooks
from humantele.media.aiortc_hooks import (
    AiortcChanged,
    newest_frame,
    sender_encoder,
    use_encoder,
    use_jitter_buffer,
)
from humantele.media.config import BitrateConfig, ExpertVideoConfig
from humantele.media.encoders import Vp8Encoder
from humantele.media.jitter import BoundedJitterBuffer, vp8_is_keyframe
from humantele.media.receiver import VideoReceiver
from humantele.transport.clocksync import ClockSync
from humantele.video.counter import draw_counter


async def test_a_new_sender_and_receiver_have_what_the_hooks_replace():
    pc = RTCPeerConnection()
    try:
        t = pc.addTransceiver("video")
        # aiortc 1.16: the sender makes its encoder on the first frame; the receiver's video
        # jitter buffer is its JitterBuffer
        assert sender_encoder(t.sender) is None
        assert isinstance(getattr(t.receiver, aiortc_hooks._RECEIVER_JITTER), JitterBuffer)
        encoder = Vp8Encoder(BitrateConfig())
        use_encoder(t.sender, encoder)
        assert sender_encoder(t.sender) is encoder
        buffer = BoundedJitterBuffer(vp8_is_keyframe)
        use_jitter_buffer(t.receiver, buffer)
        assert getattr(t.receiver, aiortc_hooks._RECEIVER_JITTER) is buffer
        assert isinstance(encoder, AiortcVp8Encoder)  # aiortc's packetisation is kept
        # the NACK the jitter buffer asks again with: aiortc's receiver's own coroutine
        coro = aiortc_hooks.request_retransmission(t.receiver, 1234, [7, 5])
        assert asyncio.iscoroutine(coro)
        await coro  # no RTCP SSRC before negotiation: sends nothing, raises nothing
    finally:
        await pc.close()


def test_a_hook_on_an_object_without_the_attribute_is_a_clear_error():
    with pytest.raises(AiortcChanged, match="aiortc changed"):
        use_encoder(object(), Vp8Encoder(BitrateConfig()))  # type: ignore[arg-type]
    with pytest.raises(AiortcChanged, match="aiortc changed"):
        use_jitter_buffer(object(), BoundedJitterBuffer(vp8_is_keyframe))  # type: ignore[arg-type]
    with pytest.raises(AiortcChanged, match="aiortc changed"):
        newest_frame(object(), None)
    with pytest.raises(AiortcChanged, match="aiortc changed"):
        aiortc_hooks.request_retransmission(object(), 1, [2])  # type: ignore[arg-type]


def _frame(seq: int) -> av.VideoFrame:
    img = np.zeros((64, 96, 3), np.uint8)
    draw_counter(img, seq)
    frame = av.VideoFrame.from_ndarray(img, format="bgr24").reformat(format="yuv420p")
    frame.pts = seq * 4500
    return frame


async def test_a_receiver_that_fell_behind_takes_the_newest_decoded_frame():
    """Three frames decoded while the expert's loop was busy: it handles only the newest."""
    rx = VideoReceiver(ExpertVideoConfig(enabled=True), ClockSync())
    pc = object()
    rx._pc = pc  # type: ignore[assignment]
    track = RemoteStreamTrack(kind="video")
    for seq in (1, 2, 3):  # as aiortc's decoder thread delivers them
        track._queue.put_nowait(_frame(seq))
    task = asyncio.ensure_future(rx._consume(pc, "us", track))  # type: ignore[arg-type]
    try:
        for _ in range(200):
            if rx.stats_by_track["us"].frames:
                break
            await asyncio.sleep(0.01)
        st = rx.stats_by_track["us"]
        assert st.frames == 1 and st.stale_dropped == 2
        assert rx.latest("us").seq == 3
        track._queue.put_nowait(_frame(4))  # one more, with nothing queued behind it
        for _ in range(200):
            if st.frames == 2:
                break
            await asyncio.sleep(0.01)
        assert rx.latest("us").seq == 4 and st.stale_dropped == 2
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


def test_frames_without_a_counter_get_their_capture_time_from_the_records_and_rtp():
    """A real source's picture is sent unaltered (no counter drawn): the frame records and the
    RTP timestamps alone give each frame its capture time, once the frames agree on one anchor."""
    from humantele.media.frameinfo import FrameInfo
    from humantele.transport.clocksync import SyncSample

    clock = ClockSync()
    clock.best = SyncSample(offset=0.0, rtt=0.001, t_local=0.0)
    rx = VideoReceiver(ExpertVideoConfig(enabled=True), clock, now=lambda: 100.0)
    pc = object()
    rx._pc = pc  # type: ignore[assignment]
    rng = np.random.default_rng(1)
    t_capture = 50.0 + np.cumsum(0.05 + rng.uniform(-0.004, 0.004, 12))  # 20 fps, jittered
    for seq, t in enumerate(t_capture, start=1):
        rx._on_info(pc, FrameInfo("us", seq, float(t)).encode())
    first = int(round(t_capture[2] * 90000))  # the receiver's pts count from its first frame
    got = []
    for t in t_capture[2:8]:  # frames 3..8 arrive (1 and 2 were lost), no counter in them
        frame = av.VideoFrame.from_ndarray(np.full((64, 96, 3), 90, np.uint8), format="bgr24")
        frame = frame.reformat(format="yuv420p")
        frame.pts = int(round(t * 90000)) - first
        rx._on_frame("us", frame)
        got.append(rx.latest("us").t_capture)
    assert got[0] is None  # one frame alone allows many anchors
    assert None not in got[2:]  # a few frames narrow them down to one (here by the third)
    for g, t in zip(got, t_capture[2:8], strict=True):
        assert g is None or g == pytest.approx(t, abs=3e-5)  # never a wrong capture time
    st = rx.stats_by_track["us"]
    assert st.unreadable == 6 and st.anchor == first  # capture time = (pts + anchor) / 90 kHz


async def test_a_lost_clock_sync_ping_does_not_stretch_the_video_waits():
    """The clock sync's pings go over the reliable control channel: a lost one waits for
    SCTP's retransmission (>= 1 s). The expert's jitter buffers must not take that for the
    link's round trip: it made the wait for every lost video packet, the keyframe requests'
    repeat and the re-asking 1 s on any lossy link (a freeze of up to 1 s per loss)."""
    from humantele.wire import Pong

    t = {"now": 0.0}
    clock = ClockSync(clock=lambda: t["now"])
    for rtt in [0.02] * 10 + [1.3] + [0.02] * 3:
        ping = clock.make_ping()
        t["now"] += rtt
        clock.on_pong(Pong(seq=ping.seq, t0=ping.t0, t1=ping.t0, t2=ping.t0))
    assert clock.high_rtt == pytest.approx(1.3) and clock.rtt == pytest.approx(0.02)
    rx = VideoReceiver(ExpertVideoConfig(enabled=True), clock)
    pc = RTCPeerConnection()
    try:
        rx.prepare(pc)
        assert set(rx._jitter) == {"us", "pov"}
        for buf in rx._jitter.values():
            assert buf.wait_s() == pytest.approx(0.1) and buf.pli_every_s() == 0.5
            assert buf.renack_every_s() == pytest.approx(0.035)
    finally:
        await pc.close()


async def test_forget_missing_stops_the_receivers_nacks_for_given_up_packets():
    from aiortc.rtp import RtpPacket

    from humantele.media.aiortc_hooks import EncodedFrameTap, forget_missing

    pc = RTCPeerConnection()
    try:
        receiver = pc.addTransceiver("video").receiver
        generator = receiver._RTCRtpReceiver__nack_generator
        for seq in (10, 14):  # 11-13 missing
            generator.add(RtpPacket(sequence_number=seq))
        assert generator.missing == {11, 12, 13}
        assert forget_missing(receiver, [11, 12, 99]) == 2
        assert generator.missing == {13}

        class GivesUp:  # a buffer that has just given up on 13
            def add(self, packet):
                return False, None

            def take_given_up(self):
                return [13]

        tap = EncodedFrameTap(GivesUp(), None)
        tap.on_give_up = lambda seqs: forget_missing(receiver, seqs)
        tap.add(RtpPacket(sequence_number=15))
        assert generator.missing == set()
    finally:
        await pc.close()


def test_the_tap_sends_the_nacks_its_buffer_asks_for_between_packets():
    from aiortc.rtp import RtpPacket

    from humantele.media.aiortc_hooks import EncodedFrameTap

    class Renacks:  # a buffer whose poll asks again for 7
        def __init__(self):
            self.polled, self.out = 0, []

        def add(self, packet):
            return False, None

        def poll(self):
            self.polled += 1
            self.out = [7]

        def take_nacks(self):
            out, self.out = self.out, []
            return out

    sent = []
    tap = EncodedFrameTap(Renacks(), None)
    tap.on_nack = lambda ssrc, lost: sent.append((ssrc, lost))
    tap.poll()
    assert sent == []  # no stream known yet: nothing to send to
    tap.add(RtpPacket(sequence_number=5, ssrc=1234))
    tap.poll()
    assert sent == [(1234, [7])] and tap.buffer.polled == 2


async def test_each_nack_a_receiver_sends_leaves_twice():
    """aiortc's own NACK at a new gap and request_retransmission's both go through the
    receiver's ``_send_rtcp_nack``: each leaves again ``after_s`` later, counted; a PLI not."""
    from aiortc.rtp import RtcpPacket, RtcpPsfbPacket, RtcpRtpfbPacket

    from humantele.media.aiortc_hooks import repeat_nacks, request_keyframe

    pc = RTCPeerConnection()
    try:
        receiver = pc.addTransceiver("video").receiver
        receiver._RTCRtpReceiver__rtcp_ssrc = 99  # as after negotiation
        sent: list[tuple[float, bytes]] = []
        now = [0.0]

        async def fake_send_rtcp(packet) -> None:  # in place of the transport
            sent.append((now[0], bytes(packet)))

        async def sleep(s: float) -> None:
            now[0] += s

        receiver._send_rtcp = fake_send_rtcp
        repeats = []
        repeat_nacks(receiver, 0.005, lambda: repeats.append(now[0]), sleep=sleep)
        await receiver._send_rtcp_nack(1234, [5, 7])  # as aiortc's receive path calls it
        await aiortc_hooks.request_retransmission(receiver, 1234, [9])
        await asyncio.gather(*receiver._send_rtcp_nack.tasks)
        nacks = [(t, RtcpPacket.parse(d)[0]) for t, d in sent]
        assert all(isinstance(p, RtcpRtpfbPacket) for _, p in nacks)
        assert sorted(p.lost for _, p in nacks) == [[5, 7], [5, 7], [9], [9]]
        assert [t for t, _ in nacks] == [0.0, 0.0, 0.005, 0.01] and len(repeats) == 2
        sent.clear()
        await request_keyframe(receiver, 1234)  # other RTCP: once
        assert len(sent) == 1 and isinstance(RtcpPacket.parse(sent[0][1])[0], RtcpPsfbPacket)
        assert not receiver._send_rtcp_nack.tasks
    finally:
        await pc.close()


async def test_the_expert_repeats_its_nacks_unless_told_not_to():
    for on in (True, False):
        rx = VideoReceiver(ExpertVideoConfig(enabled=True, repeat_nacks=on), ClockSync())
        pc = RTCPeerConnection()
        try:
            rx.prepare(pc)
            for receiver in rx._receivers.values():
                assert hasattr(receiver._send_rtcp_nack, "tasks") is on
        finally:
            await pc.close()

"""The follower's encoders (humantele.media.encoders) through aiortc's decoders: the frame
counter reads on every sim US frame at the default settings, the bit rate stays within the
track's limits whatever REMB says, keyframes come when asked; bad bit-rate configs are refused
with the field's name."""

from __future__ import annotations

import fractions

import av
import cv2
import numpy as np
import pytest
from aiortc.codecs.h264 import H264Decoder, h264_depayload
from aiortc.codecs.vpx import Vp8Decoder, vp8_depayload
from aiortc.jitterbuffer import JitterFrame

from humantele.config import ConfigError, validate_config
from humantele.media import encoders
from humantele.media.config import BitrateConfig, FollowerVideoConfig
from humantele.media.encoders import make_encoder, two_packets
from humantele.media.jitter import h264_is_keyframe, vp8_is_keyframe
from humantele.media.receiver import luma_plane
from humantele.video.counter import read_counter
from humantele.video.scene import DemoScene
from humantele.video.sim_ultrasound import SimUltrasound, SimUltrasoundConfig

CODECS = {
    "video/VP8": (Vp8Decoder, vp8_depayload, vp8_is_keyframe),
    "video/H264": (H264Decoder, h264_depayload, h264_is_keyframe),
}


def sim_us_frames(n: int) -> list[tuple[int, av.VideoFrame]]:
    """``n`` default-size sim US frames of the demo scene at 20 fps, as the follower sends
    them (I420, pts at 90 kHz)."""
    t = {"now": 0.0}
    scene = DemoScene(clock=lambda: t["now"])
    source = SimUltrasound(SimUltrasoundConfig(), scene)
    out = []
    for i in range(n):
        t["now"] = i / 20.0
        f = source.render(scene())
        frame = av.VideoFrame.from_ndarray(
            cv2.cvtColor(f.image, cv2.COLOR_BGR2YUV_I420), format="yuv420p"
        )
        frame.pts, frame.time_base = i * 4500, fractions.Fraction(1, 90000)
        out.append((f.seq, frame))
    return out


@pytest.fixture(scope="module")
def us_frames():
    return sim_us_frames(80)


def round_trip(mime, encoder, frames, keyframe_at=(), decoder=None):
    """Encode with ``encoder``, depayload and decode with aiortc's decoder (a new one unless
    given): [(seq, decoded frame, its payloads, was it a keyframe)]."""
    decoder_class, depayload, is_key = CODECS[mime]
    decoder = decoder or decoder_class()
    out = []
    for i, (seq, frame) in enumerate(frames):
        # as sim_us_frames stamped it (aiortc's H.264 encoder restamps the frames it gets)
        frame.pts, frame.time_base = (seq - 1) * 4500, fractions.Fraction(1, 90000)
        payloads, ts = encoder.encode(frame, i in keyframe_at)
        data = b"".join(depayload(p) for p in payloads)
        for d in decoder.decode(JitterFrame(data, ts)):
            out.append((seq, d, payloads, is_key(data)))
    return out


def luma_counter(frame: av.VideoFrame) -> int | None:
    return read_counter(np.ascontiguousarray(luma_plane(frame)[:32, :64]))


@pytest.mark.parametrize("mime", ["video/VP8", "video/H264"])
def test_the_counter_reads_on_every_us_frame_at_the_default_settings(us_frames, mime):
    limits = FollowerVideoConfig().us_bitrate
    out = round_trip(mime, make_encoder(mime, limits), us_frames)
    assert len(out) == len(us_frames)
    assert [luma_counter(d) for _, d, _, _ in out] == [seq for seq, _, _, _ in out]


@pytest.mark.parametrize("kbps", [250, 4000])
def test_the_counter_reads_at_the_low_and_high_ends_of_the_bit_rates(us_frames, kbps):
    limits = BitrateConfig(start_kbps=kbps, min_kbps=kbps, max_kbps=kbps)
    out = round_trip("video/VP8", make_encoder("video/VP8", limits), us_frames[:60])
    assert all(luma_counter(d) == seq for seq, d, _, _ in out)


def rate_kbps(out, fps=20.0):
    """The mean bit rate (kbit/s) of round_trip's output."""
    return np.mean([sum(len(p) for p in payloads) for _, _, payloads, _ in out]) * 8 * fps / 1e3


def test_remb_moves_the_bit_rate_of_the_running_encoder_within_the_limits(us_frames):
    limits = BitrateConfig(start_kbps=800, min_kbps=400, max_kbps=1200)
    enc, dec = make_encoder("video/VP8", limits), Vp8Decoder()
    round_trip("video/VP8", enc, us_frames[:5], decoder=dec)
    assert enc.target_bitrate == 800_000 and enc.restarts == 1
    enc.target_bitrate = 100_000  # REMB far below the floor
    assert enc.target_bitrate == 400_000
    low = round_trip("video/VP8", enc, us_frames[5:30], decoder=dec)
    enc.target_bitrate = 9_000_000  # and far above the ceiling
    assert enc.target_bitrate == 1_200_000
    high = round_trip("video/VP8", enc, us_frames[30:55], decoder=dec)
    # the same encoder all along: no reopening, no keyframe, every frame decoded and read
    assert enc.restarts == 1 and enc.reconfigurations == 2
    assert not any(key for *_, key in low + high)
    assert all(luma_counter(d) == seq for seq, d, _, _ in low + high)
    assert rate_kbps(low[5:]) < 600 < 900 < rate_kbps(high[5:])


def test_a_smaller_frame_is_a_live_resize_with_one_keyframe_not_a_reopening(us_frames):
    enc, dec = make_encoder("video/VP8", BitrateConfig(), max_size=(640, 480)), Vp8Decoder()
    round_trip("video/VP8", enc, us_frames[:5], decoder=dec)
    half = []
    for seq, frame in us_frames[5:15]:
        small = frame.reformat(width=320, height=240)
        small.pts, small.time_base = frame.pts, frame.time_base
        half.append((seq, small))
    out = round_trip("video/VP8", enc, half, decoder=dec)
    out += round_trip("video/VP8", enc, us_frames[15:20], decoder=dec)
    assert [key for *_, key in out] == [True] + [False] * 9 + [True] + [False] * 4
    assert [d.width for _, d, _, _ in out] == [320] * 10 + [640] * 5
    assert enc.restarts == 1 and enc.resizes == 2


def test_keyframe_requests_within_a_round_trip_of_a_keyframe_are_answered_once(us_frames):
    enc = make_encoder("video/VP8", BitrateConfig())
    enc.rtt_s = 0.18  # frames every 50 ms: one keyframe per 0.23 s at most
    out = round_trip("video/VP8", enc, us_frames[:30], keyframe_at=set(range(10, 30)))
    keys = [i for i, (*_, key) in enumerate(out) if key]
    assert keys == [0, 10, 15, 20, 25]
    assert enc.keyframes_forced == 20 and enc.keyframes_suppressed == 16
    enc.rtt_s = 5.0  # a slow link never stretches it past the receiver's 0.5 s repeat
    assert enc.keyframe_interval_s() < 0.5


def test_a_keyframe_request_within_the_interval_is_deferred_not_dropped(us_frames):
    """The receiver asks again 100 ms after a keyframe (that keyframe lost a packet for good):
    the request is answered once the interval has passed, not only at the receiver's next
    request 0.5 s or more later."""
    enc = make_encoder("video/VP8", BitrateConfig())
    enc.rtt_s = 0.18  # frames every 50 ms: one keyframe per 0.23 s at most
    out = round_trip("video/VP8", enc, us_frames[:20], keyframe_at={2})
    keys = [i for i, (*_, key) in enumerate(out) if key]
    assert keys == [0, 5]  # 0.25 s after the first: the first frame past 0.23 s; once
    assert enc.keyframes_suppressed == 1 and enc.keyframes_deferred == 1


def test_without_libvpx_ffmpegs_encoder_is_reopened_on_a_rate_move(us_frames, monkeypatch):
    monkeypatch.setattr(encoders, "USE_LIBVPX", False)
    limits = BitrateConfig(start_kbps=800, min_kbps=400, max_kbps=1200)
    enc, dec = make_encoder("video/VP8", limits), Vp8Decoder()
    round_trip("video/VP8", enc, us_frames[:5], decoder=dec)
    enc.target_bitrate = 9_000_000
    out = round_trip("video/VP8", enc, us_frames[5:40], decoder=dec)
    assert enc.restarts == 2 and out[0][3]  # reopened at the new rate: a keyframe first
    assert rate_kbps(out[5:]) > 800
    enc.target_bitrate = 1_150_000  # within 10 %: no reopening (no keyframe)
    out = round_trip("video/VP8", enc, us_frames[40:45], decoder=dec)
    assert enc.restarts == 2 and not any(key for *_, key in out)


@pytest.mark.parametrize("mime", ["video/VP8", "video/H264"])
def test_a_keyframe_when_the_receiver_asks(us_frames, mime):
    enc = make_encoder(mime, BitrateConfig())
    out = round_trip(mime, enc, us_frames[:12], keyframe_at={8})
    keys = [i for i, (*_, key) in enumerate(out) if key]
    assert keys == [0, 8] and enc.keyframes_forced == 1


def test_a_small_vp8_frame_goes_in_two_packets_that_depayload_to_it():
    data = bytes(range(200))
    payloads = two_packets(data, 1234)
    assert len(payloads) == 2
    assert b"".join(vp8_depayload(p) for p in payloads) == data


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"us_bitrate": {"start_kbps": 10}}, "us_bitrate.start_kbps"),
        ({"pov_bitrate": {"max_kbps": 1e9}}, "pov_bitrate.max_kbps"),
        ({"us_bitrate": {"min_kbps": 3000, "start_kbps": 1000}}, "min_kbps"),
        ({"us_bitrate": {"start_kbps": 900, "max_kbps": 800}}, "max_kbps"),
        ({"us_bitrate": {"start_kbps": "fast"}}, "us_bitrate.start_kbps"),
        ({"us_bitrate": {"kbps": 500}}, "us_bitrate.kbps"),
    ],
)
def test_bad_bit_rates_are_refused_with_the_field_name(data, field):
    with pytest.raises(ConfigError) as err:
        validate_config(FollowerVideoConfig, data, "follower.toml")
    assert field in str(err.value) and "follower.toml" in str(err.value)


def test_an_unknown_codec_has_no_encoder():
    with pytest.raises(ValueError, match="video/AV1"):
        make_encoder("video/AV1", BitrateConfig())


def dark_frame(like: av.VideoFrame, pts: int) -> av.VideoFrame:
    """A black I420 frame (the sim US before the probe touches the patient)."""
    y = np.full((like.height, like.width), 16, np.uint8)
    uv = np.full((like.height // 2, like.width), 128, np.uint8)
    frame = av.VideoFrame.from_ndarray(np.concatenate([y, uv]), format="yuv420p")
    frame.pts, frame.time_base = pts, fractions.Fraction(1, 90000)
    return frame


def test_the_first_picture_after_a_dark_run_stays_near_its_budget(us_frames):
    """libvpx lowers the quantizer to qmin on frames that cannot spend their budget (black):
    the first picture after them came out at about 51 kB at 500 kbit/s (a frame's budget is
    3.1 kB), a burst a thin link's queue drops. The quantizer floor holds it near the last
    picture's; steady frames are unchanged (they spend their budget)."""
    enc = make_encoder("video/VP8", BitrateConfig(start_kbps=500, min_kbps=500, max_kbps=500))
    frames = [f for _, f in us_frames]
    sizes, pts = [], 0
    seq = frames[:20] + [dark_frame(frames[0], 0)] * 40 + frames[20:60]
    for frame in seq:
        frame.pts, frame.time_base = pts, fractions.Fraction(1, 90000)
        pts += 4500
        payloads, _ = enc.encode(frame)
        sizes.append(sum(len(p) for p in payloads))
    budget = 500_000 / 8 / 20
    assert enc.figures()["libvpx"]
    assert max(sizes[50:60]) < 200  # dark frames cost next to nothing
    assert sizes[60] < 3 * budget  # was ~16 x
    assert sum(sizes[60:64]) < 4 * 3 * budget
    assert np.mean(sizes[70:]) == pytest.approx(budget, rel=0.3)  # the steady rate as before
    assert enc.oversized == 0 and enc.q_floor > 2

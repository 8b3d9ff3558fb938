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


def test_remb_moves_the_bit_rate_only_within_the_limits_and_reopens_the_encoder(us_frames):
    limits = BitrateConfig(start_kbps=800, min_kbps=400, max_kbps=1200)
    enc, dec = make_encoder("video/VP8", limits), Vp8Decoder()
    round_trip("video/VP8", enc, us_frames[:5], decoder=dec)
    assert enc.target_bitrate == 800_000 and enc.restarts == 1
    enc.target_bitrate = 100_000  # REMB far below the floor
    assert enc.target_bitrate == 400_000
    enc.target_bitrate = 9_000_000  # and far above the ceiling
    assert enc.target_bitrate == 1_200_000
    out = round_trip("video/VP8", enc, us_frames[5:40], decoder=dec)
    assert enc.restarts == 2 and out[0][3]  # reopened at the new rate: a keyframe first
    sizes = [sum(len(p) for p in payloads) for _, _, payloads, _ in out[5:]]
    assert np.mean(sizes) * 8 * 20 > 800_000  # now above the starting 800 kbit/s
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

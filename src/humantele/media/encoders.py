"""The follower's video encoders: aiortc's VP8 and H.264 encoders with each track's bit-rate
limits, and VP8 without libvpx's temporal denoiser and encode breakout.

**Bit rate.** aiortc's encoders start at a fixed rate (VP8 500 kbit/s, H.264 1 Mbit/s) and
clamp the expert's congestion feedback (REMB, set by aiortc as ``encoder.target_bitrate``) to
fixed limits (250-1500 and 500-3000 kbit/s). Ours start at the track's
:class:`~humantele.media.config.BitrateConfig` ``start_kbps`` and clamp REMB to its
``min_kbps``-``max_kbps``. PyAV cannot change the rate of an open libvpx or libx264 encoder (a
new ``bit_rate`` is ignored), so, as in aiortc, the encoder is reopened (a keyframe) when the
target has moved by more than 10 %; ``restarts`` counts the openings.

**VP8 settings.** aiortc's real-time libvpx settings less two: ``noise-sensitivity`` (aiortc 4,
here 0: no temporal denoiser) and ``static-thresh`` (aiortc 1, here 0: no encode breakout).
With both on, libvpx's real-time mode decision skips the residual of some macroblocks whose
source changed, so the decoded block is the previous frame's; the encode breakout's chroma
test (``2 * sse_uv < static-thresh``) always passes on exactly grey content. The US image is
grey, and its frame counter (black and white 8 px cells on black) read wrong on 10-16 % of
frames through aiortc's encoder offline (25 % in the demo), always one cell of the previous
frame's number; either setting at 0 gives 0 of 200, and so does a counter with chroma noise
(``humantele bench video``, docs/video.md). Speckle is the image, not noise to smooth away.

H.264 keeps aiortc's settings (libx264 zerolatency, Baseline); only its limits are ours.
"""

from __future__ import annotations

import multiprocessing
from typing import Any

import av
from aiortc.codecs import h264, vpx
from aiortc.codecs.base import Encoder
from aiortc.mediastreams import VIDEO_TIME_BASE, convert_timebase

from humantele.media.config import BitrateConfig

RESTART_CHANGE = 0.1  # reopen the encoder when the target moved by more than this fraction

VP8_OPTIONS = {  # aiortc 1.16's, less the denoiser and the encode breakout (module doc)
    "cpu-used": "-6",
    "deadline": "realtime",
    "lag-in-frames": "0",
    "noise-sensitivity": "0",
    "static-thresh": "0",
    "overshoot-pct": "15",
    "undershoot-pct": "100",
    "partitions": "0",  # one token partition
}


class _Limits:
    """The target bit rate (bit/s) within a track's limits; counts encoder (re)openings."""

    def _init_limits(self, limits: BitrateConfig) -> None:
        self.limits = limits
        self._target = limits.start_kbps * 1000
        self.restarts = 0  # encoder openings (the first included)
        self.keyframes_forced = 0  # keyframes asked for by the receiver (PLI/FIR)

    @property
    def target_bitrate(self) -> int:
        """Target bit rate (bit/s); aiortc sets it on each REMB, clamped to the limits."""
        return self._target

    @target_bitrate.setter
    def target_bitrate(self, bitrate: int) -> None:
        lo, hi = self.limits.min_kbps * 1000, self.limits.max_kbps * 1000
        self._target = max(lo, min(int(bitrate), hi))

    def _stale(self, codec: Any, width: int, height: int) -> bool:
        """The open encoder no longer fits: another size, or the target moved too far."""
        return (
            codec.width != width
            or codec.height != height
            or abs(self._target - codec.bit_rate) > RESTART_CHANGE * codec.bit_rate
        )

    def figures(self) -> dict[str, Any]:
        return {
            "bitrate_kbps": round(self._target / 1000),
            "restarts": self.restarts,
            "keyframes_forced": self.keyframes_forced,
        }


class Vp8Encoder(_Limits, vpx.Vp8Encoder):
    """aiortc's VP8 encoder (its packetisation) with our libvpx settings and limits."""

    def __init__(self, limits: BitrateConfig) -> None:
        vpx.Vp8Encoder.__init__(self)
        self._init_limits(limits)

    def _open(self, width: int, height: int) -> Any:
        rate = self._target
        codec = av.CodecContext.create("libvpx", "w")
        codec.width, codec.height, codec.pix_fmt = width, height, "yuv420p"
        codec.bit_rate = rate
        codec.gop_size = 3000  # keyframes only when asked (PLI) or reopened
        codec.qmin, codec.qmax = 2, 56
        # bufsize: a 1 s rate-control buffer; minrate = maxrate = bit_rate: constant bit rate
        codec.options = {**VP8_OPTIONS, "bufsize": str(rate), "minrate": str(rate),
                         "maxrate": str(rate)}  # fmt: skip
        codec.thread_count = vpx.number_of_threads(width * height, multiprocessing.cpu_count())
        self.restarts += 1
        return codec

    def encode(self, frame: Any, force_keyframe: bool = False) -> tuple[list[bytes], int]:
        if frame.format.name != "yuv420p":
            frame = frame.reformat(format="yuv420p")
        if self.codec is not None and self._stale(self.codec, frame.width, frame.height):
            self.codec = None
        if self.codec is None:
            self.codec = self._open(frame.width, frame.height)
        if force_keyframe:
            frame.pict_type = av.video.frame.PictureType.I
            self.keyframes_forced += 1
        data = b"".join(bytes(p) for p in self.codec.encode(frame))
        payloads = self._packetize(data, self.picture_id)
        if len(payloads) == 1 and len(data) >= 2:
            payloads = two_packets(data, self.picture_id)
        timestamp = convert_timebase(frame.pts, frame.time_base, VIDEO_TIME_BASE)
        self.picture_id = (self.picture_id + 1) % (1 << 15)
        return payloads, timestamp


def two_packets(data: bytes, picture_id: int) -> list[bytes]:
    """A VP8 frame of one packet's size in two RTP payloads. The expert's jitter buffer hands
    the decoder at most one frame per packet it receives, so a stream of one-packet frames
    never catches up once frames have queued behind a retransmitted packet; two packets per
    frame do (``humantele.media.jitter``). Costs one packet header (~40 B) a frame."""
    half = (len(data) + 1) // 2
    descriptor = vpx.VpxPayloadDescriptor(partition_start=1, partition_id=0, picture_id=picture_id)
    first = bytes(descriptor) + data[:half]
    descriptor.partition_start = 0
    return [first, bytes(descriptor) + data[half:]]


class H264Encoder(_Limits, h264.H264Encoder):
    """aiortc's H.264 encoder with our limits."""

    def __init__(self, limits: BitrateConfig) -> None:
        h264.H264Encoder.__init__(self)
        self._init_limits(limits)

    def encode(self, frame: Any, force_keyframe: bool = False) -> tuple[list[bytes], int]:
        before = self.codec
        if force_keyframe:
            self.keyframes_forced += 1
        out = h264.H264Encoder.encode(self, frame, force_keyframe)
        if self.codec is not before and self.codec is not None:
            self.restarts += 1
        return out


ENCODERS: dict[str, type[Vp8Encoder | H264Encoder]] = {
    "video/vp8": Vp8Encoder,
    "video/h264": H264Encoder,
}  # the codecs we encode, by lower-case MIME type


def make_encoder(mime_type: str, limits: BitrateConfig) -> Encoder:
    """Our encoder for a negotiated codec (``video/VP8`` or ``video/H264``, any case)."""
    encoder = ENCODERS.get(mime_type.lower())
    if encoder is None:
        raise ValueError(f"no encoder for {mime_type}")
    return encoder(limits)

"""The follower's video encoders: aiortc's VP8 and H.264 encoders with each track's bit-rate
limits, and VP8 without libvpx's temporal denoiser and encode breakout.

**Bit rate.** aiortc's encoders start at a fixed rate (VP8 500 kbit/s, H.264 1 Mbit/s) and
clamp the expert's congestion feedback (REMB, set by aiortc as ``encoder.target_bitrate``) to
fixed limits (250-1500 and 500-3000 kbit/s). Ours start at the track's
:class:`~humantele.media.config.BitrateConfig` ``start_kbps`` and clamp REMB to its
``min_kbps``-``max_kbps`` and to the link budget's share (:meth:`_Limits.set_budget`). VP8 runs
on libvpx itself (:mod:`humantele.media.vpx`): a new target is applied to the running encoder,
no keyframe. PyAV cannot change the rate of an open FFmpeg encoder (a new ``bit_rate`` is
ignored), so without a usable libvpx, and for H.264, as in aiortc, the encoder is reopened (a
keyframe) when the target has moved by more than 10 %; ``restarts`` counts the openings.

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
import numpy as np
from aiortc.codecs import h264, vpx
from aiortc.codecs.base import Encoder
from aiortc.mediastreams import VIDEO_TIME_BASE, convert_timebase

from humantele.media.config import MIN_KBPS, BitrateConfig

RESTART_CHANGE = 0.1  # FFmpeg's encoder: reopen it when the target moved by more than this
USE_LIBVPX = True  # VP8 on libvpx itself when it loads (humantele.media.vpx); tests switch
VIDEO_CLOCK_HZ = 90_000  # RTP video clock
MIN_KEYFRAME_GAP_S = 0.15  # keyframes asked for: at most one per round trip, within these (s)
MAX_KEYFRAME_GAP_S = 0.45  # below the receiver's 0.5 s repeat, so a repeat is always answered
MAX_INTRA_PCT = 300  # a keyframe at most this % of an average frame's budget (WebRTC's floor)
# The quantizer floor (libvpx, VP8 on libvpx itself; docs/video.md, "Thin, lossy links"): a
# frame that spends under SPENT_SHARE of its budget (a dark or still picture) says nothing of
# the quantizer the picture needs, yet libvpx lowers it to qmin for it; the first frame in
# contact was then 51 kB at a 500 kbit/s target (budget 3 kB). The quantizer may fall at most
# Q_FALL below the last frame that spent its budget (Q_START before one has).
SPENT_SHARE = 0.25
Q_FALL = 8
Q_START = 40
OVERSIZED = 4.0  # a frame over this many times its budget is counted (``oversized``)

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

LIBVPX_OPTIONS = {  # the same settings on libvpx itself (humantele.media.vpx.LiveVp8)
    "cpu_used": -6, "noise_sensitivity": 0, "static_thresh": 0, "partitions": 0,
    "undershoot_pct": 100, "overshoot_pct": 15, "qmin": 2, "qmax": 56, "buf_ms": 1000,
    "max_intra_pct": MAX_INTRA_PCT,
}  # fmt: skip


class _Limits:
    """The target bit rate (bit/s) within a track's limits; counts encoder (re)openings."""

    def _init_limits(self, limits: BitrateConfig) -> None:
        self.limits = limits
        self._target = limits.start_kbps * 1000
        self.remb: int | None = None  # the expert's last estimate for this track (bit/s)
        self.cap: int | None = None  # the link budget's share for this track (bit/s)
        self.floor: int | None = None  # the floor at the track's level (bit/s), if lower
        self.restarts = 0  # encoder openings (the first included)
        self.keyframes_forced = 0  # keyframes asked for by the receiver (PLI/FIR)

    @property
    def target_bitrate(self) -> int:
        """Target bit rate (bit/s); aiortc sets it on each REMB, clamped to the limits (and
        to the link budget's share, :meth:`set_budget`)."""
        return self._target

    @target_bitrate.setter
    def target_bitrate(self, bitrate: int) -> None:
        self.remb = int(bitrate)
        self._retarget()

    def set_budget(self, cap: int | None, floor: int | None = None) -> None:
        """The link budget's share for this track (bit/s; None: no cap) and its floor at the
        track's level (bit/s; None: the configured ``min_kbps``; never above it)."""
        self.cap, self.floor = cap, floor
        self._retarget()

    def _retarget(self) -> None:
        lo, hi = self.limits.min_kbps * 1000, self.limits.max_kbps * 1000
        if self.floor is not None:
            lo = min(lo, max(MIN_KBPS * 1000, int(self.floor)))
        want = self.remb if self.remb is not None else self._target
        if self.cap is not None:
            want = min(want, int(self.cap))
        self._target = max(lo, min(int(want), hi))

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
    """aiortc's VP8 encoder (its packetisation) with our libvpx settings and limits.

    On libvpx itself (:mod:`humantele.media.vpx`): a new target bit rate (REMB, the link
    budget) is applied to the running encoder (``reconfigurations``, no keyframe), a smaller
    frame (the POV's level) too, with one keyframe (``resizes``); the encoder is opened again
    only for a frame larger than its first (``restarts``). Without a usable libvpx, FFmpeg's
    encoder through PyAV, reopened on each move of more than 10 % (a keyframe each time).

    Keyframes asked for by the receiver (PLI) come at most once per
    :meth:`keyframe_interval_s` (about a round trip, ``rtt_s`` as the sender measures it): on
    a lossy link this keeps a PLI storm from becoming a stream of keyframes (each 3-10 times a
    delta frame, so more packets to lose). A request within it is deferred, not dropped: the
    keyframe comes once the interval has passed (``keyframes_deferred``). Dropped, a request
    made because the last keyframe itself could not be repaired was answered only at the
    receiver's next request, 0.5 s or more later: a freeze that long each time. A keyframe's
    size is capped at ``MAX_INTRA_PCT`` % of an average frame's budget (WebRTC's floor for
    its libvpx encoder): a smaller keyframe is fewer packets to lose and leaves sooner; the
    frames after it sharpen the picture.
    """

    def __init__(self, limits: BitrateConfig, max_size: tuple[int, int] | None = None) -> None:
        vpx.Vp8Encoder.__init__(self)
        self._init_limits(limits)
        self.max_size = max_size  # the largest frame this track sends (open at it)
        self.live: Any = None  # a humantele.media.vpx.LiveVp8 once the first frame came
        self.reconfigurations = 0  # bit-rate changes applied to the running encoder
        self.resizes = 0  # size changes applied to the running encoder (a keyframe each)
        self.keyframes_suppressed = 0  # requests within keyframe_interval_s of a keyframe
        self.keyframes_deferred = 0  # keyframes made after the interval for such a request
        self._key_pending = False  # a request not yet answered (it came within the interval)
        self.keyframes = 0  # keyframes sent (any cause)
        self.rtt_s: float | None = None  # the link's round trip (s), set by the sender
        self.q_ref = Q_START  # the quantizer of the last frame that spent its budget (0-63)
        self.q_floor = 0  # the quantizer floor in force (0-63; libvpx only)
        self.oversized = 0  # frames over OVERSIZED times their budget (libvpx only)
        self._last_key_pts: int | None = None  # 90 kHz
        self._last_pts: int | None = None

    def keyframe_interval_s(self) -> float:
        """The least time between two keyframes the receiver asks for (s)."""
        rtt = self.rtt_s if self.rtt_s is not None and self.rtt_s > 0 else 0.1
        return min(MAX_KEYFRAME_GAP_S, max(MIN_KEYFRAME_GAP_S, rtt + 0.05))

    def _want_key(self, force_keyframe: bool, pts: int) -> bool:
        """Whether this frame (``pts``, 90 kHz) is to be a keyframe: one was asked for now or
        earlier, and the last keyframe is at least :meth:`keyframe_interval_s` old."""
        if force_keyframe:
            self.keyframes_forced += 1
        elif not self._key_pending:
            return False
        if self._last_key_pts is not None:
            since = (pts - self._last_key_pts) / VIDEO_CLOCK_HZ
            if 0 <= since < self.keyframe_interval_s():
                self.keyframes_suppressed += force_keyframe
                self._key_pending = True
                return False
        if not force_keyframe:
            self.keyframes_deferred += 1
        self._key_pending = False
        return True

    def figures(self) -> dict[str, Any]:
        return {
            **super().figures(),
            "reconfigurations": self.reconfigurations,
            "resizes": self.resizes,
            "keyframes": self.keyframes,
            "keyframes_suppressed": self.keyframes_suppressed,
            "keyframes_deferred": self.keyframes_deferred,
            "oversized": self.oversized,
            "q_floor": self.q_floor,
            "libvpx": self.live is not None,
        }

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

    def _open_live(self, lib: Any, width: int, height: int) -> Any:
        from humantele.media.vpx import LiveVp8

        w, h = width, height
        if self.max_size is not None and width <= self.max_size[0] and height <= self.max_size[1]:
            w, h = self.max_size  # open at the largest size: smaller ones are then live changes
        threads = vpx.number_of_threads(w * h, multiprocessing.cpu_count())
        live = LiveVp8(lib, w, h, round(self._target / 1000), threads, LIBVPX_OPTIONS)
        if (w, h) != (width, height):
            live.set_size(width, height)
        self.restarts += 1
        return live

    def _encode_live(self, lib: Any, frame: Any, force_keyframe: bool) -> tuple[bytes, bool]:
        w, h = frame.width, frame.height
        if self.live is None or not self.live.fits(w, h):
            if self.live is not None:
                self.live.close()
            self.live = self._open_live(lib, w, h)
        elif (w, h) != (self.live.width, self.live.height):
            self.live.set_size(w, h)
            self.resizes += 1
        kbps = round(self._target / 1000)
        if kbps != self.live.kbps:
            self.live.set_bitrate(kbps)
            self.reconfigurations += 1
        pts = convert_timebase(frame.pts, frame.time_base, VIDEO_TIME_BASE)
        duration = 3000 if self._last_pts is None else pts - self._last_pts
        if not 0 < duration < 90_000:
            duration = 3000
        self._last_pts = pts
        key = self._want_key(force_keyframe, pts)
        self.q_floor = max(int(LIBVPX_OPTIONS["qmin"]), self.q_ref - Q_FALL)
        self.live.set_min_quantizer(self.q_floor)
        data, is_key = self.live.encode(i420_array(frame), pts, duration, key)
        budget = self._target / 8 * duration / VIDEO_CLOCK_HZ  # bytes
        if len(data) >= SPENT_SHARE * budget:
            self.q_ref = self.live.last_quantizer()
        self.oversized += len(data) > OVERSIZED * budget
        return data, is_key

    def _encode_ffmpeg(self, frame: Any, force_keyframe: bool) -> tuple[bytes, bool]:
        if self.codec is not None and self._stale(self.codec, frame.width, frame.height):
            self.codec = None
        if self.codec is None:
            self.codec = self._open(frame.width, frame.height)
        pts = convert_timebase(frame.pts, frame.time_base, VIDEO_TIME_BASE)
        if self._want_key(force_keyframe, pts):
            frame.pict_type = av.video.frame.PictureType.I
        packets = self.codec.encode(frame)
        return b"".join(bytes(p) for p in packets), any(p.is_keyframe for p in packets)

    def encode(self, frame: Any, force_keyframe: bool = False) -> tuple[list[bytes], int]:
        if frame.format.name != "yuv420p":
            frame = frame.reformat(format="yuv420p")
        from humantele.media.vpx import load

        lib = load() if USE_LIBVPX else None
        if lib is not None:
            data, is_key = self._encode_live(lib, frame, force_keyframe)
        else:
            data, is_key = self._encode_ffmpeg(frame, force_keyframe)
        timestamp = convert_timebase(frame.pts, frame.time_base, VIDEO_TIME_BASE)
        if is_key:
            self.keyframes += 1
            self._last_key_pts = timestamp
            self._key_pending = False  # a keyframe for any cause answers a request
        payloads = self._packetize(data, self.picture_id)
        if len(payloads) == 1 and len(data) >= 2:
            payloads = two_packets(data, self.picture_id)
        self.picture_id = (self.picture_id + 1) % (1 << 15)
        return payloads, timestamp


def i420_array(frame: Any) -> np.ndarray:
    """A yuv420p frame's planes as one contiguous (H*3/2, W) uint8 array (I420)."""
    if frame.width % 2 or frame.height % 2:
        raise ValueError(f"odd frame size {frame.width}x{frame.height}")
    return np.ascontiguousarray(frame.to_ndarray(format="yuv420p"))


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


def make_encoder(
    mime_type: str, limits: BitrateConfig, max_size: tuple[int, int] | None = None
) -> Encoder:
    """Our encoder for a negotiated codec (``video/VP8`` or ``video/H264``, any case);
    ``max_size`` (width, height): the largest frame the track sends (VP8 opens at it, so a
    smaller frame is a live change)."""
    mime = mime_type.lower()
    if mime == "video/vp8":
        return Vp8Encoder(limits, max_size)
    encoder = ENCODERS.get(mime)
    if encoder is None:
        raise ValueError(f"no encoder for {mime_type}")
    return encoder(limits)

"""hl2ss's AHAT encodings: RAW, and depth SAME + AB H.264/H.265 (PyAV), both ways.

Checked against github.com/jdibenes/hl2ss at commit 9a70fad2: the app's
``hl2ss/hl2ss/encoder_rm_zht.cpp`` (``ZABToNV12``, ``InvalidateZ``) and the client's
``viewer/hl2ss.py`` (``_decode_rm_depth_ahat_z_ab_h26x``, ``_codec_h264``, ``_codec_hevc``).

Depth SAME + AB H.26x packs one NV12 frame (512 x 512) per AHAT frame and encodes it:

- Y = ``uint8(invalidate(depth) >> 2)``: depth in 4 mm steps, narrowed to 8 bits (NEON
  ``vshrn``: the high bits are dropped, so 1024-1054 mm wrap to 0-7 steps);
- UV = ``uint8(uint16(sqrt(float16(AB))))`` of every other AB pixel of each row (``vld2q``
  keeps the even ones), written in order into the interleaved chroma plane: U holds AB
  columns 0, 4, 8, ... and V columns 2, 6, 10, ...

The client decodes with ``depth = Y * 4`` and ``AB = U**2, V**2`` each repeated over 2
columns (AB at a quarter of the horizontal resolution, square-rooted to 8 bits, then lossy).
hl2ss's H.264 decoder drops the packet's first 6 bytes (the access unit delimiter the
Windows encoder starts each frame with) and appends one, so the parser returns the frame at
once; H.265 packets are parsed whole, an AUD appended. This module decodes the same way.

Depth ZDEPTH (lossless depth) needs hl2ss's ``pyzdepth`` extension, which is not on PyPI
(built from ``extensions/pyzdepth`` with a C++ compiler and zstd) and is not simple to write
(Zdepth's own format, ~1000 lines of C++): the configuration refuses it.

The replay server encodes with libx264 / libx265 through PyAV, with what the headset's
Media Foundation encoder is given (the profile, the bitrate, ``MF_LOW_LATENCY``: one packet
out per frame in, no B frames; the GOP size option, hl2ss_lnm's default 45 frames), and an
access unit delimiter before each H.264 frame, as the Windows encoder writes.
"""

from __future__ import annotations

import struct
from fractions import Fraction

import numpy as np
from numpy.typing import ArrayLike, NDArray

from humantele.tracking.camera import CameraIntrinsics
from humantele.tracking.hl2ss_protocol import (
    AHAT_DEPTH_MASK,
    AHAT_FPS,
    AHAT_HEIGHT,
    AHAT_PIXELS,
    AHAT_WIDTH,
    DEPTH_PROFILE_SAME,
    GOP_SIZE_OPTION,
    HEADER,
    SIZES,
    TICKS,
    VIDEO_PROFILE_RAW,
    AhatConfiguration,
    AhatPayload,
    PacketError,
    decode_ahat_payload,
    encode_ahat_packet,
)

H264_BASE, H264_MAIN, H264_HIGH, H265_MAIN = 0, 1, 2, 3
PROFILE_NAMES = {
    "raw": VIDEO_PROFILE_RAW,
    "h264_base": H264_BASE,
    "h264_main": H264_MAIN,
    "h264_high": H264_HIGH,
    "h265_main": H265_MAIN,
}
_X264_PROFILE = {H264_BASE: "baseline", H264_MAIN: "main", H264_HIGH: "high"}
TRUNCATE = 4  # hl2ss: depth is stored >> 2 in Y
H264_AUD = b"\x00\x00\x00\x01\x09\x10"  # _codec_h264._aud
HEVC_AUD = b"\x00\x00\x00\x01\x46\x01\x03"  # _codec_hevc._aud


def default_bitrate(profile_ab: int, divisor: int = 1) -> int:
    """hl2ss_lnm's default bitrate (bit/s) for depth SAME: width * height * fps * 12 *
    factor * 16, factor 1/75 for H.264, 1/150 for H.265, 1 for RAW (the divisor is not used,
    as in hl2ss_lnm)."""
    del divisor
    factor = 1.0 if profile_ab == VIDEO_PROFILE_RAW else 1 / 75 if profile_ab < 3 else 1 / 150
    return int(AHAT_WIDTH * AHAT_HEIGHT * AHAT_FPS * 12 * factor) * 16


def default_gop_size(profile_ab: int) -> int:
    """hl2ss_lnm's default GOP size: the frame rate for H.26x, 1 for RAW."""
    return 1 if profile_ab == VIDEO_PROFILE_RAW else AHAT_FPS


def zab_to_yuv420p(depth_mm: ArrayLike, ab: ArrayLike) -> NDArray[np.uint8]:
    """The app's ``ZABToNV12`` as a planar (768, 512) yuv420p image (NV12's chroma plane
    de-interleaved into U then V, the layout PyAV's ``to_ndarray`` gives hl2ss's decoder)."""
    d = np.asarray(depth_mm, np.uint16).reshape(AHAT_HEIGHT, AHAT_WIDTH)
    d = np.where(d < AHAT_DEPTH_MASK, d, 0)
    y = ((d >> 2) & 0xFF).astype(np.uint8)  # vshrn_n_u16(..., 2): narrowed, high bits dropped
    even = np.asarray(ab, np.uint16).reshape(AHAT_HEIGHT, AHAT_WIDTH)[:, 0::2]
    with np.errstate(over="ignore", invalid="ignore"):  # >= 65520 is inf in float16
        root = np.sqrt(even.astype(np.float16)).astype(np.float32)
    root = np.minimum(np.floor(root), 65535.0)  # vcvtq_u16_f16: toward zero, saturating
    chroma = (root.astype(np.uint16) & 0xFF).astype(np.uint8).reshape(-1)  # vmovn_u16
    u = chroma[0::2].reshape(-1, AHAT_WIDTH)
    v = chroma[1::2].reshape(-1, AHAT_WIDTH)
    return np.concatenate([y, u, v])


def yuv420p_to_zab(yuv: NDArray[np.uint8]) -> tuple[NDArray[np.uint16], NDArray[np.uint16]]:
    """hl2ss's ``_decode_rm_depth_ahat_z_ab_h26x.decode`` after the codec: depth = Y * 4,
    AB = U**2 and V**2 each over two columns."""
    h, cs = AHAT_HEIGHT, AHAT_HEIGHT // 4
    y = yuv[:h, :]
    u = yuv[h : h + cs, :].reshape((h, -1))
    v = yuv[h + cs : h + 2 * cs, :].reshape((h, -1))
    depth = np.multiply(y, TRUNCATE, dtype=np.uint16)
    ab = np.empty((h, AHAT_WIDTH), dtype=np.uint16)
    u = np.square(u, dtype=np.uint16)
    v = np.square(v, dtype=np.uint16)
    ab[:, 0::4] = u
    ab[:, 1::4] = u
    ab[:, 2::4] = v
    ab[:, 3::4] = v
    return depth, ab


def unbias_h26x(depth_mm: NDArray[np.uint16], intrinsics: CameraIntrinsics,
                undistorted: bool) -> tuple[NDArray[np.uint16], CameraIntrinsics]:  # fmt: skip
    """What hl2ss's decode leaves biased, for the tracker: depth was truncated to 4 mm steps
    (1.5 mm short on average: +2 mm here, valid pixels only), and each AB value of an even
    column is repeated over the next, which moves the image 0.5 px right (the intrinsics'
    ``cx`` + 0.5 here, unless the frame is ``undistorted``: then the AB map is shifted)."""
    depth = np.where(depth_mm > 0, depth_mm + np.uint16(2), 0).astype(np.uint16)
    if not undistorted:
        intrinsics = intrinsics.model_copy(update={"cx": intrinsics.cx + 0.5})
    return depth, intrinsics


def _codec_name(profile_ab: int) -> str:
    return "hevc" if profile_ab == H265_MAIN else "h264"


class AhatDecoder:
    """Decodes a connection's AHAT payloads as hl2ss's ``decode_rm_depth_ahat`` does
    (depth SAME; AB RAW or H.26x). One per connection: an H.26x stream refers to its earlier
    frames, so a frame the reader skips must still go through :meth:`skip`."""

    def __init__(self, profile_z: int = DEPTH_PROFILE_SAME, profile_ab: int = VIDEO_PROFILE_RAW):
        if profile_z != DEPTH_PROFILE_SAME:
            raise ValueError("depth ZDEPTH needs hl2ss's pyzdepth, which is not available")
        self.profile_ab = profile_ab
        self._codec = None
        if profile_ab != VIDEO_PROFILE_RAW:
            import av

            self._codec = av.CodecContext.create(_codec_name(profile_ab), "r")

    def _frames(self, blob: bytes):
        import av

        if self.profile_ab == H265_MAIN:
            data = blob + HEVC_AUD
        else:
            data = blob[6:] + H264_AUD
        try:
            for packet in self._codec.parse(data):
                yield from self._codec.decode(packet)
        except (av.error.FFmpegError, ValueError) as exc:
            raise PacketError("decode", f"the H.26x frame does not decode ({exc})") from exc

    def _blob(self, payload: bytes | bytearray | memoryview) -> tuple[bytes, int]:
        n = len(payload)
        if n < SIZES.size + TICKS.size:
            raise PacketError("size", f"payload of {n} bytes is shorter than its own header")
        size_z, size_ab = SIZES.unpack_from(payload, 0)
        if SIZES.size + size_z + size_ab + TICKS.size != n:
            raise PacketError("size", f"size_z {size_z} + size_ab {size_ab} disagree with {n}")
        if size_z != 0:
            raise PacketError("encoding", f"a Zdepth frame (size_z {size_z}) on a SAME stream")
        (ticks,) = TICKS.unpack_from(payload, n - TICKS.size)
        return bytes(payload[SIZES.size : SIZES.size + size_ab]), int(ticks)

    def decode(self, payload: bytes | bytearray | memoryview) -> AhatPayload:
        """The depth (mm) and AB images and sensor ticks of one payload; :class:`PacketError`
        ("size", "encoding": not this stream's encoding, "decode": the codec refused it or
        gave no picture) otherwise."""
        if self._codec is None:
            return decode_ahat_payload(payload)
        blob, ticks = self._blob(payload)
        if len(blob) == 4 * AHAT_PIXELS:
            raise PacketError("encoding", "a RAW frame on an H.26x stream")
        for frame in self._frames(blob):
            depth, ab = yuv420p_to_zab(frame.to_ndarray())
            return AhatPayload(depth, ab, ticks)
        raise PacketError("decode", "the H.26x packet gave no picture")

    def skip(self, payload: bytes | bytearray | memoryview) -> None:
        """Feed a payload the reader skips to the codec (later frames refer to it), without
        converting the picture; bad payloads are ignored here (the next decode says so)."""
        if self._codec is None:
            return
        try:
            blob, _ = self._blob(payload)
            for _frame in self._frames(blob):
                pass
        except PacketError:
            pass


class AhatEncoder:
    """Encodes AHAT frames into payloads for one connection's configuration, as the app does
    (:func:`encode_ahat_packet` for RAW; libx264/libx265 through PyAV for H.26x)."""

    def __init__(self, config: AhatConfiguration):
        if config.profile_z != DEPTH_PROFILE_SAME:
            raise ValueError("no Zdepth encoder (hl2ss's pyzdepth is not available)")
        self.config = config
        self.profile_ab = config.profile_ab
        self._codec = None
        self._pts = 0
        if self.profile_ab == VIDEO_PROFILE_RAW:
            return
        import av

        fps = Fraction(AHAT_FPS, config.divisor)
        gop = config.options.get(GOP_SIZE_OPTION, default_gop_size(self.profile_ab))
        if self.profile_ab == H265_MAIN:
            c = av.CodecContext.create("libx265", "w")
            kbps = max(1, config.bitrate // 1000)  # capped as x264's maxrate/bufsize below
            params = (f"log-level=error:bframes=0:keyint={max(1, gop)}:aud=1:repeat-headers=1"
                      f":vbv-maxrate={kbps}:vbv-bufsize={max(1, kbps // 2)}")  # fmt: skip
            c.options = {"preset": "ultrafast", "tune": "zerolatency", "x265-params": params}
        else:
            c = av.CodecContext.create("libx264", "w")
            c.options = {"preset": "ultrafast", "tune": "zerolatency", "aud": "1",
                         "profile": _X264_PROFILE[self.profile_ab], "bf": "0",
                         "maxrate": str(config.bitrate),
                         "bufsize": str(config.bitrate // 2)}  # fmt: skip
            c.gop_size = max(1, gop)
        c.width, c.height, c.pix_fmt = AHAT_WIDTH, AHAT_HEIGHT, "yuv420p"
        c.time_base, c.framerate = 1 / fps, fps
        c.bit_rate = config.bitrate
        c.open()
        self._codec = c

    def payload(self, depth_mm: ArrayLike, ab: ArrayLike, sensor_ticks: int = 0) -> bytes:
        """One frame's payload: size_z, size_ab, the AB blob (RAW images or the H.26x
        frame), sensor ticks."""
        if self._codec is None:
            packet = encode_ahat_packet(0, depth_mm, ab, sensor_ticks)
            return packet[HEADER.size :]
        import av

        frame = av.VideoFrame.from_ndarray(zab_to_yuv420p(depth_mm, ab), format="yuv420p")
        frame.pts = self._pts
        self._pts += 1
        blob = b"".join(bytes(p) for p in self._codec.encode(frame))
        return SIZES.pack(0, len(blob)) + blob + TICKS.pack(sensor_ticks)

    def packet(self, timestamp: int, depth_mm: ArrayLike, ab: ArrayLike, sensor_ticks: int = 0,
               pose: ArrayLike | None = None) -> bytes:  # fmt: skip
        """A whole packet: header, :meth:`payload`, then the rig pose in mode 1."""
        payload = self.payload(depth_mm, ab, sensor_ticks)
        tail = b"" if pose is None else np.asarray(pose, dtype="<f4").reshape(4, 4).tobytes()
        return HEADER.pack(timestamp, len(payload)) + payload + tail


def payload_bytes(payload: bytes) -> int:
    """The AB blob's size of a payload (for bitrate figures)."""
    return struct.unpack_from("<II", payload, 0)[1]

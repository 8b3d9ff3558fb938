"""JPEG of a console frame: from a decoded frame's I420 planes (no BGR image is made), or
from a BGR image (the sim sources', which render BGR).

An :class:`I420Jpeg` keeps one libavcodec MJPEG encoder (one per track: not thread-safe, so
one caller at a time). A received frame is limited-range YUV (``yuv420p``); JPEG is
full-range, so the planes are rescaled by swscale into ``yuvj420p`` first (a planar copy,
~0.3 ms at 640 x 480).
"""

from __future__ import annotations

from fractions import Fraction
from typing import Any

import av
import cv2
import numpy as np


def qscale(quality: int) -> int:
    """libavcodec's MJPEG quantiser scale (2 best .. 31) for a JPEG quality (30-100)."""
    return int(max(2, min(31, round((100 - quality) / 4))))


class I420Jpeg:
    """JPEG-encode decoded frames (``av.VideoFrame``, planar YUV 4:2:0) at ``quality``."""

    def __init__(self, quality: int = 88) -> None:
        self.quality = quality
        self._ctx: Any = None
        self._size: tuple[int, int] | None = None
        self.encoded = 0

    def _context(self, width: int, height: int) -> Any:
        if self._ctx is None or self._size != (width, height):
            ctx = av.CodecContext.create("mjpeg", "w")
            ctx.width, ctx.height = width, height
            ctx.pix_fmt = "yuvj420p"
            ctx.time_base = Fraction(1, 90000)
            ctx.qscale = qscale(self.quality)
            ctx.flags |= 2  # AV_CODEC_FLAG_QSCALE: a fixed quantiser, not a bit rate
            self._ctx, self._size = ctx, (width, height)
        return self._ctx

    def encode(self, frame: av.VideoFrame) -> bytes:
        """The JPEG bytes of ``frame``; ValueError if it cannot be encoded."""
        if frame.format.name not in ("yuv420p", "yuvj420p"):
            raise ValueError(f"not a planar YUV 4:2:0 frame: {frame.format.name}")
        full = frame if frame.format.name == "yuvj420p" else frame.reformat(format="yuvj420p")
        full.pts = self.encoded
        ctx = self._context(frame.width, frame.height)
        try:
            packets = ctx.encode(full)
        except av.error.FFmpegError as exc:
            self._ctx = None
            raise ValueError(f"JPEG encoding failed: {exc}") from exc
        if not packets:
            raise ValueError("JPEG encoding gave nothing")
        self.encoded += 1
        return bytes(packets[0])


def bgr_jpeg(image: np.ndarray, quality: int) -> bytes:
    """The JPEG bytes of a (H, W, 3) uint8 BGR image; ValueError if it is not one."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"not a BGR uint8 image: {image.shape} {image.dtype}")
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def frame_jpeg(frame: Any, quality: int, encoder: I420Jpeg | None = None) -> bytes:
    """The JPEG of a console frame: from its decoded planes (``frame.av_frame``) when it has
    them, else from its BGR ``image``."""
    av_frame = getattr(frame, "av_frame", None)
    if av_frame is not None:
        return (encoder or I420Jpeg(quality)).encode(av_frame)
    return bgr_jpeg(frame.image, quality)

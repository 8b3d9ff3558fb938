"""Encode frames with a video codec and decode them again, in process (PyAV, aiortc's
dependency): what a frame looks like after the link, without the link. For the frame
counter's robustness and the quality (PSNR, SSIM) against bit rate.

``vp8``: libvpx as aiortc sets it up for real time (deadline realtime, cpu-used 8, no
look-ahead); ``h264``: libx264 ultrafast, zerolatency. One decoded frame per input frame, in
order.
"""

from __future__ import annotations

import fractions
import time
from collections.abc import Sequence
from typing import Literal

import av
import numpy as np
from numpy.typing import NDArray

ENCODERS = {
    "vp8": ("libvpx", {"deadline": "realtime", "cpu-used": "8", "lag-in-frames": "0"}),
    "h264": ("libx264", {"preset": "ultrafast", "tune": "zerolatency"}),
}
DECODERS = {"vp8": "vp8", "h264": "h264"}


def codec_round_trip(
    images: Sequence[NDArray[np.uint8]],
    codec: Literal["vp8", "h264"] = "vp8",
    bit_rate: int = 500_000,
    fps: int = 20,
) -> tuple[list[NDArray[np.uint8]], float]:
    """(decoded BGR images, encoder seconds per frame) for BGR ``images`` of one size."""
    h, w = images[0].shape[:2]
    name, options = ENCODERS[codec]
    enc = av.CodecContext.create(name, "w")
    enc.width, enc.height, enc.pix_fmt = w, h, "yuv420p"
    enc.bit_rate = int(bit_rate)
    enc.framerate = fractions.Fraction(fps, 1)
    enc.time_base = fractions.Fraction(1, fps)
    enc.options = dict(options)
    dec = av.CodecContext.create(DECODERS[codec], "r")
    out: list[NDArray[np.uint8]] = []
    spent = 0.0
    for i, img in enumerate(images):
        frame = av.VideoFrame.from_ndarray(img, format="bgr24")
        frame.pts = i
        t0 = time.perf_counter()
        packets = enc.encode(frame)
        spent += time.perf_counter() - t0
        for packet in packets:
            out.extend(d.to_ndarray(format="bgr24") for d in dec.decode(packet))
    for packet in enc.encode(None):
        out.extend(d.to_ndarray(format="bgr24") for d in dec.decode(packet))
    return out, spent / max(len(images), 1)

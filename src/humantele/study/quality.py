"""The US picture's quality at the expert: SSIM of each decoded frame against the frame the
follower captured, from a session's recordings.

The expert records every US frame as it arrived, encoded (``/expert/us_video``); the follower
records some of the frames it captured as JPEG (``/follower/us_image``, ``record_us_hz``, with
the frame's number ``seq``). The encoded frames are decoded in order (a frame after a gap the
jitter buffer gave up waits for its keyframe, as at the expert), each decoded frame's number
is read from its drawn counter (:func:`humantele.video.counter.read_counter`), and where the
follower recorded that frame the two are compared (:func:`humantele.video.fidelity.ssim`,
grey, below the counter's rows). The reference is the captured frame after its JPEG
(``jpeg_quality``, 80 by default), so the figure is slightly low at high bit rates; a
frozen picture adds no sample (its share is the freeze figure).
"""

from __future__ import annotations

import base64
from typing import Any

import av
import cv2
import numpy as np

from humantele.media.receiver import luma_plane
from humantele.video.counter import read_counter
from humantele.video.fidelity import ssim

US_VIDEO, US_IMAGE = "/expert/us_video", "/follower/us_image"
COUNTER_ROWS = 32  # the drawn counter's rows (top left), left out of the comparison


def _bytes(value: Any) -> bytes:
    return base64.b64decode(value) if isinstance(value, str) else bytes(value)


def us_ssim(expert: list[dict], follower: list[dict]) -> list[tuple[float, int, float]]:
    """(expert time s, frame number, SSIM) for each US frame decoded at the expert whose
    capture the follower recorded. ``expert``: ``/expert/us_video`` samples (``t``, ``data``,
    ``codec``, ``keyframe``), in arrival order; ``follower``: ``/follower/us_image`` samples
    (``data`` JPEG, ``seq``). Undecodable frames are skipped until the next keyframe."""
    refs: dict[int, bytes] = {}
    for s in follower:
        if isinstance(s.get("seq"), int) and s.get("data"):
            refs[s["seq"]] = _bytes(s["data"])
    if not refs or not expert:
        return []
    out = []
    decoder = None
    codec_name = None
    waiting_key = True
    for s in expert:
        codec = s.get("codec", "vp8")
        if codec != codec_name:
            decoder, codec_name, waiting_key = av.CodecContext.create(codec, "r"), codec, True
        if waiting_key and not s.get("keyframe"):
            continue
        try:
            frames = decoder.decode(av.Packet(_bytes(s["data"])))
        except (av.error.FFmpegError, ValueError):
            waiting_key = True
            continue
        waiting_key = False
        for f in frames:
            seq = read_counter(np.ascontiguousarray(luma_plane(f)[:32, :64]))
            ref = refs.get(seq) if seq is not None else None
            if ref is None:
                continue
            image = cv2.imdecode(np.frombuffer(ref, np.uint8), cv2.IMREAD_COLOR)
            decoded = f.to_ndarray(format="bgr24")
            if image is None or image.shape != decoded.shape:
                continue
            h, w = decoded.shape[:2]
            out.append((float(s["t"]), int(seq), ssim(image, decoded, (COUNTER_ROWS, h, 0, w))))
    return out

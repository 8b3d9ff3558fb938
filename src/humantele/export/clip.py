"""A clip of the console's cine (the last seconds of ultrasound, as JPEGs the page drew) as
an H.264 MP4, each frame at its capture time: the console's Capture keeps one beside the
still (:mod:`humantele.expert.console.server`, ``clip_seconds``; docs/console.md).
Run it off the event loop: about 6 ms a 640 x 480 frame.
"""

from __future__ import annotations

import fractions
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import av
import cv2
import numpy as np

TIME_BASE = fractions.Fraction(1, 1000)


@dataclass
class ClipInfo:
    path: Path
    frames: int
    duration_s: float
    bad_frames: int  # JPEGs that did not decode (skipped)


def write_clip(
    frames: Iterable[tuple[float, bytes]], path: Path, seconds: float | None = None, crf: int = 20
) -> ClipInfo:
    """Write ``frames`` (capture time s, JPEG bytes; oldest first) to a new MP4 at ``path``
    (never overwritten: FileExistsError), keeping the last ``seconds`` if given. ValueError
    when no frame decodes."""
    items = list(frames)
    if seconds is not None and items:
        newest = items[-1][0]
        items = [f for f in items if newest - f[0] <= seconds]
    pictures: list[tuple[float, np.ndarray]] = []
    bad = 0
    for t, jpeg in items:
        img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR) if jpeg else None
        if img is None:
            bad += 1
            continue
        pictures.append((t, img))
    if not pictures:
        raise ValueError(f"no decodable frame among {len(items)} for {path}")
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)  # never overwrite
    os.close(fd)
    h, w = pictures[0][1].shape[:2]
    w2, h2 = w - w % 2, h - h % 2  # yuv420p wants even sizes
    t0, last = pictures[0][0], -1
    with av.open(str(path), "w", format="mp4") as out:
        stream = out.add_stream("libx264", options={"preset": "veryfast", "crf": str(crf)})
        stream.width, stream.height, stream.pix_fmt = w2, h2, "yuv420p"
        stream.time_base = stream.codec_context.time_base = TIME_BASE
        stream.codec_context.max_b_frames = 0
        for t, img in pictures:
            if img.shape[:2] != (h, w):
                img = cv2.resize(img, (w, h))
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(img[:h2, :w2]), "bgr24")
            frame = frame.reformat(format="yuv420p")
            last = max(int(round((t - t0) / float(TIME_BASE))), last + 1)
            frame.pts, frame.time_base = last, TIME_BASE
            out.mux(stream.encode(frame))
        out.mux(stream.encode(None))
    return ClipInfo(path, len(pictures), last * float(TIME_BASE), bad)

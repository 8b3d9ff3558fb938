"""A clip of the console's cine (the last seconds of ultrasound, as JPEGs the page drew) as
an H.264 MP4, each frame at its capture time: the console's Capture keeps one beside the
still (:mod:`humantele.expert.console.server`, ``clip_seconds``; docs/console.md).
Run it off the event loop: about 6 ms a 640 x 480 frame.
"""

from __future__ import annotations

import errno
import fractions
import io
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import av
import cv2
import numpy as np

from humantele.runtime.files import write_new

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
    (never overwritten: FileExistsError), keeping the last ``seconds`` if given, whole or not
    at all (OSError: nothing left). ValueError when no frame decodes."""
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
    if path.exists():
        raise FileExistsError(errno.EEXIST, "clip exists, not overwritten", str(path))
    h, w = pictures[0][1].shape[:2]
    w2, h2 = w - w % 2, h - h % 2  # yuv420p wants even sizes
    t0, last = pictures[0][0], -1
    # Muxed in memory, then written whole (runtime.files.write_new): a full disk met by the
    # muxer left a file without its moov box, and PyAV's close, failing at the trailer, kept
    # the file's descriptor and its encoder (issue 34: the expert 139 -> 491 MB, 19 -> 40
    # descriptors after 22 such clips)
    buf = io.BytesIO()
    with av.open(buf, "w", format="mp4") as out:
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
    write_new(path, buf.getbuffer())
    return ClipInfo(path, len(pictures), last * float(TIME_BASE), bad)

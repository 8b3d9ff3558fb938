"""Recordings with encoded video for the export tests: a synthetic session (poses, scans) and
an expert file with VP8 frames of a known moving picture, as the receiver records them."""

from __future__ import annotations

import fractions
import functools
from pathlib import Path

import av
import numpy as np

from humantele.recording import McapLog
from humantele.recording.synthetic import T0_EXPERT, SyntheticSession, write_synthetic

FPS = 20
W, H = 160, 120


def picture(i: int) -> np.ndarray:
    """Frame ``i``: a gradient with a bright square moving right (BGR)."""
    y, x = np.mgrid[0:H, 0:W]
    img = np.stack([(x + 2 * i) % 256, (y * 2) % 256, (x + y) % 256], axis=-1).astype(np.uint8)
    c = 10 + (3 * i) % (W - 30)
    img[40:70, c : c + 20] = 255
    return img


def vp8_frames(n: int, gop: int = 10) -> list[tuple[bytes, bool]]:
    """``n`` VP8 frames of :func:`picture` (a keyframe every ``gop``), as libvpx makes them.
    Encoded once per (n, gop) in a process, the same frames for every file (encoding them
    again for each was 2.9 CPU-s of the clock-offset export test's six files)."""
    return list(_vp8_frames(n, gop))


@functools.lru_cache(maxsize=8)
def _vp8_frames(n: int, gop: int) -> tuple[tuple[bytes, bool], ...]:
    enc = av.CodecContext.create("libvpx", "w")
    enc.width, enc.height, enc.pix_fmt = W, H, "yuv420p"
    enc.time_base = fractions.Fraction(1, FPS)
    enc.gop_size = gop
    enc.options = {"deadline": "realtime", "cpu-used": "8"}
    enc.bit_rate = 800_000
    out = []
    for i in range(n):
        f = av.VideoFrame.from_ndarray(picture(i), format="bgr24").reformat(format="yuv420p")
        f.pts = i
        out += [(bytes(p), bool(p.is_keyframe)) for p in enc.encode(f)]
    out += [(bytes(p), bool(p.is_keyframe)) for p in enc.encode(None)]
    return tuple(out)


def write_video(
    path: Path, session_id: str, t0: float, n: int, streams=("us",), metadata=None
) -> list:
    """An expert file of ``session_id`` with ``n`` frames per stream from expert time ``t0``
    (capture times 30 ms before arrival; the first two frames without one, as before the
    receiver's anchor) and a force sample with each; ``metadata``: more session fields.
    Returns the frames."""
    frames = vp8_frames(n)
    md = {"role": "expert", "session_id": session_id, **(metadata or {})}
    log = McapLog(path, md, fsync=False)
    for i, (data, key) in enumerate(frames):
        t = t0 + i / FPS
        for name in streams:
            payload = {"data": data, "codec": "vp8", "keyframe": key,
                       "rtp_timestamp": (123456 + 4500 * i) % (1 << 32)}  # fmt: skip
            if i >= 2:
                payload["t_capture"] = t - 0.03
            log.append(f"/expert/{name}_video", t, payload, int(t * 1e9))
        log.append("/expert/force", t, {"force": [0.0, -1.0, 0.1 * i]}, int(t * 1e9))
        if i % 4 == 3:
            log.flush()  # a chunk every 0.2 s, as the recorder writes them
    log.close()
    return frames


def session_with_video(
    tmp: Path, n_scans: int = 2, duration_s: float = 9.0, metadata=None, **kw
) -> list[Path]:
    """A synthetic session's file and its video file (frames through the whole session;
    ``metadata``: more fields of the video file's session)."""
    cfg = SyntheticSession(duration_s=duration_s, n_scans=n_scans, expert_rate_hz=200.0,
                           session_id="vid01", **kw)  # fmt: skip
    a, b = tmp / "session.mcap", tmp / "video.expert.mcap"
    write_synthetic(a, cfg)
    write_video(b, "vid01", T0_EXPERT, int(duration_s * FPS), metadata=metadata)
    return [a, b]

"""What recording every received video frame costs the expert: replays the encoded frames of
a recording (``/expert/us_video``, ``/expert/pov_video``) at their recorded times through the
receiver's recording callback and a :class:`~humantele.recording.Recorder` (writer thread,
zstd chunks, fsync every 0.2 s, as the daemon records), and reports the CPU (% of one core,
this process, all threads) against the same replay without the frames, and MB per minute.

``python -m humantele.export.video_cost RECORDING.expert.mcap [--seconds S]``
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import tempfile
import time
from pathlib import Path

from humantele.media.jitter import KEYFRAME_TESTS
from humantele.recording import Recorder, read_recording
from humantele.recording.schemas import VIDEO_TOPICS


def _frames(path: Path, seconds: float) -> list[tuple[float, str, bytes, int]]:
    rec = read_recording(path, list(VIDEO_TOPICS.values()))
    out = []
    for topic in VIDEO_TOPICS.values():
        for s in rec.samples(topic):
            out.append((float(s["t"]), topic, base64.b64decode(s["data"]), s["rtp_timestamp"]))
    if not out:
        raise SystemExit(f"{path}: no encoded video recorded")
    out.sort(key=lambda f: f[0])
    t0 = out[0][0]
    return [(t - t0, topic, d, ts) for t, topic, d, ts in out if t - t0 <= seconds]


def replay(frames: list, with_video: bool, tmp: Path) -> dict[str, float]:
    """Replay at the recorded pace; CPU of this process (s) and file size (bytes)."""
    path = tmp / f"cost_{int(with_video)}_{time.monotonic_ns()}.mcap"
    is_key = KEYFRAME_TESTS["vp8"]
    rec = Recorder(path, "expert")
    span = frames[-1][0]
    c0, w0 = time.process_time(), time.monotonic()
    for t, topic, data, ts in frames:
        delay = w0 + t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        if with_video:  # what the receiver's callback does per frame (media/receiver.py)
            payload = {"data": data, "codec": "vp8", "keyframe": is_key(data),
                       "rtp_timestamp": ts, "t_capture": t}  # fmt: skip
            rec.write(topic, time.monotonic(), payload)
    rec.close()
    cpu, wall = time.process_time() - c0, time.monotonic() - w0
    size = path.stat().st_size
    path.unlink()
    return {"cpu_s": cpu, "wall_s": wall, "span_s": span, "bytes": size}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("recording", type=Path)
    p.add_argument("--seconds", type=float, default=30.0)
    args = p.parse_args(argv)
    frames = _frames(args.recording, args.seconds)
    with tempfile.TemporaryDirectory(dir=args.recording.parent) as d:
        base = replay(frames, False, Path(d))
        video = replay(frames, True, Path(d))
    span = video["span_s"]
    per_min = 60.0 / span
    result = {
        "frames": len(frames),
        "fps": round(len(frames) / span, 1),
        "video_mb_per_min": round((video["bytes"] - base["bytes"]) / 1e6 * per_min, 2),
        "encoded_mb_per_min": round(sum(len(f[2]) for f in frames) / 1e6 * per_min, 2),
        "cpu_percent_core": round(100 * (video["cpu_s"] - base["cpu_s"]) / video["wall_s"], 2),
        "cpu_ms_per_frame": round(1e3 * (video["cpu_s"] - base["cpu_s"]) / len(frames), 3),
        "loadavg": os.getloadavg()[0],
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Captures and clips on a full disk, as the console writes them: what is left, and what the
process keeps (issue 34 §4: 335 refused captures left orphan JPEGs, clips without a moov box
that their JSON named, and the expert grew 139 -> 491 MB, 19 -> 40 descriptors).

The disk is made full for this process by a file size limit (RLIMIT_FSIZE: a write past it
fails, as on a full disk; no root needed); each round saves a capture (still + JSON, through
the console's captures module) and a clip of ``--frames`` 640 x 480 frames (export.clip).

    python tools/full_disk_captures.py --rounds 20
    # or on a really small disk (as root: mount -t tmpfs -o size=3m tmpfs /mnt/small)
    python tools/full_disk_captures.py --rounds 20 --dir /mnt/small
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import tempfile
from pathlib import Path

import cv2
import numpy as np
import psutil

from humantele.expert.console.captures import save_capture
from humantele.export.clip import write_clip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=20)
    p.add_argument("--frames", type=int, default=60, help="frames of each clip")
    p.add_argument("--limit-kb", type=int, default=64, help="the largest file that fits (kB)")
    p.add_argument("--dir", type=Path, help="write there (a small file system) instead")
    a = p.parse_args()
    rng = np.random.default_rng(1)
    frames = [(k / 20, cv2.imencode(".jpg", rng.integers(0, 255, (480, 640, 3), np.uint8))[1]
               .tobytes()) for k in range(a.frames)]  # fmt: skip
    out = Path(tempfile.mkdtemp(prefix="full-disk-", dir=a.dir))
    if a.dir is None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        limit = a.limit_kb * 1024
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    proc = psutil.Process()
    rss0, fds0 = proc.memory_info().rss, proc.num_fds()
    failed = 0
    for i in range(a.rounds):
        for job, arg in ((save_capture, i), (write_clip, out / f"clip-{i}.mp4")):
            try:
                if job is save_capture:
                    save_capture(out, arg, frames[0][1], {"seq": arg})
                else:
                    write_clip(frames, arg)
            except OSError:
                failed += 1
    left = sorted(x.name for x in out.iterdir())
    print(json.dumps({
        "rounds": a.rounds, "failed_writes": failed, "files_left": len(left),
        "rss_growth_mb": round((proc.memory_info().rss - rss0) / 1e6, 1),
        "fd_growth": proc.num_fds() - fds0, "examples_left": left[:4],
    }))  # fmt: skip
    for x in out.iterdir():
        os.unlink(x)
    out.rmdir()


if __name__ == "__main__":
    main()

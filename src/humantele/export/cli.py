"""``humantele export RECORDING... [--scan N] [--start S] [--end S] [--out DIR] [--jobs N]``
(``--dicom``: DICOM objects instead, :mod:`humantele.export.dicom`):
per scan, an MP4 (H.264) of each video stream for raters and any player, and an MCAP for
Foxglove with the video (``foxglove.CompressedVideo``, H.264) beside the poses and force.

Transcoding runs on worker processes (``--jobs``, default: the cores this process may use),
one clip (a scan's stream) per task; a progress bar on stderr. Files that are not recordings
are named and left out; a truncated or damaged recording gives what is intact, and one line
says where it stops. See docs/export.md.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import queue
import sys
import time
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path
from typing import Any

from humantele.config import ConfigError
from humantele.export.mcapfile import ScanMcap, clock_metadata
from humantele.export.source import ExportSession, load
from humantele.export.video import (
    EncodedFrame,
    TranscodeJob,
    TranscodeResult,
    first_decodable,
    transcode,
)

STREAMS = ("us", "pov")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "recordings",
        nargs="+",
        type=Path,
        metavar="RECORDING",
        help="MCAP recordings (a session's expert and follower files)",
    )
    parser.add_argument(
        "--scan",
        type=int,
        action="append",
        metavar="N",
        help="only scan N (repeatable); default: every scan",
    )
    parser.add_argument(
        "--start",
        type=float,
        default=None,
        metavar="S",
        help="clip start, s from each scan's start (default 0)",
    )
    parser.add_argument(
        "--end",
        type=float,
        default=None,
        metavar="S",
        help="clip end, s from each scan's start (default: the scan's end)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("export"),
        metavar="DIR",
        help="output directory (default ./export)",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=None,
        metavar="N",
        help="worker processes for transcoding (default: the usable cores)",
    )
    parser.add_argument(
        "--crf", type=int, default=20, help="x264 quality, 0 (lossless) - 51; default 20"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    from humantele.export.dicom import add_arguments as dicom_arguments

    dicom_arguments(parser)  # --dicom and its options


def usable_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


class Progress:
    """A one-line bar on stderr: frames done of total, and speed in x real time."""

    def __init__(self, total: int, media_s: float, enabled: bool) -> None:
        self.total, self.media_s, self.enabled = max(total, 1), media_s, enabled
        self.done = 0
        self.t0 = time.monotonic()
        self._shown = 0.0

    def add(self, n: int) -> None:
        self.done = min(self.total, self.done + n)
        now = time.monotonic()
        if self.enabled and (now - self._shown > 0.2 or self.done == self.total):
            self._shown = now
            frac = self.done / self.total
            bar = "#" * int(30 * frac)
            speed = frac * self.media_s / max(now - self.t0, 1e-6)
            sys.stderr.write(
                f"\rexport [{bar:<30}] {100 * frac:3.0f}% {self.done}/{self.total} frames, "
                f"{speed:.1f}x real time"
            )
            sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()


_PROGRESS: Any = None  # the worker's progress queue (set by _init_worker)


def _init_worker(q: Any) -> None:
    global _PROGRESS
    _PROGRESS = q


def _worker(job: TranscodeJob) -> TranscodeResult:
    q = _PROGRESS
    return transcode(job, None if q is None else q.put)


def clip_window(start: float, stop: float, a: float | None, b: float | None) -> tuple[float, float]:
    """The clip within a scan ``[start, stop]`` for ``--start a --end b`` (s from its start)."""
    lo = start + (a or 0.0)
    hi = stop if b is None else min(stop, start + b)
    return lo, hi


def clip_frames(frames: list[EncodedFrame], lo: float, hi: float) -> list[EncodedFrame]:
    """The frames a clip [lo, hi] needs: from the keyframe its decoding starts at to ``hi``
    (a worker is sent these, not the session's)."""
    begin = first_decodable(frames, lo)
    if begin is None:
        return [f for f in frames if lo <= f.t <= hi]  # none decodable: counted as such
    return [f for f in frames[begin:] if f.t <= hi]


def plan(
    sessions: list[ExportSession], args: argparse.Namespace, out: Path
) -> tuple[list[tuple[ExportSession, Any, float, float]], list[TranscodeJob], list[str]]:
    """The scans to export (session, scan, clip start, clip stop), their transcoding jobs and
    lines about what is not there."""
    scans, jobs, notes = [], [], []
    for es in sessions:
        for iv in es.scans:
            if args.scan and iv.scan not in args.scan:
                continue
            lo, hi = clip_window(iv.start, iv.stop, args.start, args.end)
            if hi <= lo:
                notes.append(
                    f"session {es.session_id} scan {iv.scan}: empty clip "
                    f"({hi - lo:.1f} s after --start/--end); skipped"
                )
                continue
            scans.append((es, iv, lo, hi))
            for name in STREAMS:
                stream = es.video.get(name)
                if stream is None:
                    notes.append(
                        f"session {es.session_id}: no {name} video recorded (before issue 21, "
                        "or [expert.video] record_encoded = false): no MP4 of it"
                    )
                    continue
                jobs.append(
                    TranscodeJob(
                        f"{es.session_id}_scan{iv.scan}_{name}",
                        clip_frames(stream.frames, lo, hi),
                        lo,
                        hi,
                        stream.codec,
                        out / f"{es.session_id}_scan{iv.scan}_{name}.mp4",
                        crf=args.crf,
                    )
                )
        if args.scan:
            have = {iv.scan for iv in es.scans}
            for n in args.scan:
                if n not in have:
                    notes.append(f"session {es.session_id}: no scan {n} (scans: {sorted(have)})")
    return scans, jobs, list(dict.fromkeys(notes))


def run_jobs(jobs: list[TranscodeJob], n_workers: int, progress: Progress) -> list[TranscodeResult]:
    """Transcode on ``n_workers`` processes (in this process when 1 job or 1 worker)."""
    if not jobs:
        return []
    if n_workers <= 1 or len(jobs) == 1:
        return [transcode(j, progress.add) for j in jobs]
    ctx = mp.get_context("spawn")  # no fork of a process holding threads
    q = ctx.Queue()
    results: list[TranscodeResult] = []
    with ProcessPoolExecutor(
        min(n_workers, len(jobs)), mp_context=ctx, initializer=_init_worker, initargs=(q,)
    ) as pool:
        futures: list[Future] = [pool.submit(_worker, j) for j in jobs]
        while not all(f.done() for f in futures):
            try:
                progress.add(q.get(timeout=0.1))
            except queue.Empty:
                pass
        while True:
            try:
                progress.add(q.get_nowait())
            except queue.Empty:
                break
        results = [f.result() for f in futures]
    return results


def run(args: argparse.Namespace) -> int:
    if getattr(args, "dicom", False):  # humantele export --dicom (humantele.export.dicom)
        from humantele.export.dicom import run_dicom

        return run_dicom(args)
    if args.jobs is not None and args.jobs < 1:
        raise ConfigError(f"--jobs: must be >= 1, got {args.jobs}")
    if not 0 <= args.crf <= 51:
        raise ConfigError(f"--crf: must be 0-51, got {args.crf}")
    if args.start is not None and args.start < 0:
        raise ConfigError(f"--start: must be >= 0 s, got {args.start}")
    if args.end is not None and args.start is not None and args.end <= args.start:
        raise ConfigError(f"--end ({args.end}) must be after --start ({args.start})")
    sessions, problems = load(args.recordings)
    for line in problems:
        print(f"humantele export: {line}", file=sys.stderr)
    if not sessions:
        print("humantele export: nothing to export (no readable recording)", file=sys.stderr)
        return 2
    out: Path = args.out
    scans, jobs, notes = plan(sessions, args, out)
    for line in notes:
        print(f"humantele export: {line}", file=sys.stderr)
    if not scans:
        print("humantele export: no scan to export", file=sys.stderr)
        return 1
    media_s = sum(j.stop - j.start for j in jobs)
    total = sum(sum(1 for f in j.frames if j.start <= f.t <= j.stop) for j in jobs)
    progress = Progress(total, media_s, not args.quiet and sys.stderr.isatty())
    t0 = time.monotonic()
    try:
        results = run_jobs(jobs, args.jobs or usable_cores(), progress)
    finally:
        progress.close()
    wall = time.monotonic() - t0
    by_name = {r.name: r for r in results}
    written = 0
    for es, iv, lo, hi in scans:
        base = f"{es.session_id}_scan{iv.scan}"
        doc = ScanMcap(es.unix_offset_s or 0.0)
        for name in STREAMS:
            r = by_name.get(f"{base}_{name}")
            if r is None:
                continue
            if r.error:
                print(
                    f"humantele export: {base} {name}: transcoding failed ({r.error})",
                    file=sys.stderr,
                )
            lost = r.frames_in - r.frames_out
            if lost:
                print(
                    f"humantele export: {base} {name}: {lost} of {r.frames_in} frames not "
                    f"exported ({r.decode_errors} undecodable, the rest before the first "
                    "keyframe)",
                    file=sys.stderr,
                )
            if r.frames_out:
                doc.video(name, r.h264)
                written += 1
                print(
                    f"{out / (base + '_' + name + '.mp4')}: {r.frames_out} frames, "
                    f"{r.duration_s:.1f} s, {r.size[0] if r.size else 0}x"
                    f"{r.size[1] if r.size else 0}"
                )
        s = es.session
        doc.poses("virtual", s.virtual, lo, hi)
        doc.poses("real", s.real, lo, hi)
        for topic, (t, f) in es.force.items():
            doc.force(topic, t, f, lo, hi)
        path = out / f"{base}.mcap"
        n = doc.write(
            path,
            {
                "session_id": es.session_id,
                "scan": str(iv.scan),
                "clip_start_s": f"{lo:.6f}",
                "clip_stop_s": f"{hi:.6f}",
                **clock_metadata(es.unix_offset_s),
            },
        )
        print(f"{path}: {n} messages (video, poses, force) for Foxglove")
    if media_s > 0 and results:
        print(
            f"transcoded {media_s:.1f} s of video in {wall:.1f} s "
            f"({media_s / max(wall, 1e-6):.1f}x real time, {args.jobs or usable_cores()} "
            "worker(s))"
        )
    return 0 if written or not jobs else 1

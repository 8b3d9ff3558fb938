"""What ``humantele export`` reads: each session's scans (as ``humantele analyze`` finds them),
its recorded video frames per stream, poses and force, all on the expert's clock.

A file that is not a recording is named in one line and left out; a truncated or damaged one
gives what it holds intact (:func:`humantele.recording.reader.read_recording`) and one line
saying where it stops.
"""

from __future__ import annotations

import base64
import binascii
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from humantele.analysis.sessions import TOPICS as ALIGNMENT_TOPICS
from humantele.analysis.sessions import ScanInterval, Session, build_session
from humantele.export.video import EncodedFrame
from humantele.recording.reader import Recording, RecordingReadError, read_recording
from humantele.recording.schemas import VIDEO_TOPICS

FORCE_TOPICS = ("/expert/force", "/follower/force")
READ_TOPICS = (*ALIGNMENT_TOPICS, *VIDEO_TOPICS.values(), *FORCE_TOPICS)
RTP_RATE = 90000.0


@dataclass
class VideoStream:
    """One stream's recorded frames in arrival order; ``codec`` 'vp8' or 'h264';
    ``estimated`` frames whose capture time came from their RTP timestamp (or, failing
    that, their receive time) because none was recorded."""

    name: str
    codec: str
    frames: list[EncodedFrame]
    estimated: int = 0
    bad: int = 0  # recorded frames that could not be read (counted, left out)


@dataclass
class ExportSession:
    """A session to export: the analysis' view of it (scans, poses, clock) plus video and
    force (``(t expert clock, force xyz N)``)."""

    session: Session
    video: dict[str, VideoStream]
    force: dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]
    problems: list[str] = field(default_factory=list)
    unix_offset_s: float | None = None  # expert clock + this = Unix time (s); None: unknown

    @property
    def session_id(self) -> str:
        return self.session.session_id

    @property
    def scans(self) -> list[ScanInterval]:
        return self.session.scans


def _unwrap(ts: list[int]) -> NDArray[np.float64]:
    """32-bit RTP timestamps unwrapped (the first one's cycle is 0)."""
    a = np.asarray(ts, dtype=np.int64)
    steps = np.diff(a, prepend=a[:1])
    wraps = np.cumsum((steps < -(1 << 31)).astype(np.int64) - (steps > (1 << 31)))
    return (a + wraps * (1 << 32)).astype(float)


def video_stream(name: str, samples: list[dict]) -> VideoStream | None:
    """The frames of one stream from its recorded samples (see :class:`VideoStream`)."""
    frames: list[EncodedFrame] = []
    rtp: list[int] = []
    capture: list[float] = []
    received: list[float] = []
    codec = ""
    bad = 0
    for s in samples:
        try:
            data = base64.b64decode(s["data"], validate=True)
            ts = int(s["rtp_timestamp"])
            key = bool(s["keyframe"])
            codec = codec or str(s["codec"])
        except (KeyError, TypeError, ValueError, binascii.Error):
            bad += 1
            continue
        frames.append(EncodedFrame(float(s["t"]), data, key))
        rtp.append(ts)
        capture.append(float(s.get("t_capture", np.nan)))
        received.append(float(s["t"]))
    if not frames:
        return None
    t_rtp = _unwrap(rtp) / RTP_RATE
    cap = np.asarray(capture)
    known = np.isfinite(cap)
    estimated = int((~known).sum())
    if known.any():  # capture = RTP time + a constant (the sender's clock), expert clock
        offset = float(np.median(cap[known] - t_rtp[known]))
        times = np.where(known, cap, t_rtp + offset)
    else:
        times = np.asarray(received)
    for f, t in zip(frames, times, strict=True):
        f.t = float(t)
    return VideoStream(name, codec, frames, estimated, bad)


def _where_it_stops(rec: Recording) -> str:
    last = [float(rec.times(topic)[-1]) for topic in rec.messages if rec.count(topic)]
    return f" (last sample at t = {max(last):.1f} s)" if last else " (nothing intact)"


def load(paths: Iterable[str | Path]) -> tuple[list[ExportSession], list[str]]:
    """The sessions in ``paths`` (grouped by session id) and one line per file with a problem
    (not a recording: left out; truncated/damaged: what is intact is used)."""
    groups: dict[str, list[Recording]] = {}
    problems: list[str] = []
    for p in paths:
        try:
            rec = read_recording(p, READ_TOPICS)
        except RecordingReadError as exc:
            problems.append(f"{exc}; left out")
            continue
        if rec.problem and rec.problem.startswith("reading stopped early"):
            problems.append(
                f"{rec.path}: damaged, {rec.problem}; exporting what is intact before it"
                + _where_it_stops(rec)
            )
        elif rec.problem:
            problems.append(
                f"{rec.path}: {rec.problem}; exporting what was recorded" + _where_it_stops(rec)
            )
        if rec.bad_messages:
            problems.append(f"{rec.path}: {rec.bad_messages} undecodable message(s) skipped")
        sid = rec.session.get("session_id") or Path(p).stem
        groups.setdefault(sid, []).append(rec)
    out = []
    for sid, recs in groups.items():
        session = build_session(sid, recs)
        video: dict[str, VideoStream] = {}
        for name, topic in VIDEO_TOPICS.items():
            samples = [s for r in recs for s in r.samples(topic)]
            for r in recs:  # the base64 text is freed as the frames are decoded (memory: an
                r.messages.pop(topic, None)  # hour of both streams is ~1.3 GB of frames)
            stream = video_stream(name, samples)
            del samples
            if stream is not None:
                video[name] = stream
                if stream.bad:
                    problems.append(f"session {sid}: {stream.bad} unreadable {name} frame(s)")
        force = {}
        for topic in FORCE_TOPICS:
            parts = [r for r in recs if r.count(topic)]
            if not parts:
                continue
            t = np.concatenate([r.times(topic) for r in parts])
            f = np.concatenate([r.column(topic, "force").reshape(-1, 3) for r in parts])
            if topic.startswith("/follower/"):
                t = session.clock.to_expert(t)
            order = np.argsort(t, kind="stable")
            force[topic] = (t[order], f[order].astype(float))
        offset = _unix_offset([r for r in recs if r.session.get("role") == "expert"])
        out.append(ExportSession(session, video, force, unix_offset_s=offset))
    return out, problems


def _unix_offset(expert: list[Any]) -> float | None:
    """The expert recording's ``clock_unix_offset_s`` (its clock to Unix time, s), or None
    (an older recording, or a value that is not a finite number)."""
    for rec in expert:
        try:
            value = float(rec.session.get("clock_unix_offset_s", "nan"))
        except ValueError:
            continue
        if math.isfinite(value):
            return value
    return None

"""From recording files to per-scan alignment results.

Files with the same ``session_id`` (an expert file and a follower file, or one demo file) form
one session. Scans come from the expert's ``/expert/scan`` start/stop events (expert clock); a
scan without a stop ends at the last expert sample (a crash) and is marked incomplete. A
session without scan events is analysed whole, as scan 0, with a warning; when a file of the
expert's side is cut (not closed, or unreadable past some point) that scan 0 is incomplete
too: its start and end are unknown (the lost part may hold the scan events). Incomplete scans
are reported but left out of the tables and summaries (:mod:`humantele.analysis.report`).

A scan inside which the follower's tracker gave no measurement for :data:`SENSING_GAP_S` or
more (a killed sensing process: 10 s and more) has its sensing gaps listed (when into the
scan, how long): its figures stand on the rest of it, and the report and the study's tables
say so beside them.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from humantele.analysis.alignment import (
    AlignmentErrors,
    AlignmentRmse,
    ClockMap,
    PoseTrack,
    alignment_errors,
    alignment_rmse,
    fit_clock_map,
)
from humantele.recording.reader import Recording, read_recording

SENSING_GAP_S = 1.0  # no tracker frame for this long inside a scan: a sensing gap (45 Hz: 22 ms)

# What the alignment reads; other topics (force at 1 kHz...) are not even decoded.
TOPICS = (
    "/follower/video_frame",
    "/expert/pose",
    "/follower/probe_pose",
    "/expert/scan",
    "/expert/clock_sync",
    "/follower/clock_sync",
)


@dataclass
class ScanInterval:
    scan: int
    start: float
    stop: float
    follower_id: str = ""
    sonographer_id: str = ""
    complete: bool = True
    why_incomplete: str = ""  # when not complete: why (said in the report)


@dataclass
class Session:
    """One session's streams, with the follower's probe times already on the expert clock."""

    session_id: str
    files: list[Path]
    virtual: PoseTrack
    real: PoseTrack  # tracked frames only, expert clock
    frame_times: NDArray[np.float64]  # every tracker frame (tracked or not), expert clock
    clock: ClockMap
    scans: list[ScanInterval]
    warnings: list[str] = field(default_factory=list)
    # The sim ultrasound's known-answer image quality of each captured frame (0-1), expert
    # clock; empty unless the follower recorded a sim US source.
    us_quality_t: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    us_quality: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))


@dataclass
class ScanResult:
    """The alignment of one scan; ``errors`` holds the per-frame errors (for plots)."""

    session_id: str
    interval: ScanInterval
    rmse: AlignmentRmse
    errors: AlignmentErrors
    frames_total: int
    frames_tracked: int
    sim_quality: float | None = None  # mean sim US image quality over the scan (0-1)
    sim_quality_frames: int = 0
    # (s into the scan, s long) of each stretch without a tracker frame (sensing_gaps)
    sensing_gaps: list[tuple[float, float]] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        """The JSON object of this scan (mm and degrees, the paper's units)."""
        r, iv = self.rmse, self.interval
        return {
            "scan": iv.scan,
            "session": self.session_id,
            "follower_id": iv.follower_id,
            "sonographer_id": iv.sonographer_id,
            "complete": iv.complete,
            "incomplete_reason": None if iv.complete else iv.why_incomplete,
            "duration_s": round(iv.stop - iv.start, 3),
            "frames": self.frames_total,
            "frames_tracked": self.frames_tracked,
            "samples_used": r.n,
            "position_rmse_mm": _num(r.position_rmse_m * 1e3),
            "centered_position_rmse_mm": _num(r.centered_position_rmse_m * 1e3),
            "orientation_rmse_deg": _num(np.degrees(r.orientation_rmse_rad)),
            "centered_orientation_rmse_deg": _num(np.degrees(r.centered_orientation_rmse_rad)),
            "mean_position_error_mm": [_num(v * 1e3) for v in r.mean_position_error_m],
            "mean_rotation_error_deg": _num(np.degrees(r.mean_rotation_error_rad)),
            "sim_image_quality": None if self.sim_quality is None else _num(self.sim_quality),
            "sim_image_quality_frames": self.sim_quality_frames,
            "sensing_gaps": [
                {"at_s": round(a, 2), "duration_s": round(d, 2)} for a, d in self.sensing_gaps
            ],
            "sensing_gap_s": round(sum(d for _, d in self.sensing_gaps), 2),
        }


def _num(v: float) -> float | None:
    return None if not np.isfinite(v) else round(float(v), 4)


def _gather(recordings: list[Recording], topic: str, name: str, default: Any = np.nan) -> NDArray:
    parts = [r.column(topic, name, default) for r in recordings if r.count(topic)]
    return np.concatenate(parts) if parts else np.empty((0,))


def _track(recordings: list[Recording], topic: str) -> tuple[NDArray, NDArray, NDArray]:
    t = _gather(recordings, topic, "t").astype(float)
    p = _gather(recordings, topic, "position").astype(float).reshape(-1, 3)
    q = _gather(recordings, topic, "quaternion").astype(float).reshape(-1, 4)
    return t, p, q


def build_session(session_id: str, recordings: list[Recording]) -> Session:
    """Assemble one session from its recordings (see the module docstring)."""
    warnings: list[str] = []
    for rec in recordings:
        if rec.problem:
            warnings.append(f"{rec.path}: {rec.problem}; using what was recorded")
        if rec.bad_messages:
            warnings.append(f"{rec.path}: {rec.bad_messages} undecodable message(s) skipped")

    def gather(topic: str) -> list[dict]:
        out: list[dict] = []
        for rec in recordings:
            out.extend(rec.samples(topic))
        return out

    t_v, p_v, q_v = _track(recordings, "/expert/pose")
    t_f, p_f, q_f = _track(recordings, "/follower/probe_pose")
    tracked = _gather(recordings, "/follower/probe_pose", "tracked", False).astype(bool)
    good = tracked & np.all(np.isfinite(p_f), axis=1) & np.all(np.isfinite(q_f), axis=1)
    good &= np.linalg.norm(q_f, axis=1) > 0.5
    if len(t_v) == 0:
        warnings.append(f"session {session_id}: no /expert/pose samples")
    if len(t_f) == 0:
        warnings.append(f"session {session_id}: no /follower/probe_pose samples")

    # Clock: follower estimates are (t_f, t_e - t_f); expert ones (t_e, t_f - t_e).
    ts, offs, rtts = [], [], []
    for s in gather("/follower/clock_sync"):
        ts.append(s["t"])
        offs.append(s["offset_s"])
        rtts.append(s.get("rtt_s", np.nan))
    for s in gather("/expert/clock_sync"):
        ts.append(s["t"] + s["offset_s"])
        offs.append(-s["offset_s"])
        rtts.append(s.get("rtt_s", np.nan))
    clock = fit_clock_map(ts, offs, rtts)
    roles = {rec.session.get("role", "") for rec in recordings}
    if clock.n_estimates == 0 and "demo" not in roles and len(t_f):
        warnings.append(
            f"session {session_id}: no clock-sync figures recorded; follower times used as "
            "expert times (only right if both daemons share one clock)"
        )

    real = PoseTrack(clock.to_expert(t_f[good]), p_f[good], q_f[good])
    uq = [
        (float(v["t"]), float(v["quality"]))
        for v in gather("/follower/video_frame")
        if v.get("stream") == "us" and v.get("event") == "captured" and "quality" in v
    ]
    uq_t = clock.to_expert(np.array([a for a, _ in uq], dtype=float)) if uq else np.empty(0)
    uq_v = np.array([b for _, b in uq], dtype=float)
    virtual = PoseTrack(t_v, p_v, q_v)
    cut = [  # the expert's side (the scan events and the virtual pose) not read to its end
        f"{rec.path.name} ({rec.problem})"
        for rec in recordings
        if rec.problem and rec.session.get("role", "") != "follower"
    ]
    scans = _scan_intervals(gather("/expert/scan"), virtual, real, session_id, warnings, cut)
    return Session(
        session_id=session_id,
        files=[rec.path for rec in recordings],
        virtual=virtual,
        real=real,
        frame_times=clock.to_expert(t_f),
        clock=clock,
        scans=scans,
        warnings=warnings,
        us_quality_t=uq_t,
        us_quality=uq_v,
    )


def _scan_intervals(
    events: list[dict],
    virtual: PoseTrack,
    real: PoseTrack,
    session_id: str,
    warnings: list[str],
    cut: list[str] = (),  # type: ignore[assignment]
) -> list[ScanInterval]:
    end = float(virtual.t[-1]) if len(virtual) else (float(real.t[-1]) if len(real) else 0.0)
    begin = float(virtual.t[0]) if len(virtual) else 0.0
    open_: dict[int, ScanInterval] = {}
    out: list[ScanInterval] = []
    for ev in sorted(events, key=lambda e: e["t"]):
        scan = int(ev.get("scan", -1))
        if ev.get("event") == "start":
            if scan in open_:
                warnings.append(f"session {session_id}: scan {scan} started twice; restarted")
            open_[scan] = ScanInterval(
                scan, float(ev["t"]), end, ev.get("follower_id", ""), ev.get("sonographer_id", "")
            )
        elif ev.get("event") == "stop":
            iv = open_.pop(scan, None)
            if iv is None:
                warnings.append(f"session {session_id}: stop of scan {scan} without a start")
                continue
            iv.stop = float(ev["t"])
            out.append(iv)
    for iv in open_.values():
        iv.complete = False
        iv.why_incomplete = "no stop event: its end is unknown (the recording ends first)"
        warnings.append(f"session {session_id}: scan {iv.scan} has no stop (ends at the data)")
        out.append(iv)
    if not events:
        warnings.append(f"session {session_id}: no scan start/stop events; whole session = scan 0")
        whole = ScanInterval(0, begin, end)
        if cut:
            whole.complete = False
            whole.why_incomplete = (
                "no scan events, and the expert's recording is cut: "
                + "; ".join(cut)
                + " (the lost part may hold the scan's start and stop)"
            )
        out.append(whole)
    return sorted(out, key=lambda iv: (iv.start, iv.scan))


def sensing_gaps(
    frame_times: NDArray[np.float64], start: float, stop: float, min_gap_s: float = SENSING_GAP_S
) -> list[tuple[float, float]]:
    """The stretches of ``[start, stop]`` (s) with no tracker frame (``frame_times``, every
    frame, tracked or not) of ``min_gap_s`` or more: (s from ``start``, s long), in order; the
    scan's edges count (a scan without any frame is one gap)."""
    t = np.sort(frame_times[(frame_times >= start) & (frame_times <= stop)])
    edges = np.concatenate(([start], t, [stop]))
    d = np.diff(edges)
    at = np.flatnonzero(d >= min_gap_s)
    return [(float(edges[i] - start), float(d[i])) for i in at]


def analyze_scans(session: Session, max_gap_s: float = 0.05) -> list[ScanResult]:
    """Alignment RMSE of each scan of ``session``."""
    results = []
    for iv in session.scans:
        in_scan = (session.real.t >= iv.start) & (session.real.t <= iv.stop)
        errors = alignment_errors(session.virtual, session.real.select(in_scan), max_gap_s)
        rmse = alignment_rmse(errors)
        if rmse.n == 0:
            session.warnings.append(
                f"session {session.session_id}: scan {iv.scan} has no tracked frames with a "
                "virtual pose"
            )
        ft = session.frame_times
        frames_total = int(np.count_nonzero((ft >= iv.start) & (ft <= iv.stop)))
        result = ScanResult(session.session_id, iv, rmse, errors, frames_total, int(in_scan.sum()))
        result.sensing_gaps = sensing_gaps(ft, iv.start, iv.stop)
        q_in = (session.us_quality_t >= iv.start) & (session.us_quality_t <= iv.stop)
        if np.any(q_in):
            result.sim_quality = float(np.mean(session.us_quality[q_in]))
            result.sim_quality_frames = int(q_in.sum())
        results.append(result)
    return results


def load_sessions(paths: Iterable[str | Path]) -> list[Session]:
    """Read the files and group them by session id (the file name when none is recorded)."""
    groups: dict[str, list[Recording]] = {}
    for p in paths:
        rec = read_recording(p, TOPICS)
        sid = rec.session.get("session_id") or Path(p).stem
        groups.setdefault(sid, []).append(rec)
    return [build_session(sid, recs) for sid, recs in groups.items()]

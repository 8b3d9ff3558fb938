"""What ``humantele demo`` says at the end: the summary of the two daemons' final stats
(``--json`` prints it), with the stream counts of a restarted daemon's window
(:class:`CountWindow`), and the lines for a person.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from humantele.demo_status import children_summary, status_line


def summarize(
    e: dict[str, Any], f: dict[str, Any], duration: float, codes: dict[str, int | None]
) -> dict[str, Any]:
    """The demo's summary from the two daemons' final stats."""
    recording = {
        r: s["recording"] for r, s in (("expert", e), ("follower", f)) if s.get("recording")
    }
    return {
        "duration_s": round(duration, 2),
        "poses_sent": e.get("poses_sent", 0),
        "poses_received": f.get("poses_received", 0),
        "pose_age_p50_ms": f.get("pose_age_p50_ms"),
        "pose_age_p99_ms": f.get("pose_age_p99_ms"),
        "states_sent": f.get("states_sent", 0),
        "states_received": e.get("states_received", 0),
        "state_age_p50_ms": e.get("state_age_p50_ms"),
        "servo_rate_hz": e.get("servo_rate_hz"),
        "servo_overruns": e.get("servo_overruns"),
        "servo_period_p99_us": e.get("servo_period_p99_us"),
        "servo_state": e.get("servo_state"),
        "servo_restarts": e.get("servo_restarts", 0),
        "models_refused": e.get("models_refused", 0),
        "calibrated": bool(f.get("calibrated", False)),
        "model_installed": bool(e.get("has_model", False)),
        "alignment_mm_rms": f.get("alignment_mm_rms"),
        "alignment_deg_rms": f.get("alignment_deg_rms"),
        "dropped_messages": int(e.get("dropped_total", 0)) + int(f.get("dropped_total", 0)),
        "dropped": {"expert": e.get("dropped", {}), "follower": f.get("dropped", {})},
        "link_connections": e.get("connections", 0),
        "cpu_percent_expert": e.get("cpu_percent"),
        "cpu_percent_servo": e.get("cpu_percent_servo"),
        "cpu_percent_follower": f.get("cpu_percent"),
        "cpu_percent_sensing": f.get("cpu_percent_sensing"),
        "follower_tick_late_p99_ms": f.get("tick_late_p99_ms"),
        "loop_priority": {"expert": e.get("loop_priority"), "follower": f.get("loop_priority")},
        "scans": e.get("scans_started", 0),
        "recording": recording or None,
        "video": video_summary(e.get("video"), f.get("video")),
        "children": children_summary(e, f),
        "sensing_devices": devices_summary(f),
        "exit_codes": codes,
    }


def devices_summary(f: dict[str, Any]) -> dict[str, Any]:
    """The follower's devices at the end: the headset stream's stalls, reconnects and state,
    the force board's unplugs, reopens and state, the tracker frames not measured by reason
    (issue 30 §2)."""
    dev = f.get("sensing_devices") or {}
    cam = dev.get("camera") or {}
    board = (dev.get("force") or {}).get("board") or {}
    return {
        "headset_stream_stalled": f.get("headset_stream_stalled"),
        "frames_received": cam.get("received"),  # by the sensing process's camera
        "frames_measured": dev.get("frames"),  # by its tracker
        "stream_stalls": cam.get("stalls"),
        "stream_reconnects": cam.get("reconnects"),
        "camera_dropped": cam.get("dropped"),
        "no_pose_reasons": cam.get("no_pose"),
        "force_stale": f.get("force_stale"),
        "force_stale_measurements": dev.get("force_stale"),
        "force_board_unplugs": board.get("unplugs"),
        "force_board_reopens": board.get("reopens"),
        "unmeasured": f.get("unmeasured"),
        "unmeasured_dominant": f.get("unmeasured_dominant"),
        "sensing_hangs": f.get("sensing_hangs"),
    }


def video_summary(e: dict[str, Any] | None, f: dict[str, Any] | None) -> dict[str, Any] | None:
    """Per track at the expert: frames, rate, age (capture to shown) p50/p95/max, the playout
    delay (media.playout); the follower's POV degradation level; the parity per frame
    (media.fec: ``fec`` the expert's decoder, ``fec_sent`` the follower's encoder, None when
    off). None when video is off."""
    if not e:
        return None
    out: dict[str, Any] = {}
    keys = ("frames", "fps", "fps_mean", "gap_max_ms", "age_p50_ms", "age_p95_ms", "age_max_ms",
            "unreadable", "no_info", "stale_dropped", "jitter", "playout_ms",
            "playout_max_ms")  # fmt: skip
    for name in ("us", "pov"):
        t = e.get(name) or {}
        out[name] = {k: t.get(k) for k in (*keys, "size")}
    out["fec"] = e.get("fec")
    if f:
        out["fec_sent"] = f.get("fec")
        out["pov_level"] = f.get("pov_level")
        out["us_level"] = f.get("us_level")
        out["pov_level_changes"] = f.get("pov_level_changes")
        out["process"] = f.get("process")
        out["pacer"] = f.get("pacer")
        out["follower"] = {n: f.get(n) for n in ("us", "pov")}
    return out


# Counts of one stream at each end: (sender's key, receiver's key) per role.
STREAM_COUNTS = {"expert": ("poses_sent", "states_received"),
                 "follower": ("poses_received", "states_sent")}  # fmt: skip


class CountWindow:
    """After a daemon restarts, the stream counts of the summary cover the same window at both
    ends: from the restart on, the other daemon's counts are taken relative to its last
    figures before the new process could have connected (taken as the restart is seen, not at
    the new process's first stats, which may come after its link is up and messages flow).
    ``since_s``: the window's start (s after the demo started), None without a restart."""

    def __init__(self) -> None:
        self.baseline: dict[str, dict[str, int]] = {"expert": {}, "follower": {}}
        self._restarts_seen = {"expert": 0, "follower": 0}
        self.since_s: float | None = None

    def update(self, daemons: dict, stats: dict[str, dict], t: float) -> None:
        for role, d in daemons.items():
            if d.restarts != self._restarts_seen[role]:  # restarted since the last look
                self._restarts_seen[role] = d.restarts
                other = "follower" if role == "expert" else "expert"
                self.baseline[role] = {}
                self.baseline[other] = {
                    k: int(stats[other].get(k) or 0) for k in STREAM_COUNTS[other]
                }
                self.since_s = round(t, 2)

    def adjusted(self, stats: dict[str, dict]) -> tuple[dict, dict]:
        out = []
        for role in ("expert", "follower"):
            s = dict(stats[role])
            for k, v in self.baseline[role].items():
                s[k] = max(0, int(s.get(k) or 0) - v)
            out.append(s)
        return out[0], out[1]


def _log_tail(path: Path, lines: int = 5) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").strip().splitlines()[-lines:])
    except OSError:
        return ""


def report(
    summary: dict[str, Any],
    e: dict[str, Any],
    f: dict[str, Any],
    failed: str,
    run_dir: Path,
    rec_paths: dict[str, Path],
    as_json: bool,
    out: Any = sys.stdout,
) -> None:
    """The end of the run for a person: why it failed (with the failed daemon's log tail),
    the last status line and the figures (not with ``--json``: the summary is the output),
    a recording that failed or dropped samples, and the command that analyses the
    recordings."""
    codes = summary["exit_codes"]
    if failed:
        role = failed.split(" ", 1)[0]
        tail = _log_tail(run_dir / f"{role}.log")
        print(f"humantele demo: {failed}; logs in {run_dir}", file=sys.stderr)
        if tail:
            print(f"{role} log ends with:\n{tail}", file=sys.stderr)
    elif not all(c == 0 for c in codes.values()):
        print(f"humantele demo: a daemon failed {codes}; logs in {run_dir}", file=sys.stderr)
    if not as_json:
        print(status_line(e, f, summary["duration_s"]), file=out)
        print(
            f"poses sent {summary['poses_sent']}, received {summary['poses_received']}, "
            f"age p50 {summary['pose_age_p50_ms']} ms p99 {summary['pose_age_p99_ms']} ms; "
            f"servo {summary['servo_rate_hz'] or 0:.0f} Hz, {summary['servo_overruns']} overruns; "
            f"calibrated {summary['calibrated']}; dropped {summary['dropped_messages']}; "
            f"CPU expert {summary['cpu_percent_expert']} % (servo "
            f"{summary['cpu_percent_servo']} %), follower {summary['cpu_percent_follower']} %",
            file=out,
        )
    for role, st in (summary["recording"] or {}).items():
        if st.get("error") or st.get("dropped"):
            print(
                f"humantele demo: {role} recording: {st.get('error') or 'ok'}, "
                f"{st.get('dropped')} sample(s) dropped",
                file=sys.stderr,
            )
    if rec_paths and all(p.exists() for p in rec_paths.values()):
        files = " ".join(str(p) for p in rec_paths.values())
        print(f"recorded {summary['scans']} scan(s); analyze with:\n  humantele analyze {files}",
              file=sys.stderr if as_json else out)  # fmt: skip

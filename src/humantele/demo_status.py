"""What ``humantele demo`` is doing, for its status line: the phase the session is in, read
from the daemons' stats, and what it waits for.

The phases, in order (the first that applies):

- ``starting daemons (expert, follower)``: a daemon has written no stats yet (the ones
  named);
- ``waiting for the link (connecting)``: both run, the WebRTC link between them is not up
  (its state in brackets);
- ``starting the tracker``: the link is up, the follower's sensing process is not measuring
  yet (the presses it would miss are not asked for);
- ``calibrating: press left (2 of 4)``: the follower's technician presses the landmarks;
- ``sending the patient model``: calibrated, the expert has no model yet;
- ``following``: the expert has the model; the novice follows the virtual probe;
- ``link closed``: the daemons said bye (the run's end).

"calibrating" is never said before the link is up: before then the demo waits for the link,
whatever the follower does meanwhile.

:func:`status_line` is the whole line: the phase, the pose rate and age at the follower, the
haptic force, the alignment, the servo, the follower's children when one is not running, and
the scan and recording.
"""

from __future__ import annotations

from typing import Any

from humantele.wire import LANDMARKS


def demo_phase(e: dict[str, Any], f: dict[str, Any]) -> str:
    """The demo's phase from the expert's (``e``) and follower's (``f``) latest stats (empty
    dicts before a daemon's first)."""
    missing = [role for role, s in (("expert", e), ("follower", f)) if not s]
    if missing:
        return f"starting daemons ({', '.join(missing)})"
    link = f.get("link_state") or "new"
    if link == "closed":  # the end of the run: the daemons said bye
        return "link closed"
    if link != "connected":
        return f"waiting for the link ({link})"
    if not f.get("calibrated"):
        if f.get("sensing_ready") is False:
            return "starting the tracker"
        step = f.get("calibration_step")
        if step in LANDMARKS:
            return f"calibrating: press {step} ({LANDMARKS.index(step) + 1} of 4)"
        return "calibrating"
    if not e.get("has_model"):
        return "sending the patient model"
    return "following"


def poses_flowing(status_line: str) -> bool:
    """Whether a status line of the demo says the link is up and poses arrive (a phase after
    the link came up, and a pose rate above 0 Hz): for scripts and tests reading stderr."""
    if not status_line.startswith("[") or "] " not in status_line:
        return False
    phase = status_line.split("] ", 1)[1].split(" |", 1)[0]
    down = phase.startswith(("starting daemons", "waiting for the link", "link closed"))
    return not down and "poses 0 Hz" not in status_line and "poses - Hz" not in status_line


def status_line(e: dict[str, Any], f: dict[str, Any], elapsed: float) -> str:
    def num(v: Any, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    return (
        f"[{elapsed:5.1f} s] {demo_phase(e, f)} | "
        f"poses {num(f.get('pose_rate_hz'), '.0f')} Hz, "
        f"age {num(f.get('pose_age_last_ms'), '.1f')} ms | "
        f"force {num(e.get('force_n'), '.2f')} N | "
        f"alignment {num(f.get('alignment_mm_rms'), '.1f')} mm "
        f"{num(f.get('alignment_deg_rms'), '.1f')} deg | "
        + servo_status(e)
        + children_status(f)
        + devices_status(f)
        + recording_status(e, f)
    )


UNMEASURED_SHORT = {"no_pose": "no camera pose", "no_frame": "no frame",
                    "stale": "replaced unread", "skipped": "skipped under load"}  # fmt: skip


def devices_status(f: dict[str, Any]) -> str:
    """The follower's devices when one is not well: `` | headset stream stalled``, `` | force
    board STALE``, and when most tracker frames went unmeasured lately, why: `` | tracker
    frames 80% no camera pose`` (else '')."""
    out = ""
    if f.get("headset_stream_stalled"):
        out += " | headset stream stalled"
    if f.get("force_stale"):
        out += " | force board STALE"
    reason = f.get("unmeasured_dominant")
    if reason:
        share = f.get("unmeasured_share") or 0.0
        out += f" | tracker frames {100 * share:.0f}% {UNMEASURED_SHORT.get(reason, reason)}"
    return out


def children_status(f: dict[str, Any]) -> str:
    """The follower's children when one is not running: `` | video DOWN (...)``, `` | video
    restarting (1)``, `` | sensing restarting (1), no measurements 4 s`` (else '')."""
    out = ""
    video = (f.get("video") or {}).get("process") or {}
    state = str(video.get("state") or "running")
    if state.startswith(("down", "failed")):
        out += f" | video DOWN ({state.partition(': ')[2][:80]})"
    elif state.startswith("restarting"):
        out += f" | video {state}"
    sensing = str(f.get("sensing_state") or "running")
    if sensing.startswith(("restarting", "failed")):
        out += f" | sensing {sensing[:80]}"
        age = f.get("measurement_age_s")
        if age is not None and age > 0.5:
            out += f", no measurements {age:.0f} s"
    return out


def children_summary(e: dict[str, Any], f: dict[str, Any]) -> dict[str, Any]:
    """Each daemon child's restarts and state at the end; the follower's time without
    measurements after its first (a restarted sensing process takes seconds to measure)."""
    video = (f.get("video") or {}).get("process")
    return {
        "servo": {"restarts": e.get("servo_restarts", 0), "state": e.get("servo_state")},
        "sensing": {
            "restarts": f.get("sensing_restarts", 0),
            "state": f.get("sensing_state"),
            **{
                k: f.get(k)
                for k in ("measurement_gaps", "measurement_gap_s", "measurement_gap_max_s")
            },
        },  # fmt: skip
        "video": None if not video else {k: video.get(k) for k in ("restarts", "state")},
    }


def servo_status(e: dict[str, Any]) -> str:
    """``servo 1000 Hz``, or the fault / the reason it is down, in capitals (never hidden)."""
    state = str(e.get("servo_state") or "running")
    if state.startswith("down"):
        return f"servo DOWN ({state.partition(': ')[2][:80]})"
    text = f"servo {format(e['servo_rate_hz'], '.0f') if e.get('servo_rate_hz') else '-'} Hz"
    if state.startswith("fault"):
        text += f" FAULT {state.partition(': ')[2]}"
    if e.get("models_refused"):
        text += f", {e['models_refused']} model(s) REFUSED"
    return text


def recording_status(e: dict[str, Any], f: dict[str, Any]) -> str:
    """`` | scan 1, recording`` (or ``recording FAILED``) when the daemons record."""
    recs = [s["recording"] for s in (e, f) if s.get("recording")]
    scan = e.get("scan")
    text = f" | scan {scan}" if scan else ""
    if recs:
        failed = any(r.get("error") for r in recs)
        text += (", " if text else " | ") + ("recording FAILED" if failed else "recording")
    return text

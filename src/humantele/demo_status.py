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

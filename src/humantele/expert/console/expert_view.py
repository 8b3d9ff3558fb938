"""What the console reads of the expert daemon: :class:`ExpertView`, a protocol the daemon
implements (:class:`humantele.expert.daemon.ExpertDaemon`), so the console never imports the
daemon; :class:`PoseHistory`, the timed poses a captured frame gets its pose from; and
:func:`calibration_display`, the calibration state shown from the follower's progress.

Everything here is read on the daemon's event loop, except :class:`SessionScene
<humantele.expert.console.hook.SessionScene>`'s reads from the sim sources' threads, which
only take references the daemon replaces whole (``model``, ``last_state``, ``last_pose``).
"""

from __future__ import annotations

from collections import deque
from typing import TYPE_CHECKING, Protocol, runtime_checkable

from humantele.geometry import Pose
from humantele.wire import LANDMARKS

if TYPE_CHECKING:
    from humantele.haptics.ellipsoid import Ellipsoid
    from humantele.haptics.servo_layout import ServoSample, ServoStats
    from humantele.recording import Recorder
    from humantele.wire import CalibrationProgress, StateMessage

POSES_KEPT_S = 12.0  # pose history for captures (the cine buffer holds 10 s)


class PoseHistory:
    """Timed poses (s, the expert's clock) of the last ``seconds``; ``at(t)`` the nearest."""

    def __init__(self, seconds: float = POSES_KEPT_S) -> None:
        self.seconds = seconds
        self.items: deque[tuple[float, Pose]] = deque()

    def add(self, t: float, pose: Pose) -> None:
        self.items.append((t, pose))
        while self.items and t - self.items[0][0] > self.seconds:
            self.items.popleft()

    def at(self, t: float, within_s: float = 0.25) -> Pose | None:
        best = min(self.items, key=lambda it: abs(it[0] - t), default=None)
        if best is None or abs(best[0] - t) > within_s:
            return None
        return best[1]


def calibration_display(
    state: str, msg: CalibrationProgress, has_model: bool
) -> tuple[str, str | None]:
    """The calibration state the console shows (``not calibrated``, ``calibrating``,
    ``calibrated``) and the landmark to touch next, after the follower's progress ``msg``
    (``state``: the one before; ``has_model``: a patient model is rendered)."""
    nxt = None
    if msg.event == "start":
        state, nxt = "calibrating", 0
    elif msg.event == "point" and msg.index is not None:
        state, nxt = "calibrating", msg.index + 1
    elif msg.event == "error":
        state = "calibrating"
        nxt = msg.index if msg.index is not None else None
    elif msg.event == "done":
        state = "calibrated"
    elif msg.event == "cancel":
        state = "calibrated" if has_model else "not calibrated"
    return state, (LANDMARKS[nxt] if nxt is not None and nxt < len(LANDMARKS) else None)


class ServoView(Protocol):
    """The servo process as the console sees it (:class:`humantele.haptics.servo.ServoProcess`)."""

    @property
    def alive(self) -> bool: ...

    def latest(self) -> ServoSample | None: ...

    def stats(self) -> ServoStats: ...


class LinkView(Protocol):
    """The link to the follower: its state (``connected``, ``connecting``, ...)."""

    @property
    def state(self) -> str: ...


class MappingView(Protocol):
    """The stylus mapping: whether the clutch holds the virtual probe."""

    @property
    def clutched(self) -> bool: ...


@runtime_checkable
class ExpertView(Protocol):
    """The expert session the console shows and drives. Poses are in the patient frame (m,
    quaternion x, y, z, w), times on the daemon's monotonic clock (s)."""

    servo: ServoView
    link: LinkView
    mapping: MappingView
    rec: Recorder | None  # the session's recorder (None: not recording)
    model: Ellipsoid | None  # the patient model rendered
    last_state: StateMessage | None  # the follower's latest probe pose and force
    last_state_t: float | None  # when it was sampled, on this clock (s)
    last_pose: Pose | None  # the virtual probe as last sent
    calibration_state: str  # "not calibrated", "calibrating" or "calibrated"
    calibration_landmark: str | None  # the landmark the follower is to touch next
    calibration_events: list[str]  # the follower's calibration progress, oldest first
    scan: int | None  # the scan in progress
    console_clutch: bool  # the console's clutch button (written by the console)
    probe_history: PoseHistory  # the follower's probe, by time
    virtual_history: PoseHistory  # the virtual probe, by time

    def clock(self) -> float:
        """The daemon's clock (s)."""
        ...

    def start_scan(self, t: float) -> int:
        """Start the next scan at ``t``; its number."""
        ...

    def stop_scan(self, t: float) -> None:
        """Stop the scan in progress at ``t`` (nothing if none)."""
        ...

"""The console sees the expert daemon only through ExpertView (issue 22 §1): the daemon is
one, a stand-in that is not a daemon drives the console's session the same way, and the
calibration the console shows follows the follower's progress over the one landmark list."""

from __future__ import annotations

import math

import pytest

from humantele.expert.config import ExpertConfig
from humantele.expert.console.expert_view import ExpertView, PoseHistory, calibration_display
from humantele.expert.console.hook import DaemonSession
from humantele.expert.daemon import ExpertDaemon
from humantele.follower import calibration
from humantele.geometry import Pose, quat_from_axis_angle
from humantele.wire import LANDMARKS, CalibrationProgress, StateMessage


class Servo:
    alive = False

    def latest(self):
        raise AssertionError("a servo that is not alive is not read")

    def stats(self):
        raise AssertionError("a servo that is not alive is not read")


class Link:
    state = "connected"


class Mapping:
    clutched = False


class StandIn:
    """An expert that is not the daemon: what the protocol names, no more."""

    def __init__(self) -> None:
        self.servo, self.link, self.mapping = Servo(), Link(), Mapping()
        self.rec = None
        self.model = None
        self.last_state: StateMessage | None = None
        self.last_state_t: float | None = None
        self.last_pose: Pose | None = None
        self.calibration_state = "calibrating"
        self.calibration_landmark: str | None = "left"
        self.calibration_events = ["start", "point"]
        self.scan: int | None = None
        self.console_clutch = False
        self.probe_history = PoseHistory()
        self.virtual_history = PoseHistory()
        self.t = 50.0
        self.scans: list[tuple[str, float]] = []

    def clock(self) -> float:
        return self.t

    def start_scan(self, t: float) -> int:
        self.scans.append(("start", t))
        self.scan = len(self.scans)
        return self.scan

    def stop_scan(self, t: float) -> None:
        self.scans.append(("stop", t))
        self.scan = None


def test_the_daemon_and_a_stand_in_are_expert_views():
    assert isinstance(ExpertDaemon(ExpertConfig()), ExpertView)
    assert isinstance(StandIn(), ExpertView)
    assert not isinstance(object(), ExpertView)


def test_the_console_session_reads_and_drives_a_stand_in():
    e = StandIn()
    virtual = Pose([0.0, 0.1, 0.0], [0.0, 0.0, 0.0, 1.0])
    real = Pose([0.003, 0.104, 0.0], quat_from_axis_angle([0.0, 0.0, 1.0], math.radians(5.0)))
    e.last_pose = virtual
    e.last_state = StateMessage(1, 0.0, tuple(real.position), tuple(real.quaternion), 2,
                                (0.0, 0.0, -4.0), True)  # fmt: skip
    e.last_state_t = 49.99
    e.probe_history.add(49.0, real)
    e.virtual_history.add(49.0, virtual)
    session = DaemonSession(e)
    snap = session.snapshot()
    assert snap["t"] == 50.0 and snap["link"]["state"] == "connected"
    assert snap["link"]["pose_age_ms"] == pytest.approx(10.0)
    assert snap["alignment"]["mm"] == pytest.approx(5.0)  # Pose.distance_to, in mm
    assert snap["alignment"]["deg"] == pytest.approx(5.0)
    assert snap["calibration"] == {"state": "calibrating", "landmark": "left", "last": "point"}
    assert snap["servo"]["alive"] is False and snap["recording"]["on"] is False
    assert snap["force"]["measured_n"] == pytest.approx(4.0) and snap["force"]["contact"]
    assert session.pose_at(49.1)["virtual_position"] is virtual.position
    assert session.pose_at(40.0) is None  # nothing near: no pose rather than a wrong one
    assert session.start_scan() == 1 and e.scans == [("start", 50.0)]
    session.stop_scan()
    assert e.scans[-1] == ("stop", 50.0) and e.scan is None
    session.set_clutch(True)
    assert e.console_clutch is True and session.snapshot()["clutch"] == {
        "on": True,
        "engaged": False,
    }


def test_one_landmark_list_and_the_calibration_the_console_shows():
    assert calibration.LANDMARKS is LANDMARKS  # the follower's calibration uses the wire's
    assert LANDMARKS == ("xiphoid", "left", "right", "bed")

    def show(state, has_model=False, **msg):
        return calibration_display(state, CalibrationProgress(**msg), has_model)

    assert show("not calibrated", event="start") == ("calibrating", "xiphoid")
    assert show("calibrating", event="point", index=0, point=(0.0, 0.0, 0.0)) == (
        "calibrating",
        "left",
    )
    assert show("calibrating", event="point", index=3) == ("calibrating", None)  # the last
    assert show("calibrating", event="error", index=2) == ("calibrating", "right")  # again
    assert show("calibrating", event="done") == ("calibrated", None)
    assert show("calibrating", event="cancel") == ("not calibrated", None)
    assert show("calibrating", True, event="cancel") == ("calibrated", None)  # the old model

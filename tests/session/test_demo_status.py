"""The demo's status line says what the session waits for, in order, from the daemons' stats;
never "calibrating" before the link is up."""

from humantele.demo_status import demo_phase, poses_flowing, status_line

UP = {"link_state": "connected", "sensing_ready": True}


def test_phases_in_order():
    assert demo_phase({}, {}) == "starting daemons (expert, follower)"
    assert demo_phase({"role": "expert"}, {}) == "starting daemons (follower)"
    assert demo_phase({}, {"link_state": "new"}) == "starting daemons (expert)"
    e = {"has_model": False}
    assert demo_phase(e, {"link_state": "new"}) == "waiting for the link (new)"
    assert demo_phase(e, {"link_state": "connecting"}) == "waiting for the link (connecting)"
    assert demo_phase(e, {**UP, "sensing_ready": False}) == "starting the tracker"
    f = {**UP, "calibrated": False, "calibration_step": "left"}
    assert demo_phase(e, f) == "calibrating: press left (2 of 4)"
    assert demo_phase(e, {**f, "calibration_step": None}) == "calibrating"
    f = {**UP, "calibrated": True}
    assert demo_phase(e, f) == "sending the patient model"
    assert demo_phase({"has_model": True}, f) == "following"
    # The link lost later: the demo waits for it again, whatever it had reached.
    lost = {"link_state": "disconnected", "calibrated": True}
    assert demo_phase({"has_model": True}, lost) == "waiting for the link (disconnected)"
    assert demo_phase({"has_model": True}, {**lost, "link_state": "closed"}) == "link closed"


def test_never_calibrating_before_the_link():
    """The follower's technician may press while the link connects: the line says what the
    demo waits for, the link."""
    for link in ("new", "connecting", "disconnected", "unreachable", "closed", None):
        for step in ("xiphoid", "bed", None):
            f = {"link_state": link, "calibrated": False, "calibration_step": step}
            line = status_line({"has_model": False}, f, 3.0)
            assert "calibrat" not in line and ("waiting for the link" in line or "closed" in line)


def test_status_line_leads_with_the_phase():
    e = {"has_model": True, "force_n": 1.5, "servo_rate_hz": 1000.0}
    f = {**UP, "calibrated": True, "pose_rate_hz": 100.0, "pose_age_last_ms": 0.8}
    line = status_line(e, f, 12.0)
    assert line.startswith("[ 12.0 s] following | poses 100 Hz, age 0.8 ms")
    assert status_line({}, {}, 0.4).startswith("[  0.4 s] starting daemons (expert, follower)")


def test_poses_flowing_reads_thestatus_line():
    """What scripts and tests read from stderr: the link up (a phase after it) and poses."""

    def line(phase: str, rate: str = "45") -> str:
        return f"[ 12.0 s] {phase} | poses {rate} Hz, age 1.0 ms | force 0.00 N | servo 1000 Hz"

    assert poses_flowing(line("following")) and poses_flowing(line("calibrating: press left"))
    assert not poses_flowing(line("waiting for the link (connecting)"))
    assert not poses_flowing(line("starting daemons (expert)", "-"))
    assert not poses_flowing(line("link closed"))
    assert not poses_flowing(line("following", "0")) and not poses_flowing("following")

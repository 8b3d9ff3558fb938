"""The headset's XR space registered to the tracker's world: the rigid fit, its refusals,
the follower's side of the page's registration (touches, saving, the watch) and the feed's
routing of the page's messages."""

import json
import math

import numpy as np
import pytest

from humantele.follower.feed import RendererFeed
from humantele.follower.registration import (
    DegenerateRegistration,
    HeadsetRegistration,
    RegistrationConfig,
    fit_from_trajectories,
    fit_rigid,
    refusal,
    solve_trajectories,
    viewer_rig_offset,
)
from humantele.geometry import Pose, quat_from_axis_angle, quat_multiply

# The XR space seen from the tracker's world: 1.3 m away, turned 35 degrees about up and
# tilted 2 degrees (a real headset's is level; the fit must not assume it).
T_WORLD_XR = Pose(
    [1.3, -0.4, 0.7],
    quat_multiply(quat_from_axis_angle([1, 0, 0.3], math.radians(2)),
                  quat_from_axis_angle([0, 1, 0], math.radians(35))),
)  # fmt: skip
TARGETS = np.array([[-0.12, 0.9, -0.45], [0.12, 0.9, -0.45], [0.12, 0.9, -0.6], [-0.1, 0.95, -0.6]])
ID = "quest-01"


def errors(T: Pose, truth: Pose) -> tuple[float, float]:
    dp, da = T.distance_to(truth)
    return dp * 1000.0, math.degrees(da)


def test_known_transform_recovered_exactly_without_noise():
    fit = fit_rigid(TARGETS, T_WORLD_XR.apply(TARGETS))
    mm, deg = errors(fit.T_world_xr, T_WORLD_XR)
    assert mm < 1e-9 and deg < 1e-6 and fit.rms_m < 1e-12 and fit.n == 4
    assert math.degrees(fit.tilt_rad) == pytest.approx(2.0, abs=1e-6)
    # three points fix it too, and a large turn (170 degrees) is no special case
    T = Pose([0.0, 0.1, -2.0], quat_from_axis_angle([0, 1, 0], math.radians(170)))
    fit = fit_rigid(TARGETS[:3], T.apply(TARGETS[:3]))
    assert errors(fit.T_world_xr, T)[0] < 1e-9


@pytest.mark.parametrize(
    ("xr", "world", "why"),
    [
        (TARGETS[:2], TARGETS[:2], "at least 3"),
        ([[0, 1, 0], [0.1, 1, 0], [0.2, 1, 0], [0.3, 1.0, 0.001]], None, "on a line"),
        (TARGETS, TARGETS[:3], "4 XR points but 3"),
        ([[0, 1, 0], [0.1, 1, 0], [0.2, 1, float("nan")]], None, "finite"),
    ],
)
def test_degenerate_points_refused_with_the_reason(xr, world, why):
    with pytest.raises(DegenerateRegistration, match=why):
        fit_rigid(xr, xr if world is None else world)


def test_noisy_touches_within_bounds_and_bad_ones_refused():
    rng = np.random.default_rng(7)
    cfg = RegistrationConfig()
    work = TARGETS.mean(axis=0)
    worst_mm = []
    for _ in range(200):  # the tracker's 0.5 mm and a hand's 2 mm (per axis)
        world = T_WORLD_XR.apply(TARGETS) + rng.normal(0, math.hypot(0.5, 2.0) / 1000, (4, 3))
        fit = fit_rigid(TARGETS, world)
        assert refusal(fit, cfg) is None or fit.rms_m * 1000 > cfg.max_residual_mm
        gap = np.linalg.norm(fit.T_world_xr.apply(work) - T_WORLD_XR.apply(work)) * 1000
        worst_mm.append(gap)
    assert np.median(worst_mm) < 3.0  # at the targets the fit averages the touches
    # one touch 3 cm off: refused, naming it
    world = T_WORLD_XR.apply(TARGETS)
    world[2] += [0.03, 0, 0]
    why = refusal(fit_rigid(TARGETS, world), cfg)
    assert why is not None and "target 3" in why and "above 6 mm" in why
    # two touches swapped: a large residual or a tilt; either way refused
    world = T_WORLD_XR.apply(TARGETS)[[1, 0, 2, 3]]
    assert refusal(fit_rigid(TARGETS, world), cfg) is not None


def test_trajectories_give_the_registration_once_the_offset_is_known():
    rng = np.random.default_rng(3)
    T_viewer_rig = Pose([0.0, -0.02, 0.08], quat_from_axis_angle([1, 0, 0], 0.1))
    viewers = [
        Pose(rng.uniform(-0.5, 0.5, 3) + [0, 1.6, 0], quat_from_axis_angle(rng.normal(size=3), 0.5))
        for _ in range(10)
    ]
    rigs = [T_WORLD_XR @ v @ T_viewer_rig for v in viewers]
    T = fit_from_trajectories(viewers, rigs, T_viewer_rig)
    assert errors(T, T_WORLD_XR)[0] < 1e-9
    offset = viewer_rig_offset(T_WORLD_XR, viewers, rigs)
    assert errors(offset, T_viewer_rig)[0] < 1e-9
    # with no offset known: both from the trajectories (hand-eye, B = Z A X)
    Z, X = solve_trajectories(viewers, rigs)
    assert errors(Z, T_WORLD_XR)[0] < 1e-6 and errors(X, T_viewer_rig)[0] < 1e-6
    # ... but not from a head that only turned about one axis (here: up, looking around)
    yaw_only = [Pose(v.position, quat_from_axis_angle([0, 1, 0], 0.2 * k))
                for k, v in enumerate(viewers)]  # fmt: skip
    with pytest.raises(DegenerateRegistration, match="one axis"):
        solve_trajectories(yaw_only, [T_WORLD_XR @ v @ T_viewer_rig for v in yaw_only])


class Clinic:
    """A HeadsetRegistration with a clock, its published objects, and a sim technician who
    holds the tip on the page's targets (the world truth is T_WORLD_XR)."""

    def __init__(self, state_dir, config=None):
        self.t = 100.0
        self.published = []
        self.reg = HeadsetRegistration(
            config, state_dir, lambda k, f: self.published.append((k, f)), clock=lambda: self.t
        )

    @property
    def last(self):
        return self.published[-1][1]

    def hold(self, world_point, seconds, rig=None, jitter_m=0.0, rng=None):
        for _ in range(round(seconds * 45)):
            self.t += 1 / 45
            p = np.asarray(world_point, dtype=float)
            if jitter_m:
                p = p + rng.normal(0, jitter_m, 3)
            self.reg.on_measurement(self.t, Pose(p, [0, 0, 0, 1]), rig)

    def send(self, action, **fields):
        self.reg.on_page_message({"type": "registration", "action": action, "headset": ID,
                                  **fields})  # fmt: skip

    def register(self, rng):
        self.send("start", targets=TARGETS.tolist())
        for p in T_WORLD_XR.apply(TARGETS):
            self.hold(p + [0.1, 0.05, 0], 0.3)  # on the way
            self.hold(p, 1.3, jitter_m=0.0004, rng=rng)


def test_touching_the_targets_registers_saves_and_offers_again(tmp_path):
    rng = np.random.default_rng(1)
    c = Clinic(tmp_path)
    c.send("hello")
    assert c.last["state"] == "none"
    c.hold([0.5, 0.8, 0.2], 2.0)  # the probe lying still at start is no touch
    c.send("start", targets=TARGETS.tolist())
    c.hold([0.5, 0.8, 0.2], 2.0)
    assert c.last["state"] == "collecting" and c.last["index"] == 0
    for i, p in enumerate(T_WORLD_XR.apply(TARGETS)):
        c.hold(p + [0.1, 0.05, 0], 0.3)
        c.hold(p, 1.3, jitter_m=0.0004, rng=rng)
        assert c.last["index" if i < 3 else "state"] == (i + 1 if i < 3 else "registered")
    done = c.last
    T = Pose(done["T_world_xr"]["position"], done["T_world_xr"]["quaternion"])
    mm, deg = errors(T, T_WORLD_XR)
    assert mm < 2.0 and deg < 1.0 and done["residual_mm"] < 1.0 and not done["reused"]
    inv = Pose(done["T_xr_world"]["position"], done["T_xr_world"]["quaternion"])
    assert errors(inv @ T, Pose.identity())[0] < 1e-9
    # next start: the same headset is offered its saved registration, another is not
    again = Clinic(tmp_path)
    again.send("hello")
    assert again.last["state"] == "registered" and again.last["reused"]
    assert again.last["T_world_xr"] == done["T_world_xr"]
    again.reg.on_page_message({"type": "registration", "action": "hello", "headset": "other"})
    assert again.last["state"] == "none"
    assert json.loads((tmp_path / "headsets.json").read_text())[ID]["points"] == 4


def test_a_press_that_crossed_the_dwells_last_take_is_not_a_bad_message(tmp_path):
    """The technician presses as the dwell takes the last target (the page still showed
    'collecting'): counted as late, not as a bad message; a press long after still is."""
    c = Clinic(tmp_path)
    c.register(np.random.default_rng(3))
    assert c.last["state"] == "registered"
    c.t += 0.5
    c.send("take")
    assert c.reg.counts["press_after_done"] == 1 and not c.reg.bad_messages
    assert c.last["state"] == "registered"
    c.t += 5.0
    c.send("take")
    assert c.reg.bad_messages["take_not_collecting"] == 1


def test_a_touch_at_the_wrong_place_or_untracked_is_refused_with_the_reason(tmp_path):
    c = Clinic(tmp_path)
    c.send("start", targets=TARGETS.tolist())
    world = T_WORLD_XR.apply(TARGETS)
    c.hold(world[0] + [0.1, 0, 0], 0.5)
    c.hold(world[0], 1.2)
    assert c.last["index"] == 1
    c.hold(world[1] + [0.05, 0, 0.05], 1.5)  # 7 cm off target 2
    assert c.last["index"] == 1 and "not at target 2" in c.last["refused"]
    c.t += 1.0  # nothing tracked for a second, then a press
    c.send("take")
    assert "not tracked" in c.last["refused"] and c.last["index"] == 1
    c.hold(world[1], 0.2)
    c.send("take")  # pressed on target 2: taken at once
    assert c.last["index"] == 2 and c.last["refused"] == ""
    c.send("cancel")
    assert c.last["state"] == "cancelled"
    # a fit above the bound is refused with the residual
    c = Clinic(tmp_path, RegistrationConfig(max_residual_mm=0.5, distance_check_mm=100))
    c.send("start", targets=TARGETS.tolist())
    for k, p in enumerate(world):
        c.hold(p + [0.1, 0.05, 0], 0.3)
        c.hold(p + (0.004 if k == 2 else 0.0), 1.2)
    assert c.last["state"] == "refused" and "above 0.5 mm" in c.last["message"]


def test_the_watch_says_re_register_when_the_two_poses_drift_apart(tmp_path):
    rng = np.random.default_rng(5)
    c = Clinic(tmp_path, RegistrationConfig(offset_samples=5, watch_samples=5))
    c.register(rng)
    assert c.last["state"] == "registered" and c.last["watch"] == "waiting"
    T_viewer_rig = Pose([0.0, -0.03, 0.09], quat_from_axis_angle([1, 0, 0], 0.2))
    viewer = Pose([0.1, 1.6, 0.2], quat_from_axis_angle([0, 1, 0], 0.3))

    def look(n, rig):
        for _ in range(n):
            c.hold(T_WORLD_XR.apply(TARGETS[0]), 0.1, rig=rig)
            c.reg.on_page_message({"type": "viewer_pose", "headset": ID,
                                   "position": viewer.position.tolist(),
                                   "quaternion": viewer.quaternion.tolist()})  # fmt: skip

    rig = T_WORLD_XR @ viewer @ T_viewer_rig
    # another headset's page says hello meanwhile: this one's watch goes on regardless
    c.reg.on_page_message({"type": "registration", "action": "hello", "headset": "other"})
    look(12, rig)  # the offset calibrated from the first 5, then watched
    assert c.reg.counts["offset_calibrated"] == 1
    assert c.reg.counts["viewer_compared"] == 12 - 5 + 1  # the 5th pair calibrates, compared
    assert c.last["headset"] == ID and c.last["watch"] == "ok" and c.last["drift_mm"] < 2.0
    moved = Pose(rig.position + [0.05, 0, 0], rig.quaternion)  # the XR space jumped 5 cm
    look(6, moved)
    assert c.last["watch"] == "drifted" and c.last["drift_mm"] == pytest.approx(50, abs=3)
    # the offset is kept with the headset: a reused registration is watched at once
    again = Clinic(tmp_path, RegistrationConfig(offset_samples=5, watch_samples=5))
    again.send("hello")
    c = again
    look(6, rig)
    assert c.last["watch"] == "ok"


def test_bad_page_messages_counted_never_raised(tmp_path):
    c = Clinic(tmp_path)
    bad = [
        {"type": "registration", "action": "explode", "headset": ID},
        {"type": "registration", "action": "start", "headset": "../etc", "targets": []},
        {"type": "registration", "action": "start", "headset": ID, "targets": [[1, 2]] * 3},
        {"type": "viewer_pose", "headset": ID, "position": ["1", 0, 0], "quaternion": [0, 0, 0, 1]},
        {"type": "viewer_pose", "headset": ID, "position": [1e9, 0, 0], "quaternion": [0, 0, 0, 1]},
        {"type": "viewer_pose", "headset": ID, "position": [float("nan"), 0, 0]},
        {"type": "drawn", "pose_id": 1},
        {"nothing": True},
    ]
    for m in bad:
        c.reg.on_page_message(m)
    assert c.reg.bad_messages["malformed"] == len(bad)
    c.send("start")  # no targets
    c.send("start", targets=[[0, 1, 0], [0.1, 1, 0], [0.2, 1, 0]])  # on a line
    c.send("take")  # not registering
    assert c.reg.bad_messages["start_without_targets"] == 1
    assert c.reg.bad_messages["degenerate_targets"] == 1 and "line" in c.last["message"]
    assert c.reg.bad_messages["take_not_collecting"] == 1
    four = Clinic(tmp_path, RegistrationConfig(min_points=4))
    four.send("start", targets=TARGETS[:3].tolist())
    assert four.last["state"] == "refused" and "need 4" in four.last["message"]
    (tmp_path / "headsets.json").write_text("{not json")
    assert "headsets.json" in Clinic(tmp_path).reg.stats()["load_error"]


def test_feed_routes_the_pages_registration_messages_and_counts_bad_ones():
    feed = RendererFeed()
    got = []
    client = type("C", (), {"last_echo": 0})()
    msg = {"type": "registration", "action": "hello", "headset": ID}
    feed._on_page_message(client, json.dumps(msg))
    assert feed.refused["unrouted"] == 1 and not got
    feed.page_handler = got.append
    feed._on_page_message(client, json.dumps(msg))
    pose = {"type": "viewer_pose", "headset": ID, "position": [0, 1.6, 0],
            "quaternion": [0, 0, 0, 1]}  # fmt: skip
    feed._on_page_message(client, json.dumps(pose))
    assert got == [{**msg, "targets": None}, pose]
    for text in ['{"type": "registration"}', '{"type": "viewer_pose", "headset": "x"}', "[]"]:
        feed._on_page_message(client, text)
    assert feed.refused["malformed"] == 3 and len(got) == 2
    feed._on_page_message(client, '{"type": "drawn", "pose_id": 1, "draw_to_send_ms": 0}')
    assert feed.refused["unknown_pose"] == 1  # the echoes still go their way


def test_the_daemon_hook_routes_the_page_and_feeds_each_measurement(tmp_path):
    """The lines the follower daemon adds: construct (routing the feed's page messages to
    it), one call per measurement (tip and rig pose), one stats entry."""
    from daemon_doubles import LinkDouble
    from humantele.follower.daemon import FollowerConfig, FollowerDaemon

    d = FollowerDaemon(FollowerConfig(state_dir=str(tmp_path), probe_source="truth"))
    d.link = LinkDouble(age_s=0.01)
    client = type("C", (), {"last_echo": 0})()
    d.feed._on_page_message(client, json.dumps({"type": "registration", "action": "hello",
                                                "headset": ID}))  # fmt: skip
    assert json.loads(d.feed.latest["registration"])["state"] == "none"
    d.start_calibration()  # the sim technician picks up the probe and presses
    d.clinic.script_t0, t = 0.0, 0.0
    for _ in range(300):
        d.tick(t)
        t += 0.01
    assert d.registration.tips and d.registration.rigs  # 45 Hz frames reached it
    assert d.stats()["registration"]["counts"] == {"hello": 1}

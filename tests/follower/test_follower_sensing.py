import numpy as np
import pytest

from humantele.follower.sensing import ProbeSensing, SensingConfig, tip_transform
from humantele.follower.sim_world import WorldTruth
from humantele.geometry import Pose, matrix_to_quat, quat_from_axis_angle, quat_multiply
from humantele.tracking.sim import SimFrameConfig

# the sim headset camera 0.42 m above the probe, looking down (OpenCV axes)
DOWN = matrix_to_quat(np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]))
CAMERA = Pose([0.1, 1.37, 0.2], DOWN)


@pytest.fixture(scope="module")
def sensing():
    return ProbeSensing()


def measure(s, t, probe, f_world, camera=CAMERA):
    """Measure the sim clinic's world with the probe (body) at ``probe``, the force
    ``f_world`` on it and the headset camera at ``camera``."""
    tip = probe @ tip_transform(s.tool)
    return s.measure(t, WorldTruth(t, tip, np.asarray(f_world, dtype=float), camera))


def _probe(i):
    """Upright probe (handle, probe +z = world +y) on an abdomen, sliding and rocking."""
    upright = quat_from_axis_angle([1.0, 0.0, 0.0], -np.pi / 2)
    rock = quat_from_axis_angle([1.0, 0.0, 0.3], np.radians(10.0 * np.sin(i / 20.0)))
    return Pose([0.1 + 0.001 * i, 0.95, 0.2], quat_multiply(rock, upright))


def test_pose_and_force_come_from_the_pipeline_not_the_truth(sensing):
    errs, forces = [], []
    for i in range(60):
        f_true = np.array([0.0, -6.0, 1.0]) if 20 <= i < 40 else np.zeros(3)
        m = measure(sensing, i / 45.0, _probe(i), f_true)
        assert m.status in ("tracked", "lost", "ambiguous")
        assert np.all(np.isfinite(m.force_world))
        if m.T_world_probe is not None:
            errs.append(_probe(i).distance_to(m.T_world_probe))
            np.testing.assert_allclose(m.tip_world, m.T_world_probe.apply([0, 0, -0.15]))
            if 25 <= i < 40:
                forces.append(m.force_world - f_true)
    errs = np.array(errs)
    assert len(errs) >= 55
    assert 0 < np.sqrt(np.mean(errs[:, 0] ** 2)) < 1e-3  # measured: not exact, but close
    f_err = np.abs(np.array(forces))
    assert 0 < f_err.max() < 0.5
    assert sensing.contact.presses == 1


def test_hidden_markers_give_lost_and_no_pose():
    cfg = SensingConfig(camera=SimFrameConfig(occluded_markers=[0, 1]))
    s = ProbeSensing(cfg)
    m = measure(s, 0.0, _probe(0), np.zeros(3))
    assert m.status == "lost" and m.T_world_probe is None and m.tip_world is None


def test_the_frame_places_the_probe_with_its_camera_pose_or_not_at_all():
    """The camera's pose comes with each frame from the device (the headset moves); a frame
    without one places nothing (counted); a fixed camera uses its configured pose."""
    s = ProbeSensing()
    moved = Pose([0.15, 1.40, 0.17], quat_multiply(quat_from_axis_angle([0, 1, 0], 0.3), DOWN))
    for i, camera in enumerate((CAMERA, moved)):
        m = measure(s, i / 45.0, _probe(0), np.zeros(3), camera)
        assert m.status == "tracked" and m.T_world_rig is camera
        assert _probe(0).distance_to(m.T_world_probe)[0] < 3e-3
    assert measure(s, 0.1, _probe(0), np.zeros(3), None).status == "lost"
    assert s.no_camera_pose == 0 and s.source.no_pose == 1  # the sim head not placed: no frame
    fixed = ProbeSensing(SensingConfig(camera_anchor="fixed", camera_position_m=[0.1, 1.37, 0.2]))
    m = measure(fixed, 0.0, _probe(0), np.zeros(3))
    assert m.status == "tracked" and _probe(0).distance_to(m.T_world_probe)[0] < 3e-3


def test_one_tool_setting_drives_both_the_sim_camera_and_the_tracker(tmp_path):
    from humantele.config import ConfigError, validate_config
    from humantele.tracking.tool import load_tool

    other = tmp_path / "wide_probe.toml"  # a larger marker tree than the default probe
    other.write_text(
        "markers_mm = [[-40.0, 27.0, 3.0], [-35.0, -45.0, 4.0], [14.0, -47.0, -15.0], "
        "[62.0, 63.0, 4.0]]\n"
    )
    s = ProbeSensing(SensingConfig(), tool=str(other))
    assert s.source.tool is s.tool is s.tracker.tool  # drawn, tracked: the same tree
    assert np.abs(s.tool.markers - load_tool().markers).max() > 0.01
    assert measure(s, 0.0, _probe(0), np.zeros(3)).status == "tracked"
    # the old per-section settings are refused with where the one setting lives
    with pytest.raises(
        ConfigError,
        match=r"\[sensing\]: tool: no longer set here: .*\[follower\] tool",
    ):
        validate_config(SensingConfig, {"tool": "probe_default"}, "follower.toml [sensing]")
    with pytest.raises(ConfigError, match=r"camera\.sim\.tool: no longer set here"):
        validate_config(SensingConfig, {"camera": {"backend": "sim", "tool": "probe_default"}})

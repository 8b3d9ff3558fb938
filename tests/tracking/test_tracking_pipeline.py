import numpy as np
from scipy.spatial.transform import Rotation

from humantele.geometry import Pose, quat_from_axis_angle, quat_multiply
from humantele.tracking.filter import FilterConfig
from humantele.tracking.pipeline import PipelineConfig, Tracker
from humantele.tracking.sim import SimFrameConfig, SimFrameSource, default_sim_pose


def _random_poses(n, seed):
    """Poses a follower holds: 0.35-0.5 m away, handle towards the camera, tilted <= 30 deg."""
    rng = np.random.default_rng(seed)
    base = default_sim_pose()
    out = []
    for _ in range(n):
        tilt = quat_from_axis_angle(rng.normal(size=3), np.radians(rng.uniform(0, 30)))
        pos = [rng.uniform(-0.08, 0.08), rng.uniform(-0.08, 0.08), rng.uniform(0.35, 0.5)]
        out.append(Pose(pos, quat_multiply(tilt, base.quaternion)))
    return out


def _run(cfg: SimFrameConfig, poses, pipeline=None, filt=None):
    src = SimFrameSource(cfg)
    tr = Tracker(src.tool, pipeline, filt)
    errs, statuses = [], []
    for i, p in enumerate(poses):
        f = src.render(p, t=i / 45.0)
        r = tr.process(f)
        statuses.append(r.status)
        if r.T_camera_probe is not None:
            errs.append(p.distance_to(r.T_camera_probe))
    return np.array(errs).reshape(-1, 2), statuses


def test_accuracy_at_default_noise():
    errs, st = _run(SimFrameConfig(seed=11), _random_poses(60, 1))
    assert st.count("tracked") >= 57
    pos_rmse = np.sqrt(np.mean(errs[:, 0] ** 2))
    rot_rmse = np.degrees(np.sqrt(np.mean(errs[:, 1] ** 2)))
    # targets 0.5 mm / 0.5 deg; measured 0.19 mm / 0.24 deg on this run with the sphere-model
    # depth (0.72 mm / 0.37 deg with the old fixed surface offset)
    assert pos_rmse < 0.35e-3
    assert rot_rmse < 0.4


def test_previous_fixed_offset_depth_is_worse_than_the_sphere_model():
    poses = _random_poses(30, 1)
    new, _ = _run(SimFrameConfig(seed=11), poses)
    old, _ = _run(SimFrameConfig(seed=11), poses, PipelineConfig(depth="sphere"))
    assert np.sqrt(np.mean(new[:, 0] ** 2)) < 0.5 * np.sqrt(np.mean(old[:, 0] ** 2))


def test_one_marker_hidden_still_tracked_two_hidden_lost_never_wrong():
    poses = _random_poses(20, 2)
    for hidden in ([0], [1], [2], [3]):
        errs, st = _run(SimFrameConfig(seed=5, occluded_markers=hidden), poses)
        assert st.count("tracked") >= 18, hidden
        # three markers: a worse fit, but never a wrong one (measured <= 1.0 mm, 2.6 deg)
        assert errs[:, 0].max() < 2e-3 and np.degrees(errs[:, 1].max()) < 4.0
    errs, st = _run(SimFrameConfig(seed=5, occluded_markers=[0, 2], spurious_rate=3.0), poses)
    assert "tracked" not in st


def test_clutter_glints_and_partial_occlusion_never_give_a_wrong_pose():
    cfg = SimFrameConfig(seed=9, spurious_rate=8.0, clutter_patches=10, partial_occlusion_prob=0.3)
    errs, st = _run(cfg, _random_poses(60, 3))
    assert st.count("tracked") > 20
    # a sphere cut by a finger misfits the sphere model and is refused: the pose comes from
    # the other markers (measured <= 0.6 mm, 1.1 deg; the old pipeline let cut spheres in and
    # erred by up to ~2 mm and 8 deg)
    assert errs[:, 0].max() < 2e-3 and np.degrees(errs[:, 1].max()) < 3.0


def test_wrapped_depth_is_unwrapped_by_apparent_size_or_refused():
    cfg = SimFrameConfig(seed=2, depth_wrap_m=0.3, spurious_rate=0.0)
    poses = _random_poses(15, 4)
    errs, st = _run(cfg, poses, PipelineConfig(depth_wrap_m=0.3))
    assert st.count("tracked") >= 13 and errs[:, 0].max() < 2e-3
    errs, st = _run(cfg, poses, PipelineConfig(depth_wrap_m=0.3, unwrap=False))
    assert "tracked" not in st


def test_filter_smooths_a_still_probe_and_follows_a_steady_motion():
    still = [default_sim_pose()] * 60
    raw, _ = _run(SimFrameConfig(seed=1), still)
    filt, _ = _run(
        SimFrameConfig(seed=1), still, filt=FilterConfig(enabled=True, alpha=0.3, beta=0.03)
    )
    assert np.std(filt[20:, 1]) < np.std(raw[20:, 1])
    assert np.sqrt(np.mean(filt[20:, 1] ** 2)) < np.sqrt(np.mean(raw[20:, 1] ** 2))
    base = default_sim_pose()
    speed = 0.05  # m/s, along x
    moving = [
        Pose(base.position + [speed * i / 45.0 - 0.05, 0, 0], base.quaternion) for i in range(90)
    ]
    errs, _ = _run(
        SimFrameConfig(seed=1), moving, filt=FilterConfig(enabled=True, alpha=0.3, beta=0.03)
    )
    # an alpha-beta filter has no steady-state lag on a ramp: after settling, error ~ noise
    assert np.mean(errs[45:, 0]) < 1.0e-3


def test_filter_restarts_after_a_gap():
    from humantele.tracking.filter import PoseFilter

    f = PoseFilter(FilterConfig(enabled=True, alpha=0.2, beta=0.05))
    q = Rotation.identity().as_quat()
    f.update(0.0, Pose([0, 0, 0], q))
    f.update(0.02, Pose([0, 0, 0], q))
    jumped = f.update(1.0, Pose([1, 0, 0], q))
    np.testing.assert_allclose(jumped.position, [1, 0, 0])

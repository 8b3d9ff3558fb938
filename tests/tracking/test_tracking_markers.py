import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from humantele.geometry import Pose
from humantele.tracking.markers import MatchParams, estimate_pose, match_markers, refine_pose
from humantele.tracking.tool import load_tool

TOOL = load_tool()


def _pose(seed: int) -> Pose:
    rng = np.random.default_rng(seed)
    return Pose(
        rng.uniform([-0.1, -0.1, 0.3], [0.1, 0.1, 0.7]),
        Rotation.random(random_state=seed).as_quat(),
    )


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n_outliers=st.integers(0, 4),
    drop=st.sampled_from([None, 0, 1, 2, 3]),
    noise=st.sampled_from([0.0, 0.0003]),
)
def test_any_order_outliers_and_one_missing_give_the_right_pose_or_none(
    seed, n_outliers, drop, noise
):
    rng = np.random.default_rng(seed)
    T = _pose(seed)
    pts = T.apply(TOOL.markers) + rng.normal(0, noise, (4, 3))
    keep = [i for i in range(4) if i != drop]
    pts = pts[keep]
    outliers = T.position + rng.uniform(-0.12, 0.12, (n_outliers, 3))
    allp = np.vstack([pts, outliers])
    perm = rng.permutation(len(allp))
    est = estimate_pose(allp[perm], TOOL)
    if est is not None:  # never a wrong pose (3 noisy markers: a few degrees at most)
        dp, dr = T.distance_to(est.T_camera_probe)
        assert dp < 0.003 and np.degrees(dr) < 5.0
        for marker, idx in enumerate(est.matched):
            if idx >= 0:
                assert keep[perm[idx]] == marker if perm[idx] < len(keep) else False
    if n_outliers == 0:  # nothing to confuse it: must track
        assert est is not None and est.n_matched == len(keep)


def test_two_markers_left_is_lost():
    T = _pose(3)
    pts = T.apply(TOOL.markers)
    assert match_markers(pts[:2], TOOL).status == "lost"
    assert estimate_pose(np.vstack([pts[:2], T.position + [[0.05, 0.0, 0.0]]]), TOOL) is None


def test_large_residual_is_rejected():
    T = _pose(5)
    rng = np.random.default_rng(5)
    pts = T.apply(TOOL.markers) + rng.normal(0, 0.0007, (4, 3))
    res = match_markers(pts, TOOL)
    assert res.status == "tracked" and res.estimate.residual_m > 0.0005
    tight = MatchParams(max_rms=0.0002, max_marker_error=0.0004)
    assert match_markers(pts, TOOL, tight).status == "lost"
    assert estimate_pose(pts, TOOL, tight) is None


def test_two_copies_of_the_tool_are_ambiguous():
    a, b = _pose(7), _pose(8)
    b = Pose(a.position + [0.15, 0, 0], b.quaternion)
    pts = np.vstack([a.apply(TOOL.markers), b.apply(TOOL.markers)])
    res = match_markers(pts, TOOL)
    assert res.status == "ambiguous" and res.estimate is None


def test_non_finite_points_are_ignored():
    T = _pose(9)
    pts = np.vstack([T.apply(TOOL.markers), [[np.nan, 0, 0], [np.inf, 1, 1]]])
    est = estimate_pose(pts, TOOL)
    assert est is not None and T.distance_to(est.T_camera_probe)[0] < 1e-9


def test_refinement_trusts_bearing_over_range():
    rng = np.random.default_rng(0)
    e_k, e_r = [], []
    for i in range(40):
        T = _pose(100 + i)
        true = T.apply(TOOL.markers)
        d = true / np.linalg.norm(true, axis=1, keepdims=True)
        lat = rng.normal(0, 0.0001, (4, 3))
        lat -= np.sum(lat * d, axis=1, keepdims=True) * d
        pts = true + lat + d * rng.normal(0, 0.0006, (4, 1))
        est = estimate_pose(pts, TOOL)
        assert est is not None
        ref = refine_pose(est.T_camera_probe, TOOL.markers, pts, 0.0001, 0.0006)
        e_k.append(T.distance_to(est.T_camera_probe)[1])
        e_r.append(T.distance_to(ref)[1])
    assert np.sqrt(np.mean(np.square(e_r))) < 0.6 * np.sqrt(np.mean(np.square(e_k)))


def test_match_outcomes_use_the_one_tracking_status_vocabulary():
    from humantele.tracking.status import TrackingStatus
    from humantele.wire import TrackingStatus as WireTrackingStatus

    assert WireTrackingStatus is TrackingStatus  # one vocabulary from tracker to wire
    pts = TOOL.markers
    res = match_markers(pts, TOOL)
    assert res.status is TrackingStatus.TRACKED and res.status.has_pose
    lost = match_markers(pts[:2], TOOL).status
    assert lost is TrackingStatus.LOST and not lost.has_pose

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from fuzz_examples import examples
from humantele.geometry import Pose
from humantele.tracking.markers import MatchParams, estimate_pose, match_markers, refine_pose
from humantele.tracking.tool import kabsch, load_tool

TOOL = load_tool()


def _pose(seed: int) -> Pose:
    rng = np.random.default_rng(seed)
    return Pose(
        rng.uniform([-0.1, -0.1, 0.3], [0.1, 0.1, 0.7]),
        Rotation.random(random_state=seed).as_quat(),
    )


@settings(max_examples=examples(60), deadline=None)
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
    all_pts = T.apply(TOOL.markers)
    overlap = False
    if drop is not None:  # the dropped marker's image on another's: hidden, lost on purpose
        ray = all_pts[drop] / np.linalg.norm(all_pts[drop])
        across = np.linalg.norm(np.cross(np.delete(all_pts, drop, axis=0), ray), axis=1)
        overlap = bool(np.any(across < 2 * TOOL.sphere_radius))
    # A fit with a marker left out is kept only within MatchParams.max_rms_partial (three
    # noisy markers can exceed it: lost, on purpose); otherwise nothing confuses it: must track.
    too_noisy = (
        drop is not None and kabsch(TOOL.markers[keep], pts)[2] > MatchParams().max_rms_partial
    )
    if n_outliers == 0 and not overlap and not too_noisy:
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


@pytest.mark.parametrize("shape", [(2, 6), (12,), (3, 4), (4, 3, 1), ()])
def test_wrong_shapes_are_refused_with_a_clear_error(shape):
    pts = np.zeros(shape)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        estimate_pose(pts, TOOL)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        match_markers(pts, TOOL)
    with pytest.raises(ValueError, match="numbers"):
        estimate_pose([["a", "b", "c"]], TOOL)


def test_no_points_is_lost_and_nan_rows_are_counted():
    assert match_markers(np.zeros((0, 3)), TOOL).status == "lost"
    T = _pose(9)
    pts = np.vstack([[[np.nan, 0, 0]], T.apply(TOOL.markers), [[0, np.inf, 0]]])
    res = match_markers(pts, TOOL)
    assert res.status == "tracked" and res.n_nonfinite == 2
    assert res.estimate.matched == (1, 2, 3, 4)  # indices of the rows as given


def test_three_marker_fit_is_refused_when_the_fourth_was_seen_and_did_not_fit():
    T = _pose(4)
    pts = T.apply(TOOL.markers)
    assert estimate_pose(pts[:3], TOOL).n_matched == 3
    bad = pts.copy()
    bad[3] += 0.012 * pts[3] / np.linalg.norm(pts[3])  # its range 12 mm off: no 4-marker fit
    res = match_markers(bad, TOOL)
    assert res.status == "lost" and res.n_refuted >= 1


def test_explain_missing_refutes_two_markers_and_a_stray():
    T = _pose(11)
    pts = T.apply(TOOL.markers)
    # a stray placed where marker 2 lands when the tool turns 40 deg about the 0-1 axis
    axis = (pts[1] - pts[0]) / np.linalg.norm(pts[1] - pts[0])
    rot = Rotation.from_rotvec(np.radians(40.0) * axis)
    stray = rot.apply(pts[2] - pts[0]) + pts[0]
    three = np.vstack([pts[:2], stray])
    wrong = estimate_pose(three, TOOL)
    assert wrong is not None and np.degrees(T.distance_to(wrong.T_camera_probe)[1]) > 20
    seen: list[np.ndarray] = []

    def clear_view(centres):
        seen.append(centres)
        return np.zeros(len(centres), dtype=bool)

    res = match_markers(three, TOOL, explain_missing=clear_view)
    assert res.status == "lost" and res.n_refuted == 1
    np.testing.assert_allclose(seen[0], wrong.T_camera_probe.apply(TOOL.markers[3:]), atol=1e-9)
    hidden = match_markers(three, TOOL, explain_missing=lambda c: np.ones(len(c), bool))
    assert hidden.status == "tracked"


def _edge_on_pose(hidden: int = 1, front: int = 0) -> Pose:
    """A pose with marker ``hidden`` straight behind marker ``front`` on the camera's ray
    (camera at the origin looking along +z): the tool turned edge-on."""
    m = TOOL.markers
    p_front = np.array([0.02, -0.01, 0.4])
    rot, _ = Rotation.align_vectors([p_front / np.linalg.norm(p_front)], [m[hidden] - m[front]])
    return Pose(p_front - rot.apply(m[front]), rot.as_quat())


def test_a_marker_hidden_behind_another_with_nothing_else_in_view_is_tracked():
    T = _edge_on_pose()
    pts = T.apply(TOOL.markers)
    ray = pts[0] / np.linalg.norm(pts[0])
    assert np.linalg.norm(np.cross(pts[1], ray)) < 1e-9  # marker 1 is behind marker 0
    res = match_markers(pts[[0, 2, 3]], TOOL)
    assert res.status == "tracked" and res.estimate.n_matched == 3
    dp, dr = T.distance_to(res.estimate.T_camera_probe)
    assert dp < 1e-6 and dr < 1e-6


def test_a_marker_hidden_behind_another_with_a_stray_in_view_is_not_trusted():
    T = _edge_on_pose()
    pts = T.apply(TOOL.markers)
    stray = T.position + [0.0, 0.09, 0.02]  # a ring or a second tool's sphere, in view
    res = match_markers(np.vstack([pts[[0, 2, 3]], stray]), TOOL)
    assert res.status != "tracked"  # a stray may stand in for the hidden marker: lost

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from fuzz_examples import examples
from humantele.geometry import (
    Pose,
    matrix_to_quat,
    quat_from_axis_angle,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    quat_to_matrix,
    rotation_angle,
)

finite = st.floats(-1.0, 1.0, allow_nan=False)
quats = st.tuples(finite, finite, finite, finite).filter(lambda q: np.linalg.norm(q) > 0.1)
vecs = st.tuples(finite, finite, finite)


@settings(max_examples=examples(200), deadline=None)
@given(quats, vecs)
def test_rotation_matches_scipy(q, v):
    q = quat_normalize(q)
    r = Rotation.from_quat(q)  # scipy is scalar-last too
    np.testing.assert_allclose(quat_rotate(q, v), r.apply(v), atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(q), r.as_matrix(), atol=1e-12)


@settings(max_examples=examples(200), deadline=None)
@given(quats, quats)
def test_multiply_matches_scipy_composition(q1, q2):
    q1, q2 = quat_normalize(q1), quat_normalize(q2)
    expected = (Rotation.from_quat(q1) * Rotation.from_quat(q2)).as_matrix()
    np.testing.assert_allclose(quat_to_matrix(quat_multiply(q1, q2)), expected, atol=1e-12)


@settings(max_examples=examples(200), deadline=None)
@given(quats)
def test_matrix_roundtrip_and_sign(q):
    q = quat_normalize(q)
    back = matrix_to_quat(quat_to_matrix(q))
    assert back[3] >= 0
    # q and -q are one rotation; only at w == 0 are both signs canonical
    sign = 1.0 if abs(q[3]) > 1e-9 or np.dot(back, q) > 0 else -1.0
    np.testing.assert_allclose(back, sign * q, atol=1e-9)


@settings(max_examples=examples(200), deadline=None)
@given(quats, quats)
def test_rotation_angle_is_geodesic(q1, q2):
    q1, q2 = quat_normalize(q1), quat_normalize(q2)
    expected = (Rotation.from_quat(q1).inv() * Rotation.from_quat(q2)).magnitude()
    assert rotation_angle(q1, q2) == pytest.approx(expected, abs=1e-6)
    assert rotation_angle(q1, -q2) == pytest.approx(expected, abs=1e-6)


def test_frames_compose_and_invert():
    T_world_patient = Pose([1.0, 0.5, -0.2], quat_from_axis_angle([0, 1, 0], 0.7))
    T_patient_probe = Pose([0.1, 0.2, 0.0], quat_from_axis_angle([1, 0, 0], -0.3))
    T_world_probe = T_world_patient @ T_patient_probe
    p_probe = np.array([0.01, -0.02, 0.03])
    np.testing.assert_allclose(
        T_world_probe.apply(p_probe), T_world_patient.apply(T_patient_probe.apply(p_probe))
    )
    np.testing.assert_allclose(
        (T_world_probe @ T_world_probe.inverse()).as_matrix(), np.eye(4), atol=1e-12
    )
    np.testing.assert_allclose(
        Pose.from_matrix(T_world_probe.as_matrix()).as_matrix(),
        T_world_probe.as_matrix(),
        atol=1e-12,
    )


def test_bad_values_are_refused():
    with pytest.raises(ValueError):
        quat_normalize([0, 0, 0, 0])
    with pytest.raises(ValueError):
        quat_normalize([np.nan, 0, 0, 1])
    with pytest.raises(ValueError):
        Pose([np.inf, 0, 0], [0, 0, 0, 1])
    with pytest.raises(ValueError):
        quat_from_axis_angle([0, 0, 0], 1.0)


def test_distance_to():
    a = Pose([0, 0, 0], [0, 0, 0, 1])
    b = Pose([0.003, 0.004, 0], quat_from_axis_angle([0, 0, 1], np.deg2rad(10)))
    d, ang = a.distance_to(b)
    assert d == pytest.approx(0.005)
    assert np.rad2deg(ang) == pytest.approx(10.0)


@settings(max_examples=examples(100), deadline=None)
@given(quats, quats)
def test_tuple_product_matches_array_product(q1, q2):
    from humantele.geometry import quat_multiply_tuple

    q1, q2 = quat_normalize(q1), quat_normalize(q2)
    fast = quat_multiply_tuple(tuple(map(float, q1)), tuple(map(float, q2)))
    np.testing.assert_allclose(fast, quat_multiply(q1, q2), atol=1e-12)


@settings(max_examples=examples(200), deadline=None)
@given(quats, quats, vecs)
def test_single_vectors_match_the_batch_path(q1, q2, v):
    """The scalar fast paths (one quaternion, one vector) give what broadcasting gives."""
    q1n, q2n = quat_normalize(q1), quat_normalize(q2)
    np.testing.assert_allclose(q1n, quat_normalize(np.array([q1]))[0], atol=1e-15)
    np.testing.assert_allclose(quat_normalize(list(q1)), q1n, atol=0)
    np.testing.assert_allclose(
        quat_rotate(q1n, v), quat_rotate(q1n[None], np.array([v]))[0], atol=1e-15
    )
    np.testing.assert_allclose(
        quat_multiply(q1n, q2n), quat_multiply(q1n[None], q2n[None])[0], atol=1e-15
    )
    pose = Pose(np.array(v), q1n)
    np.testing.assert_allclose(pose.apply(v), Pose(np.array([v]), q1n).apply(np.array([v]))[0])


def test_rotation_angle_is_exact_near_zero():
    q = quat_from_axis_angle([0.2, 1.0, -0.3], 0.7)
    assert rotation_angle(q, q) < 1e-15
    for angle in (1e-12, 1e-9, 1e-6):
        dq = quat_from_axis_angle([1.0, 2.0, 3.0], angle)
        assert rotation_angle(q, quat_multiply(q, dq)) == pytest.approx(angle, rel=1e-6)


def test_a_pose_holds_a_copy_of_its_position():
    p = np.array([1.0, 2.0, 3.0])
    pose = Pose(p, [0, 0, 0, 1])
    p[0] = 9.0
    assert pose.position[0] == 1.0
    assert (
        pose.position.dtype == np.float64 and Pose([1, 2, 3], (0, 0, 0, 1)).position.dtype == float
    )

"""Alignment math: interpolation, clock fit, RMSE and centering, on hand-made inputs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from humantele.analysis.alignment import (
    AlignmentErrors,
    PoseTrack,
    alignment_errors,
    alignment_rmse,
    fit_clock_map,
)
from humantele.geometry import quat_from_axis_angle


def test_interpolation_is_linear_in_position_and_slerp_in_orientation():
    q0 = quat_from_axis_angle([0, 0, 1], 0.0)
    q1 = quat_from_axis_angle([0, 0, 1], 1.0)
    track = PoseTrack([0.0, 0.01], [[0, 0, 0], [1, 2, 3]], [q0, q1])
    pos, rot, valid = track.interpolate([0.0025, 0.005], max_gap_s=0.05)
    assert valid.all()
    np.testing.assert_allclose(pos, [[0.25, 0.5, 0.75], [0.5, 1.0, 1.5]])
    np.testing.assert_allclose(rot.as_rotvec(), [[0, 0, 0.25], [0, 0, 0.5]], atol=1e-12)


def test_no_extrapolation_and_no_interpolation_over_gaps():
    q = np.tile([0, 0, 0, 1.0], (4, 1))
    track = PoseTrack([0.0, 0.001, 0.5, 0.501], np.zeros((4, 3)), q)
    _, _, valid = track.interpolate([-0.001, 0.0005, 0.2, 0.5005, 0.6], max_gap_s=0.05)
    assert valid.tolist() == [False, True, False, True, False]


def test_unsorted_tracks_are_sorted():
    track = PoseTrack(
        [0.2, 0.0, 0.1], [[2, 0, 0], [0, 0, 0], [1, 0, 0]], np.tile([0, 0, 0, 1.0], (3, 1))
    )
    np.testing.assert_array_equal(track.t, [0.0, 0.1, 0.2])
    np.testing.assert_array_equal(track.position[:, 0], [0, 1, 2])


def test_clock_fit_recovers_offset_and_drift_and_ignores_slow_exchanges():
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 300.0, 1.0)
    true = 2.5 + 50e-6 * t
    rtt = 0.02 + np.abs(rng.normal(0, 0.002, len(t)))
    off = true + rng.normal(0, 0.0002, len(t))
    slow = rng.random(len(t)) < 0.3  # slow exchanges: large rtt, biased estimate
    rtt[slow] = 0.3
    off[slow] += 0.1
    m = fit_clock_map(t, off, rtt)
    assert m.source.endswith("linear fit")
    np.testing.assert_allclose(m.to_expert(t) - t, true, atol=3e-4)
    short = fit_clock_map([0.0, 1.0, 2.0], [1.0, 1.2, 1.1])
    assert short.drift == 0.0 and short.offset_s == pytest.approx(1.1)
    assert fit_clock_map([], []).n_estimates == 0


def test_rmse_and_centering_on_known_errors():
    ang = np.radians(5.0)
    # position errors +-1 mm around a 3 mm mean along x; rotation errors R_off * (+-2 deg about z)
    pos = np.array([[4e-3, 0, 0], [2e-3, 0, 0]] * 50)
    r_off = Rotation.from_rotvec([ang, 0, 0])
    wobble = Rotation.from_rotvec([[0, 0, np.radians(2)], [0, 0, -np.radians(2)]] * 50)
    errors = AlignmentErrors(np.arange(100.0), pos, r_off * wobble)
    r = alignment_rmse(errors)
    assert r.position_rmse_m == pytest.approx(np.sqrt((16 + 4) / 2) * 1e-3)
    assert r.centered_position_rmse_m == pytest.approx(1e-3)
    assert r.centered_orientation_rmse_rad == pytest.approx(np.radians(2), rel=1e-6)
    expected = (r_off * wobble).magnitude()
    assert r.orientation_rmse_rad == pytest.approx(np.sqrt(np.mean(expected**2)))
    assert r.mean_rotation_error_rad == pytest.approx(ang, rel=1e-6)


def test_orientation_error_is_the_relative_rotation_not_euler_differences():
    # Same Euler-angle difference, different real misalignment: a rotation about the probe's
    # own axis after a 90 deg tilt. The error must be the angle of R_v^-1 R_r.
    r_v = Rotation.from_euler("xyz", [0, 90, 0], degrees=True)
    r_r = r_v * Rotation.from_rotvec([0, 0, np.radians(10)])
    virtual = PoseTrack([0.0, 1.0], np.zeros((2, 3)), np.tile(r_v.as_quat(), (2, 1)))
    real = PoseTrack([0.5], np.zeros((1, 3)), r_r.as_quat()[None])
    e = alignment_errors(virtual, real, max_gap_s=2.0)
    assert e.rotation.magnitude()[0] == pytest.approx(np.radians(10))


def test_no_overlap_gives_nan_not_a_crash():
    virtual = PoseTrack([0.0, 0.001], np.zeros((2, 3)), np.tile([0, 0, 0, 1.0], (2, 1)))
    real = PoseTrack([5.0], np.zeros((1, 3)), np.array([[0, 0, 0, 1.0]]))
    r = alignment_rmse(alignment_errors(virtual, real))
    assert r.n == 0 and np.isnan(r.position_rmse_m)

"""The paper's radial method on the scalar servo path: root choice, exactness where it is exact."""

import math

import numpy as np
import pytest

from humantele.haptics.ellipsoid import Ellipsoid


def test_sphere_radial_depth_is_exact_inside_and_outside():
    e = Ellipsoid((0.3, 1.0, -0.2), (0.15, 0.15, 0.15), heading=0.7)
    rng = np.random.default_rng(1)
    for _ in range(200):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        r = rng.uniform(0.01, 0.3)
        p = e.center + r * direction
        d, n = e.penetration(p)
        assert d == pytest.approx(0.15 - r, abs=1e-12)
        np.testing.assert_allclose(n, direction, atol=1e-12)


def test_root_choice_inside_positive_near_side():
    # Torso: a point 10 mm under the top surface, off-centre laterally: depth must be the
    # near-side push-out distance along the outward normal (about 10 mm), not the far side.
    e = Ellipsoid((0.0, 0.12, 0.0), (10.0, 0.12, 0.17))
    p = (0.0, 0.12 + 0.11, 0.0)  # on the vertical axis: radial is exact there
    d, n = e.penetration(p)
    assert d == pytest.approx(0.01, abs=1e-12)
    assert n == pytest.approx((0.0, 1.0, 0.0), abs=1e-12)
    # off axis: still positive, the surface point along n is on the surface, and near side
    p = (0.0, 0.12 + 0.08, 0.09)
    d, n = e.penetration(p)
    assert 0.0 < d < 0.03
    surf = np.asarray(p) + d * np.asarray(n)
    local = surf - e.center
    assert np.sum((local / e.semi_axes) ** 2) == pytest.approx(1.0, abs=1e-12)
    # outside: negative, and moving by d along n lands on the near surface
    p = (0.0, 0.12 + 0.14, 0.05)
    d, n = e.penetration(p)
    assert d < 0.0
    surf = np.asarray(p) + d * np.asarray(n)
    assert np.sum(((surf - e.center) / e.semi_axes) ** 2) == pytest.approx(1.0, abs=1e-12)
    assert abs(d) < 0.03


def test_heading_rotates_normals_into_world():
    e0 = Ellipsoid((0.0, 0.0, 0.0), (10.0, 0.12, 0.17), heading=0.0)
    h = 0.9
    e1 = Ellipsoid((0.0, 0.0, 0.0), (10.0, 0.12, 0.17), heading=h)
    R = e1.rotation
    local = np.array([0.05, 0.06, 0.1])
    d0, n0 = e0.penetration(local)
    d1, n1 = e1.penetration(R @ local)
    assert d1 == pytest.approx(d0, abs=1e-14)
    np.testing.assert_allclose(n1, R @ np.asarray(n0), atol=1e-14)
    # patient +z in world is (sin h, 0, cos h)
    np.testing.assert_allclose(R @ [0, 0, 1], [math.sin(h), 0, math.cos(h)], atol=1e-15)

import math

import numpy as np
import pytest

from humantele.config import ConfigError, validate_config
from humantele.expert.mapping import MappingConfig, StylusMapping, default_registration
from humantele.geometry import Pose, quat_from_axis_angle, rotation_angle

Q0 = (0.0, 0.0, 0.0, 1.0)
TOP = np.array([0.0, 0.11, 0.0])  # top of the model, patient frame


def mapping(**kw):
    cfg = MappingConfig(**kw)
    return StylusMapping(cfg, default_registration(cfg, TOP))


def test_default_is_one_to_one_over_the_model():
    m = mapping()
    p = m.update((0.0, 0.0, 0.0), Q0, 0)
    assert np.allclose(p.position, TOP + [0, 0.03, 0])
    p2 = m.update((0.01, -0.02, 0.005), Q0, 0)
    assert np.allclose(p2.position - p.position, [0.01, -0.02, 0.005])
    # Stylus at rest holds the probe beam (+z of the tip frame) pointing down.
    assert np.allclose(p.rotate([0, 0, 1]), [0, -1, 0], atol=1e-12)


def test_scaling_and_yaw():
    m = mapping(scale=2.0, device_yaw_deg=90.0)
    a = m.update((0.0, 0.0, 0.0), Q0, 0).position
    b = m.update((0.01, 0.0, 0.0), Q0, 0).position
    assert np.allclose(b - a, [0.0, 0.0, -0.02], atol=1e-12)  # device x -> patient -z, doubled
    reg = m.registration
    assert np.allclose(
        reg.point_to_device(reg.point_to_patient([0.01, 0.02, 0.03])), [0.01, 0.02, 0.03]
    )
    assert np.allclose(reg.vector_to_device([0.0, 0.0, -1.0]), [1.0, 0.0, 0.0], atol=1e-12)


def test_clutch_reindexes_without_moving_the_probe():
    m = mapping()
    clutch = 1 << m.config.clutch_button
    before = m.update((0.02, 0.0, 0.0), Q0, 0)
    # Hold the clutch and move the stylus back: the virtual probe does not move.
    for x in np.linspace(0.02, -0.05, 20):
        held = m.update((x, 0.01, 0.0), Q0, clutch)
        assert held.distance_to(before)[0] == 0.0
    assert not m.take_changed()
    # Release: the probe continues from where it stayed, then follows the stylus again 1:1.
    after = m.update((-0.05, 0.01, 0.0), Q0, 0)
    assert after.distance_to(before)[0] < 1e-12
    assert m.take_changed() and not m.take_changed() and m.reindex_count == 1
    moved = m.update((-0.04, 0.01, 0.0), Q0, 0)
    assert np.allclose(moved.position - after.position, [0.01, 0, 0])
    # The servo loop's registration agrees with the published pose.
    assert np.allclose(m.registration.point_to_patient((-0.04, 0.01, 0.0)), moved.position)


def test_orientation_follows_the_stylus():
    m = mapping()
    q = quat_from_axis_angle([0, 0, 1], math.radians(15))
    rest = m.update((0, 0, 0), Q0, 0)
    tilted = m.update((0, 0, 0), q, 0)
    assert rotation_angle(rest.quaternion, tilted.quaternion) == pytest.approx(math.radians(15))
    assert isinstance(tilted, Pose)


def test_bad_config_names_field():
    with pytest.raises(ConfigError, match="scale"):
        validate_config(MappingConfig, {"scale": 0.0})
    with pytest.raises(ConfigError, match="clutch_button"):
        validate_config(MappingConfig, {"clutch_button": 9})

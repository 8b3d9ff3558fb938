"""The expert daemon's handlers, in process: model install, pose publishing, clutch."""

import math

import numpy as np

from daemon_doubles import Clock, LinkDouble, ServoDouble
from humantele.expert.daemon import ExpertConfig, ExpertDaemon
from humantele.geometry import Pose
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.wire import EllipsoidModel, EllipsoidParams


def make():
    d = ExpertDaemon(ExpertConfig())
    d.servo, d.link, d.clock = ServoDouble(), LinkDouble(), Clock()
    return d


def publish(d, t):
    d.clock.t = t
    d.publish_pose(t)


def model_msg(b=0.11, a=0.15):
    e = Ellipsoid((0.0, 0.0, 0.0), (10.0, b, a), 0.0)
    return EllipsoidModel(model=EllipsoidParams(**e.to_dict()))


def test_model_installed_once_and_workspace_over_it():
    d = make()
    d.on_control(model_msg())
    d.on_control(model_msg())  # the follower rejoined and sent the same model
    assert d.models_installed == 1 and len(d.servo.models) == 1
    publish(d, t=1.0)
    pose = d.link.poses[-1]
    # Device origin 3 cm above the top of the model; the probe beam points down.
    assert np.allclose(pose.position, [0.0, 0.11 + 0.03, 0.0])
    assert np.allclose(Pose(pose.position, pose.quaternion).rotate([0, 0, 1]), [0, -1, 0])
    d.on_control(model_msg(b=0.12))
    assert d.models_installed == 2


def test_clutch_holds_the_probe_and_the_force_then_reindexes():
    d = make()
    d.on_control(model_msg())
    d.servo.p_device = np.array([0.02, 0.0, 0.0])
    publish(d, t=1.0)
    held = d.link.poses[-1].position
    d.servo.buttons = 1 << d.config.mapping.clutch_button
    for i, x in enumerate(np.linspace(0.02, -0.05, 10)):
        d.servo.p_device = np.array([x, 0.0, 0.0])
        publish(d, t=1.1 + i * 0.01)
        assert d.link.poses[-1].clutch and np.allclose(d.link.poses[-1].position, held)
    assert d.servo.model is None  # no force while the stylus moves freely
    d.servo.buttons = 0
    publish(d, t=2.0)
    assert d.servo.model is not None and d.mapping.reindex_count == 1
    d.servo.p_device = np.array([-0.04, 0.0, 0.0])
    publish(d, t=2.1)  # after the servo took the new registration
    assert np.allclose(d.link.poses[-1].position, np.array(held) + [0.01, 0, 0])
    assert not math.isnan(d.link.poses[-1].position[0])


def test_no_pose_without_link_or_new_sample():
    d = make()
    d.link.connected = False
    publish(d, t=1.0)
    assert d.link.poses == []

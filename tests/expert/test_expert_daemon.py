"""The expert daemon's handlers, in process: model install, pose publishing, clutch."""

import math

import numpy as np

from daemon_doubles import Clock, LinkDouble, ServoDouble
from humantele.expert.config import ExpertConfig
from humantele.expert.daemon import ExpertDaemon
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


def test_the_follower_s_scanner_scale_reaches_the_console_s_frames_unless_configured():
    """Calipers and the depth scale on a real scanner's picture: the follower's scale, kept
    for a console started later; ``[expert.console]`` values win."""
    from types import SimpleNamespace

    from humantele.wire import UsScale

    msg = UsScale(pixel_spacing_mm=(0.2, 0.25), depth_origin_row=96.0)
    d = make()
    d.on_control(msg)  # before the console: kept
    frames = SimpleNamespace(us_spacing_mm=None, us_depth_origin_row=None)
    d.apply_us_scale(frames)  # what start_console does with the console's frames
    assert (frames.us_spacing_mm, frames.us_depth_origin_row) == ((0.2, 0.25), 96.0)
    d.console = SimpleNamespace(frames=SimpleNamespace(us_spacing_mm=None, us_depth_origin_row=0))
    d.on_control(UsScale(pixel_spacing_mm=(0.3, 0.3), depth_origin_row=10.0))
    assert d.console.frames.us_spacing_mm == (0.3, 0.3)  # a console already open takes it
    configured = ExpertDaemon(ExpertConfig(console={"us_pixel_spacing_mm": [0.1, 0.1]}))
    configured.on_control(msg)
    assert configured.us_scale is None  # the configuration wins

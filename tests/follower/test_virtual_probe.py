"""The follower's virtual probe and what it sends the expert, apart from the daemon
(follower/virtual_probe.py, follower/to_expert.py): poses placed through the calibration,
stale when old or the link is down, the renderers' probe with its device time; nothing to the
expert before a calibration or while disconnected, the state in the patient frame."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from daemon_doubles import LinkDouble
from humantele.follower.sensing import Measurement
from humantele.follower.to_expert import ExpertStream
from humantele.follower.virtual_probe import VirtualProbe
from humantele.geometry import Pose
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.media.config import FollowerVideoConfig
from humantele.tracking.status import TrackingStatus
from humantele.wire import EllipsoidModel, PoseMessage

T_WORLD_PATIENT = Pose([1.0, 0.8, 0.0], [0.0, 0.0, 0.0, 1.0])  # the patient 1 m along x


class Feed:
    def __init__(self) -> None:
        self.sent: list[tuple[str, dict, float | None]] = []

    def publish(self, kind: str, fields: dict, t_origin: float | None = None) -> None:
        self.sent.append((kind, fields, t_origin))


def calibration():
    model = Ellipsoid((0.0, 0.0, 0.0), (0.3, 0.1, 0.15), 0.0)  # patient frame
    return SimpleNamespace(T_world_patient=T_WORLD_PATIENT, model_patient=lambda: model)


def measured(device_time_s=None) -> Measurement:
    tip = Pose([1.0, 0.9, 0.0], [0.0, 0.0, 0.0, 1.0])
    return Measurement(TrackingStatus.TRACKED, tip, np.array([0.0, -3.0, 0.0]), True,
                       device_time_s=device_time_s)  # fmt: skip


def test_the_virtual_probe_is_placed_through_the_calibration_and_goes_stale():
    link, feed, cal = LinkDouble(age_s=0.02), Feed(), [None]
    v = VirtualProbe(0.3, feed, lambda: link, lambda: cal[0])
    msg = PoseMessage.from_pose(1, 0.0, Pose([0.0, 0.1, 0.0], [0.0, 0.0, 0.0, 1.0]), 0)
    v.on_pose(msg)
    assert v.world() is None and feed.sent == []  # not calibrated: nothing drawn
    assert v.figures.received == 1
    cal[0] = calibration()
    v.on_pose(msg)
    kind, fields, origin = feed.sent[-1]
    assert kind == "virtual_probe" and origin == v.rx
    assert np.allclose(fields["position"], [1.0, 0.9, 0.0])  # T_world_patient @ the pose
    assert fields["age_ms"] == pytest.approx(20.0) and fields["stale"] is False
    assert not v.stale(v.rx + 0.2) and v.stale(v.rx + 0.4)
    link.connected = False
    assert v.stale(v.rx)


def test_the_renderers_probe_carries_the_tracker_frame_s_device_time():
    link, feed = LinkDouble(), Feed()
    v = VirtualProbe(0.3, feed, lambda: link, calibration)
    v.publish_tick(0.0, measured(device_time_s=123.5))
    kind, fields, _ = feed.sent[-1]
    assert kind == "probe" and fields["device_time_s"] == 123.5 and fields["contact"]
    assert fields["tracking"] == "tracked"
    v.publish_tick(0.0, measured())
    assert "device_time_s" not in feed.sent[-1][1]


def test_the_expert_gets_nothing_before_a_calibration_or_while_disconnected():
    link, cal = LinkDouble(), [None]
    out = ExpertStream(lambda: link, lambda: cal[0], FollowerVideoConfig())
    assert out.model() is False and link.controls == []
    out.state(1.0, measured())
    assert link.states == []
    cal[0] = calibration()
    link.connected = False
    assert out.model() is False
    out.state(1.0, measured())
    assert link.states == [] and out.state_seq == 0
    link.connected = True
    assert out.model() is True and isinstance(link.controls[-1], EllipsoidModel)
    assert link.controls[-1].model.semi_axes == (0.3, 0.1, 0.15)
    out.state(1.0, measured())
    st = link.states[-1]
    assert st.seq == 1 and np.allclose(st.position, [0.0, 0.1, 0.0])  # patient frame
    assert np.allclose(st.force, [0.0, -3.0, 0.0]) and st.contact  # tip frame (same here)
    assert out.us_scale() is False  # a sim US source: no scanner scale to send

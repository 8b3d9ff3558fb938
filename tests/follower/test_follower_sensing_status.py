"""The follower's Sensing passes the tracker's status on in the one vocabulary."""

from types import SimpleNamespace

import numpy as np

from humantele.follower.daemon import FollowerConfig
from humantele.follower.sensing import Sensing
from humantele.follower.sim_world import WorldTruth
from humantele.geometry import Pose
from humantele.tracking.status import TrackingStatus


class FakePipeline:
    def __init__(self, status, pose):
        self.status, self.pose = status, pose

    def measure(self, t, world):
        return SimpleNamespace(status=self.status, T_world_probe=self.pose, force_world=np.zeros(3),
                               force_probe=np.zeros(3), contact=False)  # fmt: skip


def test_ambiguous_frames_reach_the_daemon_as_ambiguous_without_a_pose():
    s = Sensing(FollowerConfig(probe_source="truth"))
    tip = Pose([0.0, 0.9, 0.0], [0.0, 0.0, 0.0, 1.0])

    def truth(t):
        return WorldTruth(t, tip, np.zeros(3), None)

    s.pipeline = FakePipeline("ambiguous", None)
    m = s.measure(0.0, truth(0.0))
    assert m.status is TrackingStatus.AMBIGUOUS and m.T_world_tip is None
    s.pipeline = FakePipeline(TrackingStatus.TRACKED, tip @ s.T_tip_probe)
    m = s.measure(0.1, truth(0.1))
    assert m.status is TrackingStatus.TRACKED
    np.testing.assert_allclose(m.T_world_tip.position, tip.position, atol=1e-12)
    s.pipeline = FakePipeline(TrackingStatus.TRACKED, None)  # a status without its pose: lost
    assert s.measure(0.2, truth(0.2)).status is TrackingStatus.LOST
    s.pipeline = FakePipeline("searching", None)  # not a status: a sensing error, reported lost
    assert s.measure(0.3, truth(0.3)).status is TrackingStatus.LOST

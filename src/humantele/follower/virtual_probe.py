"""The expert's virtual probe at the follower: the last pose that came (``T_patient_probe``,
tip frame) and when (s, ``time.monotonic()``), the stream's figures, where it is in the
tracker's world (through the calibration's ``T_world_patient``), whether it is stale, and what
the renderers get of it and of the measured probe (:mod:`humantele.follower.feed`, world
frame)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from humantele.follower.figures import PoseStreamFigures
from humantele.geometry import Pose
from humantele.wire import PoseMessage

if TYPE_CHECKING:
    from humantele.follower.calibration import Calibration
    from humantele.follower.feed import RendererFeed
    from humantele.follower.sensing import Measurement


class VirtualProbe:
    """``link()`` and ``calibration()`` are looked up at each use (the daemon's may be
    replaced); a pose is stale ``stale_after_s`` after it came, or while the link is down."""

    def __init__(
        self,
        stale_after_s: float,
        feed: RendererFeed,
        link: Callable[[], Any],
        calibration: Callable[[], Calibration | None],
    ) -> None:
        self.stale_after_s = stale_after_s
        self.feed = feed
        self.link = link
        self.calibration = calibration
        self.last: PoseMessage | None = None
        self.rx = -math.inf  # when the last pose came (s, monotonic)
        self.figures = PoseStreamFigures()

    def on_pose(self, msg: PoseMessage) -> None:
        """A pose from the expert: counted, and published at once."""
        self.last = msg
        self.rx = time.monotonic()
        self.figures.add(self.rx, self.link().age_of(msg.t_sent))
        self.publish(self.rx)

    def stale(self, t: float) -> bool:
        return not self.link().connected or t - self.rx > self.stale_after_s

    def world(self) -> Pose | None:
        """The virtual probe's tip pose in the world, or None without a pose or calibration."""
        cal = self.calibration()
        if self.last is None or cal is None:
            return None
        return cal.T_world_patient @ self.last.pose

    def publish(self, t: float) -> None:
        """The virtual probe (world frame) to renderers, once calibrated: as each pose arrives
        (so the page sees it at once), and at each tick while it is stale (``t``: the time it
        is judged at, s)."""
        virtual = self.world()
        if virtual is None or self.last is None:
            return
        age = self.link().age_of(self.last.t_sent)
        self.feed.publish(
            "virtual_probe",
            {
                "position": virtual.position,
                "quaternion": virtual.quaternion,
                "age_ms": None if age is None else age * 1000.0,
                "stale": self.stale(t),
                "clutch": bool(self.last.clutch),
            },
            t_origin=self.rx,
        )

    def publish_tick(self, t: float, m: Measurement) -> None:
        """At each tick: the virtual probe if it went stale, and the measured probe ``m``."""
        if self.stale(t):
            self.publish(t)
        if m.T_world_tip is not None:
            probe = {
                "position": m.T_world_tip.position,
                "quaternion": m.T_world_tip.quaternion,
                "force": m.force_world,
                "contact": m.contact,
                "tracking": m.status.name.lower(),
            }
            if m.device_time_s is not None:
                probe["device_time_s"] = m.device_time_s
            self.feed.publish("probe", probe)

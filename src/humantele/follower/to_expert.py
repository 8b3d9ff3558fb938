"""What the follower sends the expert: control messages while connected (the expert learns
the rest on Hello), the patient model (patient frame), a real scanner's US scale, and the
measured probe state (pose in the patient frame, force in the probe's tip frame)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from humantele.wire import (
    ControlMessage,
    EllipsoidModel,
    EllipsoidParams,
    StateMessage,
    UsScale,
)

if TYPE_CHECKING:
    from humantele.follower.calibration import Calibration
    from humantele.follower.sensing import Measurement
    from humantele.media.config import FollowerVideoConfig


class ExpertStream:
    """``link()`` and ``calibration()`` are looked up at each send (the daemon's may be
    replaced); ``video``: ``[follower.video]`` (the US source's scale)."""

    def __init__(
        self,
        link: Callable[[], Any],
        calibration: Callable[[], Calibration | None],
        video: FollowerVideoConfig,
    ) -> None:
        self.link = link
        self.calibration = calibration
        self.video = video
        self.state_seq = 0

    def control(self, msg: ControlMessage) -> bool:
        """A control message, only while connected."""
        link = self.link()
        return link.connected and link.send_control(msg)

    def model(self) -> bool:
        """The calibration's patient model (nothing before a calibration)."""
        cal = self.calibration()
        if cal is None:
            return False
        return self.control(EllipsoidModel(model=EllipsoidParams(**cal.model_patient().to_dict())))

    def us_scale(self) -> bool:
        """A real scanner's configured scale, for the expert's calipers and depth scale."""
        us = self.video.us
        spacing, row0 = getattr(us, "pixel_spacing_mm", None), getattr(us, "depth_origin_row", None)
        if not self.video.enabled or spacing is None or row0 is None:
            return False
        return self.control(UsScale(pixel_spacing_mm=tuple(spacing), depth_origin_row=row0))

    def state(self, t: float, m: Measurement) -> None:
        """The measured probe (patient frame) and force (probe tip frame) at ``t``."""
        cal, link = self.calibration(), self.link()
        if cal is None or m.T_world_tip is None or not link.connected:
            return
        T_patient_tip = cal.T_world_patient.inverse() @ m.T_world_tip
        force_tip = m.T_world_tip.inverse().rotate(m.force_world)
        self.state_seq += 1
        link.send_state(
            StateMessage(
                self.state_seq,
                t,
                tuple(T_patient_tip.position),
                tuple(T_patient_tip.quaternion),
                m.status,
                tuple(float(v) for v in force_tip),
                m.contact,
            )
        )

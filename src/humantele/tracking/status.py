"""The one tracking-status vocabulary: what is known of the probe's pose in a frame.

Used by the tracker (:mod:`humantele.tracking.markers`, :mod:`humantele.tracking.pipeline`),
the follower's sensing and daemon, the state message on the wire (:mod:`humantele.wire`, as a
one-byte code) and the headset feed (as the lower-case string).
"""

from __future__ import annotations

from enum import StrEnum


class TrackingStatus(StrEnum):
    """``tracked``: a pose was measured in this frame; ``lost``: no pose (too few markers
    seen, or no fit); ``ambiguous``: markers seen, but more than one fit places the tool
    differently, so no pose is given; ``predicted``: a short gap bridged by prediction (a
    pose is given, not measured). Members compare equal to their strings."""

    LOST = "lost"
    TRACKED = "tracked"
    PREDICTED = "predicted"
    AMBIGUOUS = "ambiguous"

    @property
    def has_pose(self) -> bool:
        """True when a pose comes with this status (tracked or predicted)."""
        return self in (TrackingStatus.TRACKED, TrackingStatus.PREDICTED)

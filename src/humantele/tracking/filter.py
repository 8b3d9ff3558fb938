"""Temporal filter of tracked poses: an alpha-beta (constant velocity) filter on position and
on orientation (rotation vectors), so a steady motion is followed without lag while noise is
smoothed. Frames: the poses' own (e.g. T_camera_probe); times in s.

Smaller ``alpha``/``beta`` smooth more and respond more slowly; ``humantele bench tracking``
reports the noise and lag it gives. A gap longer than ``reset_after_s`` restarts the filter.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from humantele.config import ConfigModel
from humantele.geometry import Pose


class FilterConfig(ConfigModel):
    """Alpha-beta gains (per frame, 0 < beta <= alpha <= 1) and the restart gap (s)."""

    enabled: bool = False
    alpha: float = Field(0.5, gt=0, le=1)
    beta: float = Field(0.1, ge=0, le=1)
    reset_after_s: float = Field(0.2, gt=0)


class PoseFilter:
    """Alpha-beta filter of a pose stream; ``update`` returns the filtered pose."""

    def __init__(self, config: FilterConfig | None = None):
        # scipy.spatial imported here, not with the module: the filter is off by default, and
        # the import took 0.2 s of every sensing process's start
        from scipy.spatial.transform import Rotation

        self._Rotation = Rotation
        self.config = config or FilterConfig()
        self.reset()

    def reset(self) -> None:
        self._t: float | None = None
        self._x = np.zeros(3)
        self._v = np.zeros(3)
        self._r = self._Rotation.identity()
        self._w = np.zeros(3)

    def update(self, t: float, pose: Pose) -> Pose:
        """Filter the measurement ``pose`` taken at time ``t`` (s)."""
        c, Rotation = self.config, self._Rotation
        dt = None if self._t is None else t - self._t
        if dt is None or dt <= 0 or dt > c.reset_after_s:
            self._t = t
            self._x = pose.position.copy()
            self._v[:] = 0.0
            self._r = Rotation.from_quat(pose.quaternion)
            self._w[:] = 0.0
            return pose
        self._t = t
        x_pred = self._x + self._v * dt
        res = pose.position - x_pred
        self._x = x_pred + c.alpha * res
        self._v = self._v + (c.beta / dt) * res
        r_pred = Rotation.from_rotvec(self._w * dt) * self._r
        e = (Rotation.from_quat(pose.quaternion) * r_pred.inv()).as_rotvec()
        self._r = Rotation.from_rotvec(c.alpha * e) * r_pred
        self._w = self._w + (c.beta / dt) * e
        return Pose(self._x.copy(), self._r.as_quat())

"""Pinhole camera intrinsics of the IR/depth sensor.

Camera frame (OpenCV convention): x right, y down, z forward along the optical axis; pixel
(u, v) = (column, row) with integer values at pixel centres. Depth images hold the *range*
along each pixel's ray (as the HoloLens 2 AHAT stream does), in millimetres, 0 = invalid.
The AHAT lens is a wide-angle one; we model it already undistorted (a pinhole).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from humantele.config import ConfigModel


class CameraIntrinsics(ConfigModel):
    """Image size (px) and pinhole parameters (px). Defaults: AHAT-like 512 x 512, ~104 deg."""

    width: int = Field(512, ge=8, le=8192)
    height: int = Field(512, ge=8, le=8192)
    fx: float = Field(200.0, gt=0)
    fy: float = Field(200.0, gt=0)
    cx: float = 255.5
    cy: float = 255.5

    def project(self, points_camera: ArrayLike) -> NDArray[np.float64]:
        """Pixel (u, v) of camera-frame point(s) (..., 3), m; z must be > 0."""
        p = np.asarray(points_camera, dtype=float)
        z = p[..., 2]
        return np.stack([self.fx * p[..., 0] / z + self.cx, self.fy * p[..., 1] / z + self.cy], -1)

    def rays(self, u: ArrayLike, v: ArrayLike) -> NDArray[np.float64]:
        """Unit ray directions (..., 3) in the camera frame through pixel(s) (u, v)."""
        u, v = np.broadcast_arrays(np.asarray(u, dtype=float), np.asarray(v, dtype=float))
        d = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], -1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

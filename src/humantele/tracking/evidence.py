"""Negative evidence from the depth image: would a marker a fit leaves unmatched be seen?

A three-marker fit from two real markers and a stray sphere puts the fourth marker where
nothing is. A real fourth marker that is not matched is hidden (a finger, the hand, another
marker in front: something *nearer* than it along its ray) or imaged but refused by the
detector (partly covered, merged with a glint: depth at its own surface). Either way the
depth image at its place reads no farther than the marker's front surface. If instead it
reads the background behind (the ray passes through where the marker would be), the marker
would have been seen: the fit is refuted.

:class:`FreeSpaceCheck` does this per frame; the matcher calls it with the fitted places of
the unmatched markers (:data:`humantele.tracking.markers.ExplainMissing`). A place outside
the image, nearer than the camera's minimum range, or with too few valid depth pixels cannot
be checked and counts as not explained: lost rather than wrong. Units: m, px.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from humantele.tracking.camera import CameraIntrinsics


class FreeSpaceCheck:
    """Explains unmatched markers from one depth frame (``depth_mm``: range along the ray,
    mm, 0 = invalid). ``margin_m``: how much farther than the marker's front surface the
    depth may read before the ray is called clear; ``min_valid``: share of the marker's
    disc pixels that must have a depth; ``wrap_m``: the sensor's range wrap."""

    def __init__(
        self,
        depth_mm: NDArray,
        intrinsics: CameraIntrinsics,
        radius: float,
        margin_m: float = 0.01,
        min_valid: float = 0.3,
        wrap_m: float = 1.055,
        min_range_m: float = 0.1,
    ):
        self.depth_mm = depth_mm
        self.k = intrinsics
        self.radius = radius
        self.margin = margin_m
        self.min_valid = min_valid
        self.wrap = wrap_m
        self.min_range = min_range_m
        self.checked = 0  # markers looked at
        self.clear = 0  # ... whose ray was clear: the fit was refuted by them

    def __call__(self, centres: NDArray[np.float64]) -> NDArray[np.bool_]:
        """(K,) True where the marker at ``centres`` (K, 3), camera frame, could be unseen."""
        out = np.zeros(len(centres), dtype=bool)
        k, h, w = self.k, *self.depth_mm.shape
        for i, c in enumerate(np.asarray(centres, dtype=float)):
            self.checked += 1
            dist = float(np.linalg.norm(c))
            if c[2] < self.min_range:
                continue
            u, v = k.project(c)
            r_px = max(0.7 * k.fx * self.radius / c[2], 1.0)
            if not (r_px <= u <= w - 1 - r_px and r_px <= v <= h - 1 - r_px):
                continue  # outside the image: cannot say
            x0, x1 = int(np.floor(u - r_px)), int(np.ceil(u + r_px)) + 1
            y0, y1 = int(np.floor(v - r_px)), int(np.ceil(v + r_px)) + 1
            yy, xx = np.mgrid[y0:y1, x0:x1]
            disc = (xx - u) ** 2 + (yy - v) ** 2 <= r_px * r_px
            d = self.depth_mm[y0:y1, x0:x1][disc].astype(float) / 1000.0
            valid = d[d > 0]
            if valid.size == 0 or valid.size < self.min_valid * disc.sum():
                continue  # no depth there: cannot say
            front = dist - self.radius
            m = valid + self.wrap * np.round((front - valid) / self.wrap)  # nearest unwrap
            if float(np.median(m)) <= front + self.margin:
                out[i] = True  # something at or in front of the marker
            else:
                self.clear += 1
        return out

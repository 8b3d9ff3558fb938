"""Where a world point lands in a page's screenshot, and whether two screenshots differ there
(host side, numpy + OpenCV)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from humantele.geometry import Pose

DIFF_LEVEL = 40  # levels (0-255) a pixel's colour must change by, in one channel at least
GHOST_LEVEL = 8  # the ghost is see-through: it changes what is behind it less
OUTLINE_LEVEL = 20  # the outline: thin, antialiased lines


def matrix(elements: list[float]) -> NDArray[np.float64]:
    """A three.js Matrix4 from its column-major ``elements``."""
    return np.asarray(elements, dtype=float).reshape(4, 4).T


def project(camera: dict, point_world) -> tuple[float, float]:
    """Pixel (x right, y down, CSS px) of a world point (m) through the page's camera (the
    ``headset.camera()`` object: projection and view matrices, canvas size)."""
    clip = matrix(camera["projection"]) @ matrix(camera["view"]) @ np.append(point_world, 1.0)
    ndc = clip[:3] / clip[3]
    return (ndc[0] + 1.0) / 2.0 * camera["width"], (1.0 - ndc[1]) / 2.0 * camera["height"]


def handle_point(pose_obj: dict, up_m: float) -> NDArray[np.float64]:
    """A point ``up_m`` up the handle of a transducer at a feed pose (tip frame: the beam is
    +z, so the handle is along -z)."""
    pose = Pose(pose_obj["position"], pose_obj["quaternion"])
    return pose.apply([0.0, 0.0, -up_m])


def changed(shot_a: Path, shot_b: Path, level: int = DIFF_LEVEL) -> NDArray[np.bool_]:
    """Pixels that differ by more than ``level`` between two screenshots (a boolean image)."""
    a = cv2.imread(str(shot_a), cv2.IMREAD_COLOR).astype(int)
    b = cv2.imread(str(shot_b), cv2.IMREAD_COLOR).astype(int)
    assert a.shape == b.shape
    return np.abs(a - b).max(axis=2) > level


def changed_near(mask: NDArray[np.bool_], xy: tuple[float, float], radius: int = 6) -> float:
    """Fraction of changed pixels in a square of ``radius`` around ``xy``."""
    x, y = round(xy[0]), round(xy[1])
    h, w = mask.shape
    window = mask[
        max(0, y - radius) : min(h, y + radius + 1), max(0, x - radius) : min(w, x + radius + 1)
    ]
    return float(window.mean()) if window.size else 0.0

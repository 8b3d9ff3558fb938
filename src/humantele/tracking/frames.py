"""Frames from the IR/depth sensor and the interface every frame source implements.

A :class:`TrackingFrame` is what the HoloLens 2 AHAT stream delivers: an active-brightness
(IR) image and a depth image (range along the ray, mm, 0 = invalid, wrapping beyond ~1 m),
with the intrinsics and a timestamp. Backends (``sim``, ``opencv``; a HoloLens 2 stream
client can be another) are picked by configuration in :mod:`humantele.tracking.sources`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from humantele.geometry import Pose
from humantele.tracking.camera import CameraIntrinsics


class FrameSourceUnavailable(RuntimeError):
    """The configured camera cannot be opened; the message says which and what to do."""


@dataclass
class TrackingFrame:
    """One sensor frame.

    ``ir``: (H, W) uint16 active brightness (counts). ``depth_mm``: (H, W) uint16 range along
    each pixel's ray in mm (0 = invalid), or None when the camera has no depth. ``t``: capture
    time, s. ``T_camera_probe_true``: ground truth (simulated frames only).
    """

    t: float
    ir: NDArray[np.uint16]
    depth_mm: NDArray[np.uint16] | None
    intrinsics: CameraIntrinsics
    seq: int = 0
    T_camera_probe_true: Pose | None = None
    visible_true: tuple[bool, ...] | None = None


@runtime_checkable
class FrameSource(Protocol):
    """What the tracker needs from a camera: frames and intrinsics."""

    intrinsics: CameraIntrinsics

    def read(self, t: float | None = None) -> TrackingFrame | None:
        """The next frame (None if none is available now); ``t`` is the time to stamp it."""
        ...

    def close(self) -> None: ...

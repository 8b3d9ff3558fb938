"""Frames from the IR/depth sensor and the interface every frame source implements.

A :class:`TrackingFrame` is what the HoloLens 2 AHAT stream delivers: an active-brightness
(IR) image and a depth image (range along the ray, mm, 0 = invalid, wrapping beyond ~1 m),
with the intrinsics and a timestamp. Backends (``sim``, ``opencv``; a HoloLens 2 stream
client can be another) subclass :class:`FrameSource` and are picked by the ``backend`` field
of their configuration in :mod:`humantele.tracking.sources` (:func:`make_frame_source`), as
haptic devices, force sensors and video sources are.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

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
    time, s. ``T_world_camera``: the camera's pose in the tracker's world at this frame, as
    the device reports it (hl2ss: the rig pose times the AHAT extrinsics; sim: the sim
    head's camera); None when the device gave none (such a frame cannot place the probe in
    the world). ``T_world_rig``: the headset's own pose (rig frame) in the same world, when
    the device reports one. ``device_time_s``: the frame's time on the device's own clock (s;
    hl2ss: its timestamp), for matching a recording to the device's data.
    ``T_camera_probe_true``: ground truth (simulated frames only, for tests and benchmarks;
    never read by the daemons).
    """

    t: float
    ir: NDArray[np.uint16]
    depth_mm: NDArray[np.uint16] | None
    intrinsics: CameraIntrinsics
    seq: int = 0
    T_world_camera: Pose | None = None
    T_world_rig: Pose | None = None
    device_time_s: float | None = None
    T_camera_probe_true: Pose | None = None
    visible_true: tuple[bool, ...] | None = None
    ab_paired: bool = False  # AB sampled at even columns, each over two (hl2ss H.26x)


class FrameSource(ABC):
    """IR (and depth) frames from a camera or a simulation; same methods for all backends.

    ``open()`` raises :class:`FrameSourceUnavailable` (one line naming the camera and what to
    check) when the camera cannot start; ``read(t)`` returns the next frame stamped ``t`` (s;
    None: the source's own clock), or None when the camera gave none (the backend counts
    it, in its ``dropped``); ``close()`` releases the camera, safe to call twice.
    ``intrinsics`` are the camera's (the configured ones until opened).
    """

    name: str = "frames"
    intrinsics: CameraIntrinsics

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def read(self, t: float | None = None) -> TrackingFrame | None: ...

    @abstractmethod
    def close(self) -> None: ...

    def __enter__(self) -> FrameSource:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

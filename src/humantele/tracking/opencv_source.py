"""Frame source on an OpenCV ``cv2.VideoCapture`` IR camera, with optional depth capture.

The IR capture gives active brightness (grey, 8 or 16 bit; scaled by ``ir_scale`` to counts);
the optional depth capture gives 16-bit range in mm (e.g. an OpenNI/RealSense device opened by
OpenCV). Without depth the frames carry ``depth_mm=None``; the pipeline needs depth to track.
"""

from __future__ import annotations

import time
from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from humantele.config import ConfigModel
from humantele.tracking.camera import CameraIntrinsics
from humantele.tracking.frames import FrameSource, FrameSourceUnavailable, TrackingFrame


class OpenCVFrameConfig(ConfigModel):
    """A camera OpenCV can open: device index (as text, e.g. "0") or a path/URL."""

    backend: Literal["opencv"] = "opencv"
    device: str = "0"
    depth_device: str | None = None
    intrinsics: CameraIntrinsics = Field(default_factory=CameraIntrinsics)
    ir_scale: float = Field(16.0, gt=0, description="counts per grey level of the IR capture")


def _open(device: str) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(int(device) if device.isdigit() else device)
    if not cap.isOpened():
        cap.release()
        raise FrameSourceUnavailable(
            f"cannot open camera {device!r} with OpenCV (cv2.VideoCapture): no such device "
            "or it is busy; check the device index/path, or use the 'sim' tracker backend"
        )
    return cap


class OpenCVFrameSource(FrameSource):
    """IR (and depth) frames from OpenCV captures; ``open()`` raises FrameSourceUnavailable."""

    name = "opencv frames"

    def __init__(self, config: OpenCVFrameConfig | None = None):
        self.config = c = config or OpenCVFrameConfig()
        self.intrinsics = c.intrinsics
        self._ir: cv2.VideoCapture | None = None
        self._depth: cv2.VideoCapture | None = None
        self._seq = 0
        self.dropped = 0  # reads that gave no frame

    def open(self) -> None:
        """Open the IR (and depth) captures; FrameSourceUnavailable if one cannot be opened."""
        c = self.config
        self.close()
        self._ir = _open(c.device)
        if c.depth_device is not None:
            try:
                self._depth = _open(c.depth_device)
            except FrameSourceUnavailable:
                self.close()
                raise
            self._depth.set(cv2.CAP_PROP_CONVERT_RGB, 0)

    def read(self, t: float | None = None) -> TrackingFrame | None:
        """The next frame, or None (counted in ``dropped``) if the camera gave none."""
        if self._ir is None:
            raise FrameSourceUnavailable(
                f"camera {self.config.device!r} is not open; call open() before read()"
            )
        ok, img = self._ir.read()
        if not ok or img is None:
            self.dropped += 1
            return None
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        ir = np.clip(img.astype(np.float32) * self.config.ir_scale, 0, 65535).astype(np.uint16)
        depth = None
        if self._depth is not None:
            ok, d = self._depth.read()
            if not ok or d is None or d.shape[:2] != ir.shape:
                self.dropped += 1
                return None
            depth = d.astype(np.uint16) if d.ndim == 2 else d[..., 0].astype(np.uint16)
        self._seq += 1
        return TrackingFrame(
            t=time.monotonic() if t is None else t,
            ir=ir,
            depth_mm=depth,
            intrinsics=self.intrinsics,
            seq=self._seq,
        )

    def close(self) -> None:
        for cap in (self._ir, self._depth):
            if cap is not None:
                cap.release()
        self._ir = self._depth = None

"""A camera or an HDMI capture card through OpenCV's ``cv2.VideoCapture``.

How a real ultrasound machine's screen (through a capture card) or a POV camera is usually
taken in. ``device`` is an index ("0" for /dev/video0), a path (a device node or a video
file) or a URL (rtsp://, http://) that OpenCV's FFmpeg backend opens. ``width``, ``height``
and ``fps`` are requests (0: the device's own); the device may give another size, which the
frames then have. ``pixel_spacing_mm`` (row, col) is the size of a screen pixel of the US
machine in the image (from its depth scale), for calipers; None when unknown.

``open()`` opens the device and reads one frame: a missing, busy or silent device raises
:class:`~humantele.video.base.VideoSourceUnavailable` at start. ``read()`` blocks in the
driver until the next frame (``cv2.VideoCapture.read``; a network stream gives up after
``read_timeout_s``, a V4L2 device after the driver's own timeout); a failed read returns
None and is counted in ``counters.dropped``; ``stall_reads`` failures in a row raise
:class:`~humantele.video.base.VideoSourceError` (the device stopped delivering: unplugged, the
stream ended), and so does every later ``read()`` until the source is reopened. ``t_capture``
is when the driver handed the frame over (a capture card adds its own latency, about a frame,
which the glass-to-glass benchmark measures).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import Field, field_validator

from humantele.config import ConfigModel
from humantele.video.base import (
    VideoFrame,
    VideoSource,
    VideoSourceError,
    VideoSourceUnavailable,
)


class OpenCVVideoConfig(ConfigModel):
    """A capture device OpenCV can open (see the module docstring)."""

    backend: Literal["opencv"] = "opencv"
    device: str = Field("0", min_length=1, description="index, device path, file or URL")
    width: int = Field(0, ge=0, le=8192, description="requested width, px (0: the device's)")
    height: int = Field(0, ge=0, le=8192, description="requested height, px (0: the device's)")
    fps: float = Field(0.0, ge=0.0, le=240.0, description="requested rate (0: the device's)")
    pixel_spacing_mm: tuple[float, float] | None = Field(
        None, description="(row, col) mm per pixel of a US machine's image, for calipers"
    )
    depth_origin_row: float | None = Field(
        None, ge=0.0, le=8192.0, description="a US image's row (px) of depth 0 (the skin line)"
    )
    stall_reads: int = Field(30, ge=1, le=100000, description="failed reads in a row = stopped")
    loop: bool = Field(False, description="a video file: start again at its end (a replay)")
    open_timeout_s: float = Field(5.0, gt=0.0, le=120.0, description="network streams")
    read_timeout_s: float = Field(2.0, gt=0.0, le=120.0, description="network streams")

    @field_validator("pixel_spacing_mm")
    @classmethod
    def _positive(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not all(0.0 < s < 100.0 for s in v):
            raise ValueError(f"pixel spacing must be two sizes in (0, 100) mm, got {list(v)}")
        return v


def _describe(device: str) -> str:
    if device.isdigit():
        return f"camera index {device} (/dev/video{device})"
    return repr(device)


class OpenCVVideoSource(VideoSource):
    """Frames (BGR) from ``cv2.VideoCapture``; ``kind`` "camera" (it can be either track)."""

    name = "opencv video"
    kind = "camera"

    def __init__(
        self, config: OpenCVVideoConfig | None = None, clock: Callable[[], float] = time.monotonic
    ) -> None:
        super().__init__()
        self.config = config or OpenCVVideoConfig()
        self.clock = clock
        self._cap: cv2.VideoCapture | None = None
        self._first: VideoFrame | None = None
        self._seq = 0
        self._fails = 0
        self._stopped = False
        self._size = (self.config.width, self.config.height)
        self._fps = self.config.fps
        self._file = Path(self.config.device).is_file()  # played at its rate, not read at once
        self._t_next = 0.0

    @property
    def size(self) -> tuple[int, int]:
        return self._size

    @property
    def fps(self) -> float:
        return float(self._fps)

    def open(self) -> None:
        """Open the device and take one frame; VideoSourceUnavailable (one line) if it cannot."""
        c = self.config
        self.close()
        what = _describe(c.device)
        params = [
            cv2.CAP_PROP_OPEN_TIMEOUT_MSEC,
            int(c.open_timeout_s * 1000),
            cv2.CAP_PROP_READ_TIMEOUT_MSEC,
            int(c.read_timeout_s * 1000),
        ]
        target: int | str = int(c.device) if c.device.isdigit() else c.device
        # OpenCV logs each backend it tries and fails with; our one line says it better.
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        try:
            cap = cv2.VideoCapture(target, cv2.CAP_ANY, params)
        finally:
            cv2.utils.logging.setLogLevel(level)
        if not cap.isOpened():
            cap.release()
            raise VideoSourceUnavailable(
                f"cannot open video device {what} with OpenCV: it is missing, busy or not a "
                "video; check the cable and the index or path (v4l2-ctl --list-devices), or "
                "use the 'sim' video backend"
            )
        if c.width:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, c.width)
        if c.height:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, c.height)
        if c.fps:
            cap.set(cv2.CAP_PROP_FPS, c.fps)
        self._cap = cap
        self._stopped = False
        self._fails = 0
        frame = self._grab()
        if frame is None:
            self.close()
            raise VideoSourceUnavailable(
                f"video device {what} opened but gave no frame; check that it has a signal "
                "(the US machine's video output is on) and that no other program holds it"
            )
        self._first = frame
        self._t_next = time.monotonic()  # a file's first frame: now
        self._size = (frame.width, frame.height)
        device_fps = cap.get(cv2.CAP_PROP_FPS)
        self._fps = c.fps or (device_fps if 0.0 < device_fps < 1000.0 else 30.0)

    def read(self) -> VideoFrame | None:
        """The next frame; None if the device gave none (counted); VideoSourceError once it
        has failed ``stall_reads`` times in a row (and ever after, until reopened)."""
        if self._cap is None:
            raise VideoSourceError(f"{_describe(self.config.device)}: read() before open()")
        if self._first is not None:
            frame, self._first = self._first, None
            self.counters.frames += 1
            return frame
        if self._stopped:
            raise VideoSourceError(self._stall_message())
        if self._file:
            self._pace()
        frame = self._grab()
        if frame is None and self._file and self.config.loop:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)  # the file's end: from the start again
            frame = self._grab()
        if frame is None:
            self.counters.dropped += 1
            self._fails += 1
            if self._fails >= self.config.stall_reads:
                self._stopped = True
                raise VideoSourceError(self._stall_message())
            return None
        self._fails = 0
        self.counters.frames += 1
        return frame

    def _pace(self) -> None:
        """A file gives its frames at once: wait for this frame's time at the file's rate."""
        now = time.monotonic()
        period = 1.0 / self._fps
        self._t_next = max(self._t_next + period, now - period)  # late: no catch-up burst
        if self._t_next > now:
            time.sleep(self._t_next - now)

    def _stall_message(self) -> str:
        return (
            f"video device {_describe(self.config.device)} stopped delivering frames "
            f"({self.config.stall_reads} reads failed in a row); check its cable and signal, "
            "then restart the source"
        )

    def _grab(self) -> VideoFrame | None:
        assert self._cap is not None
        try:
            ok, img = self._cap.read()
        except cv2.error:
            return None
        t = self.clock()
        if not ok or img is None or img.size == 0:
            return None
        if img.dtype != np.uint8:  # 16-bit captures: keep the high byte
            img = (img >> 8).astype(np.uint8) if img.dtype == np.uint16 else None
            if img is None:
                return None
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        elif img.shape[2] != 3:
            return None
        self._seq += 1
        c = self.config
        return VideoFrame(np.ascontiguousarray(img), self._seq, t, c.pixel_spacing_mm,
                          depth_origin_row=c.depth_origin_row)  # fmt: skip

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
        self._first = None

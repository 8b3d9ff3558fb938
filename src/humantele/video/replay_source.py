"""The ``replay`` video backend: a device recording's US or POV frames.

Reads ``/video/us`` or ``/video/pov`` (``track``) of a file written by ``humantele devices
record`` (:mod:`humantele.recording.device_file`): JPEG frames with their capture times. ``read``
blocks until the frame's recorded time (relative to the first ``read``), as a capture card
does, and gives it decoded (BGR) with ``t_capture`` the time it was given (this process's
``time.monotonic``), the recorded ``pixel_spacing_mm``/``depth_origin_row`` unless the config
sets them. ``loop``: start again at the end; else the end raises
:class:`~humantele.video.base.VideoSourceError` (the source stopped delivering), as a capture
device that stops does.

``open`` raises :class:`~humantele.video.base.VideoSourceUnavailable` (one line) for a file
that is not a device recording or has no frame of the track; a truncated file is replayed up to
its torn tail, logged. A frame that does not decode is counted in ``counters.dropped``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from humantele.config import ConfigModel
from humantele.recording.device_file import (
    VIDEO,
    DeviceRecording,
    DeviceRecordingError,
    Sample,
    open_recording,
)
from humantele.video.base import VideoFrame, VideoSource, VideoSourceError, VideoSourceUnavailable


class ReplayVideoConfig(ConfigModel):
    """The ``replay`` video backend: a device recording's frames of one track."""

    backend: Literal["replay"] = "replay"
    file: str = Field(..., min_length=1, description="MCAP from `humantele devices record`")
    track: Literal["us", "pov"] = Field("us", description="which recorded track")
    loop: bool = Field(False, description="start again at the end")
    pace: bool = Field(True, description="at the recorded times (False: as fast as read)")
    pixel_spacing_mm: tuple[float, float] | None = Field(
        None, description="(row, col) mm per pixel (None: as recorded)"
    )
    depth_origin_row: float | None = Field(None, description="row of depth 0 (None: recorded)")
    # as a capture device's settings (the follower's video process sizes its buffers by them)
    width: int = Field(0, ge=0, le=8192, description="px (0: the recording's; not rescaled)")
    height: int = Field(0, ge=0, le=8192, description="px (0: the recording's; not rescaled)")
    fps: float = Field(0.0, ge=0.0, le=240.0, description="nominal rate (0: the recording's)")


class ReplayPovConfig(ReplayVideoConfig):
    """``[follower.video.pov] backend = "replay"``: the recorded POV track by default."""

    track: Literal["us", "pov"] = Field("pov", description="which recorded track")


class ReplayVideoSource(VideoSource):
    """Recorded frames of one track (see the module docstring)."""

    name = "replay video"

    def __init__(
        self,
        config: ReplayVideoConfig,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        super().__init__()
        self.config = config
        self.kind = config.track
        self.problem: str | None = None
        self._clock, self._sleep = clock, sleep
        self._rec: DeviceRecording | None = None
        self._it: Iterator[Sample] | None = None
        self._next: Sample | None = None
        self._t0: float | None = None
        self._r0 = 0.0
        self._seq = 0
        self._size = (0, 0)
        self._fps = 30.0

    @property
    def size(self) -> tuple[int, int]:
        return self._size

    @property
    def fps(self) -> float:
        return self._fps

    def open(self) -> None:
        if self._rec is not None:
            return
        c = self.config
        try:
            rec = open_recording(c.file)
        except DeviceRecordingError as exc:
            raise VideoSourceUnavailable(f"replay video ({c.track}): {exc}") from None
        self._rec = rec
        self._restart()
        first = self._next
        if first is None:
            self._rec = None
            raise VideoSourceUnavailable(
                f"replay video: {c.file} has no {c.track} frame"
                + ("" if rec.problem is None else f" ({rec.problem})")
            )
        self._size = (int(first.fields.get("width", 0)), int(first.fields.get("height", 0)))
        rate = self._peek_rate()
        self._fps = c.fps or rate or 30.0

    def _peek_rate(self) -> float | None:
        """The recorded rate from the first frames (a second pass over the file's start)."""
        assert self._rec is not None
        times = []
        for s in self._rec.samples({VIDEO[self.config.track]}):
            times.append(float(s.fields.get("t_capture", s.t)))
            if len(times) >= 10:
                break
        d = np.diff(times)
        d = d[d > 0]
        return float(1.0 / np.median(d)) if len(d) else None

    def _restart(self) -> None:
        assert self._rec is not None
        self._it = self._rec.samples({VIDEO[self.config.track]})
        self._next = next(self._it, None)
        self._t0 = None

    def read(self) -> VideoFrame | None:
        c = self.config
        if self._rec is None:
            raise VideoSourceError(f"replay video {c.file}: read() before open()")
        if self._next is None and c.loop:
            self._restart()
        s = self._next
        if s is None:
            self.problem = self._rec.problem
            raise VideoSourceError(
                f"replay video {c.file} ({c.track}) ended after {self._seq} frames"
            )
        self._next = next(self._it, None) if self._it is not None else None
        t_rec = float(s.fields.get("t_capture", s.t))
        if c.pace:
            now = self._clock()
            if self._t0 is None:
                self._t0, self._r0 = now, t_rec
            wait = self._t0 + (t_rec - self._r0) - now
            if wait > 0:
                self._sleep(wait)
        jpeg = s.blobs.get("jpeg", b"")
        img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR) if jpeg else None
        if img is None or img.ndim != 3:
            self.counters.dropped += 1
            return None
        spacing = c.pixel_spacing_mm or s.fields.get("pixel_spacing_mm")
        origin = c.depth_origin_row
        if origin is None:
            origin = s.fields.get("depth_origin_row")
        self._seq += 1
        self.counters.frames += 1
        return VideoFrame(
            np.ascontiguousarray(img),
            self._seq,
            self._clock(),
            None if spacing is None else (float(spacing[0]), float(spacing[1])),
            depth_origin_row=None if origin is None else float(origin),
        )

    def close(self) -> None:
        close = getattr(self._it, "close", None)
        if close is not None:
            close()
        self._it, self._next, self._rec = None, None, None

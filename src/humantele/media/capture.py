"""A video source captured into frames ready for the encoder (follower side).

:class:`VideoCapture` reads one source in its own thread (``humantele-video-us``, ``-pov``),
scales the POV when the policy says so, draws the frame counter, converts to YUV 4:2:0 (the
encoder's input, so aiortc's encoder thread does not) and puts a :class:`CapturedFrame` in a
:class:`~humantele.media.slot.LatestSlot`; it also records the frame's timestamps (and, at
``record_hz``, a JPEG) without touching the event loop. The follower's sender
(:mod:`humantele.media.sender`) hands the slot to aiortc; the video process
(:mod:`humantele.media.process`) subclasses the capture to publish into shared memory instead.
Nothing here imports aiortc.
"""

from __future__ import annotations

import asyncio
import contextlib
import fractions
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import av
import cv2
import numpy as np

from humantele.media.slot import LatestSlot
from humantele.video.base import VideoSource, VideoSourceError, VideoSourceUnavailable
from humantele.video.counter import draw_counter

log = logging.getLogger(__name__)

VIDEO_TIME_BASE = fractions.Fraction(1, 90000)
REOPEN_DELAY_S = 1.0

Record = Callable[[str, float, dict], Any]
IMAGE_TOPICS = {"us": "/follower/us_image", "pov": "/follower/pov_image"}


@dataclass(frozen=True, slots=True)
class CapturedFrame:
    """A frame ready for the encoder: ``frame`` (yuv420p, pts = capture time at 90 kHz), its
    number ``seq`` in the track, capture time ``t_capture`` (s, follower clock), size (px)."""

    frame: av.VideoFrame
    seq: int
    t_capture: float
    width: int
    height: int


def i420_frame(yuv: np.ndarray, t_capture: float) -> av.VideoFrame:
    """An aiortc frame of I420 pixels ((h * 3 / 2, w) uint8), pts = capture time at 90 kHz."""
    frame = av.VideoFrame.from_ndarray(yuv, format="yuv420p")
    frame.pts = int(round(t_capture * 90000))
    frame.time_base = VIDEO_TIME_BASE
    return frame


def _even(n: float) -> int:
    return max(2, int(round(n / 2.0)) * 2)


class VideoCapture:
    """One source read in its own thread into a latest-frame slot (see the module docstring).

    ``scale`` (size factor per side) and ``max_fps`` (None: the source's rate) may be changed
    from any thread; they apply from the next frame.
    """

    def __init__(
        self,
        name: str,
        source: VideoSource,
        *,
        stamp_counter: bool = True,
        record: Record | None = None,
        record_hz: float = 0.0,
        jpeg_quality: int = 85,
    ) -> None:
        self.name = name
        self.source = source
        self.stamp_counter = stamp_counter
        self.record = record
        self.record_hz = record_hz
        self.jpeg_quality = jpeg_quality
        self.slot: LatestSlot[CapturedFrame] = LatestSlot()
        self.scale = 1.0
        self.max_fps: float | None = None
        self.captured = 0
        self.published = 0
        self.rate_skipped = 0
        self.errors = 0
        self.error = ""
        self.sent = 0  # frames the encoder took (all tracks of this source)
        self.prepare_times: list[float] = []  # s per frame (scale, counter, YUV), last 500
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_pub = -1e9
        self._last_rec = -1e9

    def open(self) -> None:
        """Open the source (blocks; VideoSourceUnavailable with one clear line)."""
        self.source.open()

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self.slot.bind(loop)
        self._thread = threading.Thread(
            target=self._run, name=f"humantele-video-{self.name}", daemon=True
        )
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        with contextlib.suppress(Exception):
            self.source.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                f = self.source.read()
            except VideoSourceError as exc:
                self.errors += 1
                if self.error != str(exc):
                    log.error("video %s: %s", self.name, exc)
                self.error = str(exc)
                self._reopen()
                continue
            except Exception:  # a source bug must not end the thread silently
                self.errors += 1
                log.exception("video %s: read failed (counted)", self.name)
                self._stop.wait(REOPEN_DELAY_S)
                continue
            if f is None:
                continue
            self.captured += 1
            try:
                self._take(f)
            except Exception:
                self.errors += 1
                if self.errors in (1, 10, 100):
                    log.exception("video %s: could not prepare a frame (counted)", self.name)

    def _reopen(self) -> None:
        self._stop.wait(REOPEN_DELAY_S)
        with contextlib.suppress(Exception):
            self.source.close()
        try:
            self.source.open()
        except VideoSourceUnavailable as exc:
            self.error = str(exc)

    def _take(self, f: Any) -> None:
        t = f.t_capture
        self._record(f)
        max_fps = self.max_fps
        if max_fps is not None and t - self._last_pub < 0.9 / max_fps:
            self.rate_skipped += 1
            return
        self._last_pub = t
        t0 = time.perf_counter()
        img = f.image
        h, w = img.shape[:2]
        scale = self.scale
        if scale != 1.0 or w % 2 or h % 2:
            w, h = _even(w * scale), _even(h * scale)
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        elif self.stamp_counter:
            img = np.array(img, copy=True)  # the source's frame is recorded as it came
        if self.stamp_counter and w >= 64 and h >= 32:
            draw_counter(img, f.seq)
        yuv = cv2.cvtColor(img, cv2.COLOR_BGR2YUV_I420)
        self.prepare_times.append(time.perf_counter() - t0)
        if len(self.prepare_times) > 500:
            del self.prepare_times[:250]
        self.published += 1
        self.emit(f.seq, t, yuv, w, h)

    def emit(self, seq: int, t: float, yuv: np.ndarray, width: int, height: int) -> None:
        """Hand a prepared frame (I420, (h * 3 / 2, w) uint8) on: wrapped for aiortc into the
        slot (the video process overrides this to use shared memory)."""
        self.slot.put(CapturedFrame(i420_frame(yuv, t), seq, t, width, height))

    def _record(self, f: Any) -> None:
        """Every captured frame's timestamps; a JPEG at ``record_hz`` (any thread: the recorder
        queues without blocking)."""
        if self.record is None:
            return
        payload: dict[str, Any] = {"stream": self.name, "seq": f.seq, "event": "captured"}
        meta = getattr(f, "meta", None) or {}
        q = meta.get("quality")
        if isinstance(q, int | float) and np.isfinite(q):
            payload["quality"] = float(q)
        c = meta.get("coupling")
        if isinstance(c, int | float) and np.isfinite(c):
            payload["coupling"] = float(c)
        self.record("/follower/video_frame", f.t_capture, payload)
        if self.record_hz > 0 and f.t_capture - self._last_rec >= 0.999 / self.record_hz:
            self._last_rec = f.t_capture
            ok, buf = cv2.imencode(
                ".jpg", f.image, [int(cv2.IMWRITE_JPEG_QUALITY), int(self.jpeg_quality)]
            )
            if ok:
                self.record(
                    IMAGE_TOPICS[self.name], f.t_capture, {"data": buf.tobytes(), "seq": f.seq}
                )

"""Where the console gets its pictures: the latest frame of each track, on the expert's clock.

The console asks a :class:`FrameProvider` for ``latest("us")`` and ``latest("pov")``: the
newest decoded :class:`~humantele.video.base.VideoFrame` of that track (``seq`` increasing,
``t_capture`` the capture time mapped onto this process's ``time.monotonic()``), or None when
there is none yet. It never blocks: the receiver (or a reader thread) keeps the latest frame.

:class:`SourceFrames` is a provider over local :class:`~humantele.video.base.VideoSource` s,
one reader thread each: the sim sources in tests and, until the follower's tracks arrive over
the link, a stand-in for them; the expert daemon's WebRTC receiver is the other provider.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from typing import Protocol

from humantele.video.base import VideoFrame, VideoSource, VideoSourceError

log = logging.getLogger(__name__)

TRACKS = ("us", "pov")


class FrameProvider(Protocol):
    """The latest frame of a track (``"us"`` or ``"pov"``), or None; never blocks."""

    def latest(self, track: str) -> VideoFrame | None: ...


class SourceFrames:
    """A :class:`FrameProvider` reading local video sources, one daemon thread per track.

    ``sources``: track name -> source (not yet opened). :meth:`start` opens them in their
    threads; :meth:`stop` ends the threads and closes the sources. A source that fails is
    logged once and its track gives no new frames (``errors`` says why)."""

    def __init__(self, sources: Mapping[str, VideoSource]) -> None:
        self.sources = dict(sources)
        self.errors: dict[str, str] = {}
        self._latest: dict[str, VideoFrame] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def latest(self, track: str) -> VideoFrame | None:
        with self._lock:
            return self._latest.get(track)

    def start(self) -> None:
        """Open the sources and read them (nothing if already reading)."""
        if self._threads:
            return
        self._stop.clear()
        for track, source in self.sources.items():
            t = threading.Thread(
                target=self._read, args=(track, source), name=f"console-{track}", daemon=True
            )
            t.start()
            self._threads.append(t)

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout)
        self._threads.clear()

    def _read(self, track: str, source: VideoSource) -> None:
        try:
            source.open()
            while not self._stop.is_set():
                frame = source.read()
                if frame is not None:
                    with self._lock:
                        self._latest[track] = frame
        except VideoSourceError as exc:
            self.errors[track] = str(exc)
            log.error("console: %s source stopped: %s", track, exc)
        finally:
            source.close()

"""What the sim video sources share: pacing like a camera, the scene call, bad input counted.

A sim source renders one frame per ``read()`` from the scene snapshot it asks for then; it
paces itself like a camera (``read()`` returns at the next ``1/fps`` tick; if the caller is
late it renders at once and the ticks start again from there, with no catch-up burst).
:meth:`SimVideoSource.render` renders a given snapshot at once (tests, benchmarks).
"""

from __future__ import annotations

import logging
import math
import numbers
import time
from abc import abstractmethod
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from humantele.video.base import VideoFrame, VideoSource, VideoSourceError
from humantele.video.counter import draw_counter
from humantele.video.scene import DemoScene, Scene, SceneSnapshot
from humantele.video.sim_config import SimSourceConfig  # noqa: F401 (their home before)

log = logging.getLogger(__name__)

Rendered = tuple[NDArray[np.uint8], Mapping[str, Any]]


class SimVideoSource(VideoSource):
    """Base of the sim sources: subclasses give ``_render(snapshot)`` and ``_blank()``.

    ``scene``: the snapshot callable (None: :class:`~humantele.video.scene.DemoScene`);
    ``clock``: the time source for ``t_capture`` and pacing (default ``time.monotonic``; a
    fake clock suits :meth:`render`, while ``read()`` sleeps in real time).
    """

    def __init__(
        self,
        config: SimSourceConfig,
        scene: Scene | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__()
        self.config = config
        self.scene = scene if scene is not None else DemoScene()
        self.clock = clock
        self._seq = 0
        self._due: float | None = None
        self._open = False

    @property
    def size(self) -> tuple[int, int]:
        return (self.config.width, self.config.height)

    @property
    def fps(self) -> float:
        return float(self.config.fps)

    def open(self) -> None:
        self._open = True
        self._due = None

    def close(self) -> None:
        self._open = False

    def read(self) -> VideoFrame:
        """Wait for the next frame tick, ask the scene, render; never None, never raises for
        bad scene input (a dark frame, counted in ``counters.invalid``)."""
        if not self._open:
            raise VideoSourceError(f"{self.name}: read() before open()")
        now = self.clock()
        if self._due is not None and now < self._due:
            time.sleep(self._due - now)
            now = self.clock()
        period = 1.0 / self.fps
        self._due = (self._due + period) if self._due is not None else now + period
        if self._due < now:  # late: no burst to catch up
            self._due = now + period
        try:
            snapshot: SceneSnapshot | None = self.scene()
        except Exception:  # a failing world must not stop the video
            snapshot = None
            if self.counters.invalid == 0:
                log.exception("%s: the scene callable failed (counted, dark frame)", self.name)
        return self.render(snapshot, t_capture=now)

    def render(self, snapshot: SceneSnapshot | None, t_capture: float | None = None) -> VideoFrame:
        """The frame for ``snapshot`` now: a dark/blank one (counted in ``counters.invalid``)
        if the snapshot is unusable. Draws the frame counter when ``config.counter``."""
        t = self.clock() if t_capture is None else t_capture
        image = meta = None
        if isinstance(snapshot, SceneSnapshot) and self._usable(snapshot):
            try:
                image, meta = self._render(snapshot)
            except (ValueError, ArithmeticError):
                # Finite but absurd input (e.g. a pose that overflows float32): counted; the
                # first is logged with its traceback, as it may also be a bug.
                image = None
                if self.counters.invalid == 0:
                    log.exception("%s: could not render a snapshot (counted)", self.name)
        if image is None:
            self.counters.invalid += 1
            image, meta = self._blank()
            meta = {**meta, "valid": False}
        self._seq += 1
        if self.config.counter:
            draw_counter(image, self._seq)
        self.counters.frames += 1
        return VideoFrame(image, self._seq, t, self._spacing_mm(), meta, self._depth_origin_row())

    def _spacing_mm(self) -> tuple[float, float] | None:
        return None

    def _depth_origin_row(self) -> float | None:
        return None

    def _usable(self, s: SceneSnapshot) -> bool:
        """Finite time and force (NaN and inf fail; poses are checked by subclasses)."""
        return _finite(s.t) and _finite(s.force_n)

    @abstractmethod
    def _render(self, snapshot: SceneSnapshot) -> Rendered: ...

    @abstractmethod
    def _blank(self) -> Rendered: ...


def _finite(x: object) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x)

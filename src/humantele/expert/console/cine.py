"""The cine buffer: the last seconds of the ultrasound track, as the page was sent them.

Each entry is one frame the page was sent, with its number, capture time (s, the expert's
clock) and pixel spacing (mm): either the JPEG the page drew (the JPEG path), or the decoded
frame itself (``raw``: the expert's decode of the very encoded frame the page decoded, a
VP8 picture being the same in every conforming decoder), made a JPEG only when the
sonographer looks at it (:meth:`CineFrame.image_jpeg`). Entries older than ``seconds``
before the newest are dropped; ``max_frames`` and ``max_bytes`` bound the memory whatever
the frame rate (a decoded 640 x 480 frame is 460 kB: 92 MB at 20 fps for 10 s).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from humantele.expert.console.jpeg import frame_jpeg
from humantele.expert.console.tracks import depth0, spacing


@dataclass(slots=True)
class CineFrame:
    """One frame of the buffer: ``jpeg`` bytes of a ``width`` x ``height`` px image, or
    (``jpeg`` None) ``raw``, a decoded frame ``to_jpeg(raw)`` encodes when first asked."""

    seq: int
    t_capture: float
    jpeg: bytes | None
    width: int
    height: int
    pixel_spacing_mm: tuple[float, float] | None
    depth_origin_row: float | None = None
    raw: Any = None
    to_jpeg: Callable[[Any], bytes] | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    @property
    def nbytes(self) -> int:
        """Memory it holds (bytes, about)."""
        if self.raw is not None:  # (kept with its JPEG once made: the size stays as added)
            return self.width * self.height * 3 // 2
        return len(self.jpeg or b"")

    def image_jpeg(self) -> bytes:
        """The JPEG of this frame (encoded once, in the caller's thread: not the loop's)."""
        with self._lock:
            if self.jpeg is None:
                if self.to_jpeg is None or self.raw is None:
                    raise ValueError(f"cine frame {self.seq} has no picture")
                self.jpeg = self.to_jpeg(self.raw)
            return self.jpeg


class CineBuffer:
    """The last ``seconds`` of frames by number (``seq``); ``freeze()`` keeps them as they are
    until ``resume()`` (the frozen loop does not scroll away while the sonographer reads it)."""

    def __init__(
        self, seconds: float = 10.0, max_frames: int = 600, max_bytes: int = 160_000_000
    ) -> None:
        self.seconds = float(seconds)
        self.max_frames = int(max_frames)
        self.max_bytes = int(max_bytes)
        self._frames: OrderedDict[int, CineFrame] = OrderedDict()
        self._bytes = 0
        self.frozen = False

    def __len__(self) -> int:
        return len(self._frames)

    def add(self, frame: CineFrame) -> None:
        """Keep ``frame`` (ignored while frozen, or if not newer than the newest)."""
        if self.frozen:
            return
        if self._frames and frame.seq <= next(reversed(self._frames)):
            return
        self._frames[frame.seq] = frame
        self._bytes += frame.nbytes
        while len(self._frames) > self.max_frames or (
            self._bytes > self.max_bytes and len(self._frames) > 1
        ):
            self._pop_oldest()
        while self._frames:
            oldest = next(iter(self._frames.values()))
            if frame.t_capture - oldest.t_capture <= self.seconds:
                break
            self._pop_oldest()

    def _pop_oldest(self) -> None:
        _, f = self._frames.popitem(last=False)
        self._bytes -= f.nbytes

    def clear(self) -> None:
        """Drop every frame (not while frozen: the loop being read stays)."""
        if not self.frozen:
            self._frames.clear()
            self._bytes = 0

    def get(self, seq: int) -> CineFrame | None:
        return self._frames.get(seq)

    def index(self) -> list[tuple[int, float]]:
        """(seq, t_capture) of every frame kept, oldest first."""
        return [(f.seq, f.t_capture) for f in self._frames.values()]

    def newest(self) -> CineFrame | None:
        return next(reversed(self._frames.values())) if self._frames else None

    def freeze(self) -> None:
        self.frozen = True

    def resume(self) -> None:
        self.frozen = False


def cine_frame(frame: Any, jpeg: bytes | None, quality: int) -> CineFrame:
    """The cine entry of a video frame: its ``jpeg`` (the JPEG path), or (None) the decoded
    frame itself, made a JPEG at ``quality`` when first asked."""
    return CineFrame(
        frame.seq, frame.t_capture, jpeg, frame.width, frame.height, spacing(frame),
        depth0(frame), raw=None if jpeg is not None else frame,
        to_jpeg=lambda f: frame_jpeg(f, quality),
    )  # fmt: skip

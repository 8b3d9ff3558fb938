"""The cine buffer: the last seconds of the ultrasound track, as the page was sent them.

Each entry is one encoded frame (JPEG, what the page draws, so a frozen frame is exactly the
picture the sonographer saw) with its number, capture time (s, the expert's clock) and pixel
spacing (mm). Entries older than ``seconds`` before the newest are dropped; ``max_frames``
bounds the memory whatever the frame rate (60 kB a frame at 640 x 480: ~12 MB at 20 fps).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class CineFrame:
    """One frame of the buffer: ``jpeg`` bytes of a ``width`` x ``height`` px image."""

    seq: int
    t_capture: float
    jpeg: bytes
    width: int
    height: int
    pixel_spacing_mm: tuple[float, float] | None
    depth_origin_row: float | None = None


class CineBuffer:
    """The last ``seconds`` of frames by number (``seq``); ``freeze()`` keeps them as they are
    until ``resume()`` (the frozen loop does not scroll away while the sonographer reads it)."""

    def __init__(self, seconds: float = 10.0, max_frames: int = 600) -> None:
        self.seconds = float(seconds)
        self.max_frames = int(max_frames)
        self._frames: OrderedDict[int, CineFrame] = OrderedDict()
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
        while len(self._frames) > self.max_frames:
            self._frames.popitem(last=False)
        while self._frames:
            oldest = next(iter(self._frames.values()))
            if frame.t_capture - oldest.t_capture <= self.seconds:
                break
            self._frames.popitem(last=False)

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

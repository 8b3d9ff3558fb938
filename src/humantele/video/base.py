"""The one video source interface, shared by the real and the simulated backends.

A :class:`VideoSource` gives :class:`VideoFrame` s: the ultrasound (US) image or the
follower's point-of-view (POV) video. Backends (``sim`` ultrasound, ``sim`` POV, ``opencv``
camera or HDMI capture card; later the headset's PV camera or a network stream) are picked by
configuration in :mod:`humantele.video.sources`.

Blocking and threads
    ``read()`` blocks until the source's next frame is due and ready, like a camera: a device
    for up to about one frame period of I/O (longer if the driver stalls), a sim source until
    its next ``1/fps`` tick and then for its rendering (a few ms of CPU, mostly in OpenCV and
    numpy, which release the GIL). So a daemon never calls ``read()`` on its event loop: it
    runs it in a thread (``await asyncio.to_thread(source.read)``, or one reader thread per
    source that keeps the latest frame), or in another process. ``open()`` may block too (a
    device can take a second to open) and belongs in the same thread. A source is used by one
    thread at a time.

Errors
    A source that cannot start (missing device, busy, bad path) raises
    :class:`VideoSourceUnavailable` from ``open()``, one line naming the device and what to
    check. A read that gives no frame returns None and is counted (``counters.dropped``); a
    device that stops delivering (``stall_reads`` failures in a row) raises
    :class:`VideoSourceError` from ``read()``, and every later ``read()`` does too, until the
    source is closed and opened again. Bad scene input to a sim source gives a dark frame,
    counted (``counters.invalid``); it never raises.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray


class VideoSourceError(RuntimeError):
    """A video source that stopped delivering frames; the message says which and what to do."""


class VideoSourceUnavailable(VideoSourceError):
    """A video source that cannot start (missing device, busy, bad path): one line naming the
    device and what to check."""


@dataclass(frozen=True, slots=True)
class VideoFrame:
    """One frame of a video source.

    ``image``: (H, W, 3) uint8, channel order **BGR** (OpenCV's; aiortc's ``bgr24``),
    C-contiguous; ``seq``: the source's frame number, from 1, +1 per frame it gives (so a
    receiver that sees a gap lost frames on the way); ``t_capture``: capture time (s) on the
    producing process's ``time.monotonic()`` clock (a source that receives frames from another
    device maps the device's capture time onto it when it can, else stamps the arrival);
    ``pixel_spacing_mm``: (row, col) size of a pixel in mm when the source knows it (the US
    image), else None; ``meta``: source-specific known answers (the sim US image quality, see
    :mod:`humantele.video.sim_ultrasound`); ``depth_origin_row``: the row (px, fractional) of
    depth 0 of a US image (the skin line under the centre of the probe's face) when the source
    knows it: with the pixel spacing, where each depth is on the image.
    """

    image: NDArray[np.uint8]
    seq: int
    t_capture: float
    pixel_spacing_mm: tuple[float, float] | None = None
    meta: Mapping[str, Any] = field(default_factory=dict)
    depth_origin_row: float | None = None

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def height(self) -> int:
        return int(self.image.shape[0])


@dataclass
class SourceCounters:
    """What a source has done since it was made: ``frames`` returned, reads that gave no frame
    (``dropped``), and scene inputs a sim source could not use (``invalid``: non-finite poses or
    force, a failing scene callable; each gave a dark frame)."""

    frames: int = 0
    dropped: int = 0
    invalid: int = 0


class VideoSource(ABC):
    """Frames from a camera, a capture card or a simulation; same methods for all backends.

    ``open()`` raises :class:`VideoSourceUnavailable` when the source cannot start;
    ``read()`` blocks until the next frame (see the module docstring) and returns it, or None
    when the device gave none (counted); ``close()`` releases the device, safe to call twice.
    ``kind`` says what the source shows (``"us"`` or ``"pov"``, or ``"camera"`` when a
    capture device could be either).
    """

    name: str = "video"
    kind: str = "camera"

    def __init__(self) -> None:
        self.counters = SourceCounters()

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def read(self) -> VideoFrame | None: ...

    @abstractmethod
    def close(self) -> None: ...

    @property
    @abstractmethod
    def size(self) -> tuple[int, int]:
        """(width, height) in px of the frames it gives (the requested size until opened)."""

    @property
    @abstractmethod
    def fps(self) -> float:
        """Nominal frames per second."""

    def __enter__(self) -> VideoSource:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

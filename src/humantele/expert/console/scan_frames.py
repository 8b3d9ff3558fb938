"""A whole scan's ultrasound for the hospital's archive (``[expert.archive]``): the frames the
console received during a scan, kept so that the scan can be archived as one Ultrasound
Multi-frame Image, on request (the console's "Archive scan") or, with ``send_scans``, at each
scan's end (docs/archive.md says why on request is the default).

While a scan is in progress each ultrasound frame the console is handed is offered here (from
:class:`~humantele.expert.console.video.PageVideo`, on the loop); one every ``1 / scan_fps`` s
is made a JPEG off the loop (its own encoder, latest wins) and kept with its capture time (s,
the expert's clock): the multi-frame's Frame Time Vector comes from those times.

Memory stays bounded whatever the scan's length: past ``scan_max_frames`` frames or
``scan_max_mb`` of JPEG, every other frame kept is dropped and the keeping interval doubles,
so the image still spans the whole scan, at a lower rate (640 x 480 JPEGs of ~40 kB: a
2-minute scan at 10 fps is 1200 frames, ~50 MB; a 10-minute one ends at 2.5 fps). One
image has one calibration: the frames kept are those of the scan's first geometry (size,
pixel spacing, depth origin); frames of another are left out and counted. Kept: the scan in
progress and the last one ended (until the next starts, or until it is queued); each scan is
archived at most once.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from humantele.expert.console.jpeg import I420Jpeg, frame_jpeg
from humantele.expert.console.tracks import depth0, spacing

Geometry = tuple[int, int, "tuple[float, float] | None", "float | None"]


def geometry(frame: Any) -> Geometry:
    """A frame's (width, height, pixel spacing (row, col) mm, depth-0 row px)."""
    return frame.width, frame.height, spacing(frame), depth0(frame)


@dataclass
class KeptScan:
    """One scan's frames: (t, jpeg) oldest first, ``t`` on the expert's clock (s)."""

    scan: int
    interval_s: float  # keep one frame every this long (doubles when the scan outgrows)
    max_frames: int
    max_bytes: float
    frames: list[tuple[float, bytes]] = field(default_factory=list)
    geometry: Geometry | None = None
    nbytes: int = 0
    next_t: float = -math.inf  # the next frame is kept from then
    halvings: int = 0
    other_geometry: int = 0  # frames left out: another size or scale than the first
    late: int = 0  # frames made JPEG after the scan ended (left out)
    ended: bool = False
    wanted: bool = False  # asked for while in progress: archived at its end
    outcome: str = ""  # "" not asked; "building"; "queued"
    sent_frames: int = 0  # frames in the image queued (its own are then let go)
    first_t: float | None = None
    last_t: float | None = None

    def due(self, t: float) -> bool:
        """Whether a frame captured at ``t`` is kept; if so it is counted as taken."""
        if self.ended or not math.isfinite(t) or t < self.next_t - 1e-6:  # (a clock's float)
            return False
        gap = t - self.next_t
        self.next_t = (
            self.next_t + self.interval_s if gap < self.interval_s else t + self.interval_s
        )
        return True

    def add(self, t: float, jpeg: bytes, geo: Geometry) -> bool:
        """Keep a frame's JPEG (False: left out, counted); halves the frames past the caps."""
        if self.ended:
            self.late += 1
            return False
        if self.geometry is None:
            self.geometry = geo
        elif geo != self.geometry:
            self.other_geometry += 1
            return False
        if self.frames and t <= self.frames[-1][0]:
            return False
        self.frames.append((t, jpeg))
        self.nbytes += len(jpeg)
        self.first_t = self.frames[0][0] if self.first_t is None else self.first_t
        self.last_t = t
        while len(self.frames) > 2 and (
            len(self.frames) > self.max_frames or self.nbytes > self.max_bytes
        ):
            self.frames = self.frames[::2]
            self.nbytes = sum(len(j) for _, j in self.frames)
            self.interval_s *= 2.0
            self.halvings += 1
            self.next_t = self.frames[-1][0] + self.interval_s
        return True

    @property
    def count(self) -> int:
        return self.sent_frames if self.outcome == "queued" else len(self.frames)

    def summary(self) -> dict[str, Any]:
        """For the page and the stats: numbers only."""
        span = 0.0 if self.first_t is None or self.last_t is None else self.last_t - self.first_t
        return {"scan": self.scan, "running": not self.ended, "frames": self.count,
                "seconds": round(span, 1), "fps": round(1.0 / self.interval_s, 2),
                "halved": self.halvings, "left_out": self.other_geometry,
                "wanted": self.wanted, "outcome": self.outcome}  # fmt: skip


class ScanFrames:
    """The scans' frames. ``scan()``: the scan in progress (None: none); ``send(kept)``: build
    and queue a scan's image (called on the loop); ``auto``: every scan at its end."""

    def __init__(
        self, scan: Callable[[], int | None], send: Callable[[KeptScan], None], fps: float = 10.0,
        max_frames: int = 1200, max_mb: float = 60.0, quality: int = 88, auto: bool = False,
    ) -> None:  # fmt: skip
        self.scan = scan
        self.send = send
        self.interval_s = 1.0 / fps
        self.max_frames = max_frames
        self.max_bytes = max_mb * 1e6
        self.quality = quality
        self.auto = auto
        self.current: KeptScan | None = None  # the scan in progress
        self.last: KeptScan | None = None  # the last one ended
        self.encoded = 0
        self.bad = 0  # frames that could not be made a JPEG
        self.encode_s = 0.0  # time spent making them (s, all of this run)
        self._next: tuple[KeptScan, Any] | None = None
        self._busy = False
        self._encoder = I420Jpeg(quality)
        self._tasks: set[asyncio.Task] = set()

    # --- the scans ---------------------------------------------------------------------------

    def poll(self) -> None:
        """Follow the scan in progress: a scan that ended is archived when asked (or with
        ``auto``); a new one starts empty (the last ended one let go)."""
        now = self.scan()
        if self.current is not None and self.current.scan == now:
            return
        if self.current is not None:
            self.end()
        if now is not None:
            self.current = KeptScan(now, self.interval_s, self.max_frames, self.max_bytes)
            if self.last is not None and self.last.outcome != "building":
                self.last = None  # (one being built is let go by its task)

    def end(self) -> None:
        """The scan in progress ended (or the console stops): archived when asked."""
        k, self.current = self.current, None
        if k is None:
            return
        k.ended = True
        self.last = k
        if (k.wanted or self.auto) and not k.outcome:
            self.send(k)  # (one with too few frames is refused there, with the reason)

    def request(self) -> tuple[bool, str]:
        """The sonographer asks for the scan in progress or the last one: (done, what)."""
        self.poll()
        k = self.current
        if k is not None:
            k.wanted = True
            return True, f"scan {k.scan} will be archived whole when it stops"
        k = self.last
        if k is None:
            return False, "no scan to archive: start one"
        if k.outcome:
            return False, f"scan {k.scan} is already {k.outcome} for the archive"
        if len(k.frames) < 2:
            return False, (f"scan {k.scan} has {len(k.frames)} frame(s) kept: nothing to "
                           "archive (frames are kept while the console is open)")  # fmt: skip
        self.send(k)
        return True, f"scan {k.scan}: {len(k.frames)} frames being archived"

    def status(self) -> dict[str, Any] | None:
        self.poll()
        k = self.current or self.last
        return None if k is None else {**k.summary(), "auto": self.auto}

    # --- the frames ----------------------------------------------------------------------------

    def offer(self, frame: Any) -> None:
        """A new ultrasound frame (on the loop): kept if a scan is on and it is due."""
        self.poll()
        k = self.current
        if k is None or not k.due(frame.t_capture):
            return
        self._next = (k, frame)  # (latest wins: an encode that falls behind skips frames)
        if not self._busy:
            self._busy = True
            task = asyncio.ensure_future(self._encode())
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _encode(self) -> None:
        try:
            while self._next is not None:
                k, frame = self._next
                self._next = None
                try:
                    jpeg = await asyncio.to_thread(self._jpeg, frame)
                except ValueError:
                    self.bad += 1
                    continue
                k.add(frame.t_capture, jpeg, geometry(frame))
        finally:
            self._busy = False

    def _jpeg(self, frame: Any) -> bytes:
        t0 = time.perf_counter()
        try:
            return frame_jpeg(frame, self.quality, self._encoder)
        except (AttributeError, TypeError) as exc:  # a frame with no picture
            raise ValueError(f"no picture: {exc}") from exc
        finally:
            self.encoded += 1
            self.encode_s += time.perf_counter() - t0

    async def idle(self) -> None:
        """Until the JPEGs being made are kept (tests, the console's stop)."""
        while self._tasks:
            await asyncio.gather(*list(self._tasks), return_exceptions=True)

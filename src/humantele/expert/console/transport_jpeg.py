"""The console's JPEG transport (``transport = "jpeg"``; sim video always, it has no encoded
frames; a browser without WebCodecs): each new frame JPEG-encoded once, when it comes, from
its I420 planes (libavcodec's MJPEG, no BGR image; a sim source's BGR image through OpenCV),
in a thread, latest wins: a slow page sees the newest frame, never a backlog (``coalesced``
counts the frames it skipped). At most :data:`~.pageclient.IN_FLIGHT` frames of a track are
in flight to a page (sent, not yet drawn); more wait. The cine buffer keeps the very bytes
the page drew.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from collections.abc import Callable
from typing import Any

from humantele.expert.console.cine import CineBuffer, CineFrame, cine_frame
from humantele.expert.console.frames import TRACKS
from humantele.expert.console.jpeg import I420Jpeg, frame_jpeg
from humantele.expert.console.messages import frame_header
from humantele.expert.console.pageclient import ConsolePage
from humantele.expert.console.tracks import TrackFigures, depth0, spacing
from humantele.video.base import VideoFrame
from humantele.web.pagesocket import PageSockets

log = logging.getLogger(__name__)
IN_FLIGHT_TIMEOUT_S = 0.5  # a page that echoes nothing for this long gets the next frame


class JpegTransport:
    """JPEG frames for the pages that take them. ``spawn``: runs a coroutine as the server's
    task; ``clock``: the expert's clock (s)."""

    def __init__(
        self,
        quality: int,
        tracks: dict[str, TrackFigures],
        cine: CineBuffer,
        pages: PageSockets,
        refused: Counter[str],
        spawn: Callable[[Any], None],
        clock: Callable[[], float],
    ) -> None:
        self.quality = quality
        self.tracks = tracks
        self.cine = cine
        self.pages = pages
        self.refused = refused
        self.spawn = spawn
        self.clock = clock
        self.in_flight_timeout_s = IN_FLIGHT_TIMEOUT_S
        self._next: dict[str, Any] = {}
        self._busy: dict[str, bool] = dict.fromkeys(TRACKS, False)
        self._encoders = {t: I420Jpeg(quality) for t in TRACKS}

    def push(self, track: str, frame: Any) -> None:
        """A new frame for the JPEG pages: encoded when the last one is done (latest wins)."""
        self._next[track] = frame
        if not self._busy[track]:
            self._busy[track] = True
            self.spawn(self._encode_track(track))

    def forget(self) -> None:
        """The last page closed: a stale picture must not be sent to the next one."""
        for track in TRACKS:
            self._next.pop(track, None)

    def holds(self, c: ConsolePage, key: str, data: str | bytes, now: float) -> bool:
        """Whether JPEG frame message ``key`` waits: its page has IN_FLIGHT frames of the
        track not yet drawn (the newest is sent when it draws one, or after the timeout)."""
        track = key[6:] if key.startswith("frame:") else None
        if track not in TRACKS:
            return False
        if not c.can_take(track, now, self.in_flight_timeout_s):
            return True
        c.in_flight[track].append((int.from_bytes(data[4:8], "little"), now))
        return False

    async def _encode_track(self, track: str) -> None:
        """Encode the newest frame of ``track`` for the JPEG pages, one at a time, latest
        wins; ends when none waits."""
        st = self.tracks[track]
        try:
            while (frame := self._next.pop(track, None)) is not None:
                t0 = self.clock()
                try:
                    packet, cine = await asyncio.to_thread(self._encode, track, frame)
                except ValueError as exc:
                    self.refused["bad_frame"] += 1
                    log.debug("console: %s frame %s not encoded: %s", track, frame.seq, exc)
                    continue
                st.encode_s.append(self.clock() - t0)
                st.jpegs += 1
                if cine is not None:
                    self.cine.add(cine)
                for c in list(self.pages.clients):
                    if isinstance(c, ConsolePage) and c.transport == "jpeg":
                        if f"frame:{track}" in c.pending:
                            self.pages.coalesced += 1
                        c.post(f"frame:{track}", packet)
        finally:
            self._busy[track] = False

    def _encode(self, track: str, frame: VideoFrame) -> tuple[bytes, CineFrame | None]:
        """The frame message (header + JPEG) and, for the ultrasound, its cine entry."""
        jpeg = frame_jpeg(frame, self.quality, self._encoders[track])
        header = frame_header(
            track, frame.seq, frame.t_capture, spacing(frame), frame.width, frame.height,
            depth0=depth0(frame),
        )  # fmt: skip
        return header + jpeg, cine_frame(frame, jpeg, self.quality) if track == "us" else None

"""The video to the console's pages: while a page is open (and only then) each track of a
:class:`~humantele.expert.console.frames.FrameProvider` is subscribed to, each new frame
noted (:mod:`.tracks`) and handed to each page's transport (:mod:`.transport_webcodecs`,
the default, or :mod:`.transport_jpeg`); the page's echoes of what it drew come back here.
Nothing polls; nothing runs per frame while no page is open."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from humantele.expert.console.cine import CineBuffer
from humantele.expert.console.config import TRANSPORTS, ConsoleConfig
from humantele.expert.console.frames import TRACKS, FrameProvider
from humantele.expert.console.messages import Drawn
from humantele.expert.console.pageclient import ConsolePage
from humantele.expert.console.tracks import TrackFigures
from humantele.expert.console.transport_jpeg import JpegTransport
from humantele.expert.console.transport_webcodecs import WebCodecsTransport
from humantele.web.pagesocket import PageClient, PageSockets


class PageVideo:
    """The frames of ``frames`` (None: no video) to the pages of ``pages``. ``spawn``: runs
    a coroutine as the server's task; ``clock``: the expert's clock (s)."""

    def __init__(
        self,
        config: ConsoleConfig,
        frames: FrameProvider | None,
        cine: CineBuffer,
        pages: PageSockets,
        refused: Counter[str],
        spawn: Callable[[Any], None],
        clock: Callable[[], float],
    ) -> None:
        self.config = config
        self.frames = frames
        self.cine = cine
        self.pages = pages
        self.refused = refused
        self.clock = clock
        self.tracks = {t: TrackFigures() for t in TRACKS}
        self.jpeg = JpegTransport(
            config.jpeg_quality, self.tracks, cine, pages, refused, spawn, clock
        )
        # Encoded frames to forward: a provider that has them (the WebRTC receiver's).
        self.webcodecs: WebCodecsTransport | None = None
        if frames is not None and hasattr(frames, "request_keyframe"):
            self.webcodecs = WebCodecsTransport(frames, self.tracks, cine, config.jpeg_quality)
        self.subscribed = False
        self.scan_frames: Any = None  # the archive's whole scans (scan_frames.ScanFrames)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._subscribers = {t: functools.partial(self._from_provider, t) for t in TRACKS}

    def started(self) -> None:
        """On the loop, at the server's start: frames from other threads come to it."""
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()

    def transport(self, asked: str | None) -> str:
        """The transport of a page that asked for ``asked`` (None: the configured one)."""
        if self.webcodecs is None:
            return "jpeg"  # sim or local sources: pictures, not encoded frames
        return asked if asked in TRANSPORTS else self.config.transport

    def opened(self, client: PageClient) -> None:
        """A page opened (its transport set, its hello sent): a WebCodecs page's tracks from
        a keyframe."""
        if isinstance(client, ConsolePage) and client.transport == "webcodecs" and self.webcodecs:
            self.webcodecs.opened(client)

    def subscribe(self) -> None:
        if self.subscribed or self.frames is None or not hasattr(self.frames, "subscribe"):
            return
        self.subscribed = True
        for track in TRACKS:  # the figures are those of this page's visit
            self.tracks[track].new_visit()
            self.frames.subscribe(track, self._subscribers[track])

    def unsubscribe(self) -> None:
        """The last page closed: no more frames; the cine loop emptied."""
        if not self.subscribed or self.frames is None:
            return
        self.subscribed = False
        for track in TRACKS:
            self.frames.unsubscribe(track, self._subscribers[track])
        self.jpeg.forget()
        self.cine.clear()

    def _from_provider(self, track: str, frame: Any, encoded: Any) -> None:
        """A provider's new frame, from its thread or the loop: handled on the loop."""
        if threading.get_ident() == self._loop_thread:
            self.on_frame(track, frame, encoded)
        elif self._loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop closed: the daemon's end
                self._loop.call_soon_threadsafe(self.on_frame, track, frame, encoded)

    def on_frame(self, track: str, frame: Any, encoded: Any) -> None:
        """A new frame of ``track`` while a page is open: note its times, then to each page
        by its transport."""
        st = self.tracks[track]
        if not self.pages.clients or frame.seq == st.seq:
            return
        st.note(frame, self.clock())
        if track == "us" and self.scan_frames is not None:  # (kept only while a scan is on)
            self.scan_frames.offer(frame)
        jpeg = False
        for c in list(self.pages.clients):
            if isinstance(c, ConsolePage):
                if c.transport == "webcodecs" and self.webcodecs is not None:
                    self.webcodecs.forward(c, track, frame, encoded)
                else:
                    jpeg = True
        if jpeg:  # the cine keeps the JPEGs the page draws
            self.jpeg.push(track, frame)
        elif self.webcodecs is not None:  # the cine keeps the decoded frame
            self.webcodecs.keep(track, frame)

    def keyframe_asked(self, client: ConsolePage, track: str) -> None:
        """The page's decoder of ``track`` lost its place."""
        client.need_key[track] = True
        if self.webcodecs is not None:
            self.webcodecs.keyframe_asked(client, track)

    def on_drawn(self, client: ConsolePage, m: Drawn, arrival: float) -> None:
        """The page drew frame ``m.seq`` of ``m.track`` (its echo came at ``arrival``)."""
        client.drawn(m.track, m.seq)
        client.echo_at[m.track] = time.monotonic()
        client.wake.set()
        refusal = self.tracks[m.track].on_drawn(m, arrival, client.last_drawn.get(m.track, -1))
        if refusal in (None, "implausible"):
            client.last_drawn[m.track] = m.seq
        if refusal is not None:
            self.refused[refusal] += 1

"""The console's WebCodecs transport (``transport = "webcodecs"``, the default): the encoded
frames the expert received (VP8 or H.264), forwarded as they are over the console's WebSocket
and decoded by the page's WebCodecs ``VideoDecoder``; the expert encodes nothing.

A page gets a track in order from a keyframe on (asked of the follower with a PLI when a page
opens or its decoder loses its place). A page cannot skip a delta frame, so what it has not
drawn is bounded: :data:`ENCODED_LAG` frames sent beyond the newest it drew and it gets no
more until it has drawn them, then the newest from a keyframe; :data:`ENCODED_BACKLOG`
queued in its socket and they are dropped up to the next keyframe. No ultrasound frame is
sent while frozen (the page shows the cine loop). The cine buffer keeps the expert's own
decode of the same frames (docs/console.md, "The video path").
"""

from __future__ import annotations

import time
from typing import Any

from humantele.expert.console.cine import CineBuffer, cine_frame
from humantele.expert.console.frames import TRACKS, FrameProvider
from humantele.expert.console.messages import FLAG_ENCODED, FLAG_H264, FLAG_KEYFRAME, frame_header
from humantele.expert.console.pageclient import ConsolePage
from humantele.expert.console.tracks import TrackFigures, depth0, spacing

ENCODED_BACKLOG = 12  # encoded frames of a track queued for a page; more: to the next keyframe
ENCODED_LAG = 8  # frames of a track sent to a page beyond the newest it drew: it is behind
ENCODED_LAG_S = 2.0  # ... unless it has drawn nothing for this long (then sent anyway)


class WebCodecsTransport:
    """Forwards encoded frames to the WebCodecs pages. ``frames``: a provider with encoded
    frames (``request_keyframe``); ``cine``: where the decoded US frames are kept."""

    def __init__(
        self,
        frames: FrameProvider,
        tracks: dict[str, TrackFigures],
        cine: CineBuffer,
        jpeg_quality: int,
    ) -> None:
        self.frames = frames
        self.tracks = tracks
        self.cine = cine
        self.jpeg_quality = jpeg_quality

    def opened(self, c: ConsolePage) -> None:
        """A page opened: each track from a keyframe."""
        for track in TRACKS:
            self.frames.request_keyframe(track)  # type: ignore[attr-defined]

    def keyframe_asked(self, c: ConsolePage, track: str) -> None:
        """The page's decoder of ``track`` lost its place: from the next keyframe."""
        c.need_key[track] = True
        self.frames.request_keyframe(track)  # type: ignore[attr-defined]

    def keep(self, track: str, frame: Any) -> None:
        """The cine keeps the decoded US frame (a JPEG only when looked at)."""
        if track == "us":
            self.cine.add(cine_frame(frame, None, self.jpeg_quality))

    def forward(self, c: ConsolePage, track: str, frame: Any, encoded: Any) -> None:
        """Send the encoded frame ``frame`` was decoded from to page ``c``, in order, from a
        keyframe on; a backlog is dropped up to the next keyframe."""
        st = self.tracks[track]
        if encoded is None:
            st.encoded_dropped += 1
            return
        prefix = f"enc:{track}:"
        queued = [k for k in c.pending if k.startswith(prefix)]
        if len(queued) >= ENCODED_BACKLOG:
            for k in queued:
                del c.pending[k]
            st.encoded_dropped += len(queued)
            c.need_key[track] = True
        if track == "us" and self.cine.frozen:  # the page shows the cine loop, not these
            c.need_key[track] = True
            st.encoded_dropped += 1
            return
        if self._behind(c, track):  # a page that cannot keep up: the newest, from a
            c.need_key[track] = True  # keyframe, once it has drawn what it has (its
            st.encoded_dropped += 1  # socket and its task queue are not a buffer)
            return
        if c.need_key[track] and not encoded.keyframe:
            st.encoded_dropped += 1
            self.frames.request_keyframe(track)  # type: ignore[attr-defined]
            return
        c.need_key[track] = False
        c.sent_seq[track] = frame.seq
        flags = FLAG_ENCODED | (FLAG_KEYFRAME if encoded.keyframe else 0)
        flags |= FLAG_H264 if encoded.codec.upper() == "H264" else 0
        header = frame_header(
            track, frame.seq, frame.t_capture, spacing(frame), frame.width, frame.height,
            depth0=depth0(frame), flags=flags,
        )  # fmt: skip
        c.encoded_sent += 1
        c.post(f"{prefix}{c.encoded_sent}", header + encoded.data)
        st.forwarded += 1

    def _behind(self, c: ConsolePage, track: str) -> bool:
        """Whether page ``c`` has ``ENCODED_LAG`` frames of ``track`` it was sent and has not
        drawn (nor drawn a newer one), and said it drew within ``ENCODED_LAG_S``."""
        sent, drawn = c.sent_seq.get(track), c.last_drawn.get(track)
        if sent is None or drawn is None or sent - drawn <= ENCODED_LAG:
            return False
        return time.monotonic() - c.echo_at.get(track, 0.0) < ENCODED_LAG_S

"""The sonographer's console: one aiohttp server on loopback, a page and a WebSocket.

``GET /`` is the page (:mod:`humantele.expert.console` ``web/``), ``GET /web/...`` its files,
``GET /ws`` the WebSocket (see :mod:`humantele.expert.console.messages`). While a page is
open (and only then) the server subscribes to each track of a
:class:`~humantele.expert.console.frames.FrameProvider` and gets each new frame as it comes
(no polling). How the page gets the pictures, ``transport`` (chosen by measurement:
docs/console.md, "The video path"; figures in docs/benchmarks.md):

- ``jpeg``: each frame JPEG-encoded from its I420 planes in a thread, latest wins
  (a slow page sees the newest frame, never a backlog: ``coalesced`` counts the frames it
  skipped); the cine buffer keeps the very bytes the page drew. Sim video (no encoded
  frames) always goes this way;
- ``webcodecs``, the default: the encoded frames the expert received (VP8), forwarded as
  they are over the WebSocket, decoded by the page's WebCodecs ``VideoDecoder``: the expert
  encodes nothing; the cine buffer keeps the expert's own decode of the same frames (a JPEG is made
  only of a frame the sonographer looks at or captures);
- ``webrtc``: the page as a WebRTC receiver, the expert forwarding the encoded frames
  (:mod:`humantele.expert.console.rtcpeer`).

A page may ask another transport (``/ws?...&transport=jpeg``: the A/B bench does).

The session's state (:class:`~humantele.expert.console.session.ConsoleSession`) goes to the
page ``state_rate_hz`` times a second with each track's age, so the page shows stale data as
stale. The page's tools (freeze and cine, calipers, annotations, capture) come back as
messages; each is recorded on ``/expert/console`` when the session records, and a capture is
saved in ``captures_dir`` (and attached to the recording).

Served on loopback only, plain http (a loopback page is a secure context): the console drives
the session (scans, clutch), so another machine reaches it through an SSH tunnel. Requests
whose ``Host`` is not a loopback name are refused (DNS rebinding), as are WebSockets from
another origin, a second console while one is open (``max_clients``), and page messages that
are malformed, unknown or too many; all are counted in ``refused`` and the daemon goes on.

Who may use it: the page's WebSocket must carry the run's key (:mod:`humantele.web.credential`;
``key``, else ``$HUMANTELE_CONSOLE_KEY``, else a new one each run), which the address the
expert prints has in its fragment (``http://127.0.0.1:8767/#key=...``); without it a local
process cannot drive the session nor take the one console's place. Connections are guarded
(:mod:`humantele.web.connguard`): a header deadline, caps in total and per address, the
credentialed page held outside them. Captures are capped in rate and in disk use
(``captures_per_minute``, ``captures_max_mb``); refusals are counted and shown on the page.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import functools
import json
import logging
import math
import threading
import time
from collections import Counter, OrderedDict, deque
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from aiohttp import web
from pydantic import Field, field_validator

from humantele.config import ConfigModel, DirectoryField, directory_problem
from humantele.expert.console.captures import (
    FailureLog,
    SessionItems,
    clip_path,
    name_clip,
    save_capture,
)
from humantele.expert.console.cine import CineBuffer, CineFrame
from humantele.expert.console.frames import TRACKS, FrameProvider
from humantele.expert.console.jpeg import I420Jpeg, frame_jpeg
from humantele.expert.console.messages import (
    FLAG_ENCODED,
    FLAG_H264,
    FLAG_KEYFRAME,
    MAX_PAGE_MESSAGE,
    PAGE_MESSAGE,
    Annotation,
    Caliper,
    Capture,
    CineRequest,
    ClutchCommand,
    Drawn,
    Freeze,
    KeyframeRequest,
    Ping,
    RtcAnswer,
    ScanCommand,
    frame_header,
    outside_image,
)
from humantele.expert.console.session import ConsoleSession
from humantele.runtime.stats import percentile_ms
from humantele.signaling.messages import is_loopback
from humantele.video.base import VideoFrame
from humantele.video.counter import unwrap
from humantele.web.connguard import GuardedPages
from humantele.web.credential import Credential, Verdict, key_from_env, new_key
from humantele.web.guard import MessageBudget
from humantele.web.pagesocket import Access, PageClient, PageLimits, PageSockets, validated
from humantele.web.static import add_page_files

log = logging.getLogger(__name__)

WEB_DIR = Path(str(resources.files("humantele.expert.console") / "web"))
LATENCIES_KEPT = 20000
IN_FLIGHT = 2  # frames of a track sent to a page and not yet drawn; more wait (latest wins)
CAPTURE_BURST = 10  # captures at once before captures_per_minute applies
IN_FLIGHT_TIMEOUT_S = 0.5  # a page that echoes nothing for this long gets the next frame
SEQS_KEPT = 256  # frames per track whose times are kept for the page's echoes
# A page that reads what it is sent this late (its pings say) gets the state and each track's
# frames once every PAGE_BEHIND_EVERY_S only (the newest) until it catches up: a busy
# browser's queue never grows to seconds, it still sees something, and the answers to its
# clicks (never held) reach it. A page that stops pinging is released.
PAGE_BEHIND_S = 1.0
PAGE_BEHIND_FOR_S = 2.0
PAGE_BEHIND_EVERY_S = 1.0
CLIP_FINISH_S = 20.0  # at stop, a clip being written gets this long to finish
TRANSPORTS = ("webcodecs", "jpeg", "webrtc")
ENCODED_BACKLOG = 12  # encoded frames of a track queued for a page; more: to the next keyframe
ENCODED_LAG = 8  # frames of a track sent to a page beyond the newest it drew: it is behind
ENCODED_LAG_S = 2.0  # ... unless it has drawn nothing for this long (then sent anyway)
_ASKED: contextvars.ContextVar[str | None] = contextvars.ContextVar("transport", default=None)


class ConsoleConfig(ConfigModel):
    """The console page (``[expert.console]``): where it is served and what it keeps."""

    enabled: bool = True
    host: str = Field("127.0.0.1", description="loopback only (an SSH tunnel for elsewhere)")
    port: int = Field(8767, ge=0, le=65535, description="0 picks a free one")
    video: str = Field(
        "auto",
        pattern=r"^(auto|received|sim|none)$",
        description="'received': the follower's tracks; 'sim': sim sources here (a stand-in); "
        "'auto': received when the daemon has a receiver, else sim; 'none'",
    )
    us_pixel_spacing_mm: tuple[float, float] | None = Field(
        None,
        description="(row, col) mm per pixel of the received ultrasound frames; None: no "
        "calipers (a sim or local source gives its own)",
    )
    us_depth_origin_row: float | None = Field(
        None,
        ge=-10000.0,
        le=10000.0,
        description="row (px) of depth 0 (the skin under the probe's face) in the received "
        "ultrasound frames: with the pixel spacing, the depth scale's cm labels; None: none",
    )
    transport: str = Field(
        "webcodecs",
        pattern=r"^(webcodecs|jpeg|webrtc)$",
        description="how the page gets received video: 'webcodecs' (the encoded frames, "
        "decoded by the page), 'jpeg' (a JPEG per frame, latest wins), 'webrtc' (the page a "
        "WebRTC peer); sim video is always JPEG (docs/console.md: why WebCodecs)",
    )
    jpeg_quality: int = Field(88, ge=30, le=100, description="JPEG frames and captures")
    state_rate_hz: float = Field(20.0, gt=0, le=100)
    stale_after_s: float = Field(1.0, gt=0, le=60, description="older video or pose: stale")
    cine_seconds: float = Field(10.0, gt=0, le=60)
    captures_dir: DirectoryField = Field(
        "~/.local/state/humantele/captures", description="captured frames and their poses"
    )
    max_clients: int = Field(1, ge=1, le=8, description="consoles at once; more are refused")
    page_rate_hz: float = Field(80.0, gt=0, le=1000, description="page messages a second")
    header_timeout_s: float = Field(
        10.0, gt=0, le=120, description="accept to a request's complete headers (then closed)"
    )
    max_connections: int = Field(
        64, ge=8, le=4096, description="open at once, besides the console's own page"
    )
    max_connections_per_address: int = Field(64, ge=2, le=4096)
    captures_per_minute: float = Field(
        30.0, gt=0, le=600, description="captures a minute on average (bursts of 10); more: refused"
    )
    captures_max_mb: float = Field(
        1000.0, gt=0, le=1e6, description="disk budget of captures_dir (MB); beyond: refused"
    )
    clip_seconds: float = Field(
        5.0, ge=0, le=60, description="Capture also keeps the cine's last seconds as an MP4 "
        "beside the still (0: stills only); in the same rate cap and disk budget",
    )  # fmt: skip

    @field_validator("us_pixel_spacing_mm")
    @classmethod
    def _spacing(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not all(math.isfinite(x) and 0.001 <= x <= 10.0 for x in v):
            raise ValueError(f"pixel spacing {v} mm: each must be within 0.001-10 mm")
        return v

    @field_validator("host")
    @classmethod
    def _loopback(cls, v: str) -> str:
        if not is_loopback(v):
            raise ValueError(
                f"the console is served on loopback only, not {v!r} (it drives the session; "
                "reach it from another machine through an SSH tunnel)"
            )
        return v


class _Client(PageClient):
    """A console page: the frames it was sent and has drawn."""

    def __init__(self, ws: web.WebSocketResponse, budget: MessageBudget) -> None:
        super().__init__(ws, budget)
        self.last_drawn: dict[str, int] = {}
        # Frames sent and not yet drawn, per track (seq, when sent): a page that draws slower
        # than frames come gets the newest when it is ready, not a queue in the socket.
        self.in_flight: dict[str, deque[tuple[int, float]]] = {t: deque() for t in TRACKS}
        self.behind_s = 0.0  # how late the page read our newest message, at its last ping
        self.behind_at = -math.inf  # when that ping came (time.monotonic)
        self.trickle: dict[str, float] = {}  # key -> when last sent while behind
        self.transport = "jpeg"
        self.need_key = dict.fromkeys(TRACKS, True)  # encoded: waiting for a keyframe
        self.encoded_sent = 0  # numbers the encoded frames' message keys (never coalesced)
        self.sent_seq: dict[str, int] = {}  # the newest encoded frame sent, per track
        self.echo_at: dict[str, float] = {}  # when the page last said it drew (loop clock)
        self.peer: Any = None  # the webrtc transport's PagePeer

    def behind(self, now: float) -> bool:
        """Whether the page is reading what it is sent more than PAGE_BEHIND_S late."""
        return self.behind_s > PAGE_BEHIND_S and now - self.behind_at < PAGE_BEHIND_FOR_S
        self.need_key = dict.fromkeys(TRACKS, True)  # encoded: waiting for a keyframe
        self.encoded_sent = 0  # numbers the encoded frames' message keys (never coalesced)
        self.sent_seq: dict[str, int] = {}  # the newest encoded frame sent, per track
        self.echo_at: dict[str, float] = {}  # when the page last said it drew (loop clock)

    def can_take(self, track: str, now: float, timeout_s: float) -> bool:
        q = self.in_flight[track]
        while q and now - q[0][1] > timeout_s:
            q.popleft()
        return len(q) < IN_FLIGHT

    def drawn(self, track: str, seq: int) -> None:
        q = self.in_flight[track]
        while q and q[0][0] <= seq:
            q.popleft()


class _Track:
    """What the server knows of one track: its last frame, when it came, its rate."""

    def __init__(self) -> None:
        self.seq: int | None = None
        self.t_capture: float | None = None
        self.t_seen: float | None = None
        self.size: tuple[int, int] | None = None
        self.spacing: tuple[float, float] | None = None
        self.depth0: float | None = None
        self.times: OrderedDict[int, tuple[float, float]] = OrderedDict()  # seq -> capture, seen
        self.arrivals: deque[float] = deque(maxlen=200)
        self.frames = 0
        self.jpegs = 0  # frames JPEG-encoded for a page
        self.forwarded = 0  # encoded frames sent to pages
        self.encoded_dropped = 0  # ... not sent (a backlog, waiting for a keyframe)
        self.encode_s: deque[float] = deque(maxlen=500)
        self.capture_to_draw: deque[float] = deque(maxlen=LATENCIES_KEPT)
        self.seen_to_draw: deque[float] = deque(maxlen=LATENCIES_KEPT)
        self.capture_to_seen: deque[float] = deque(maxlen=LATENCIES_KEPT)  # of those drawn
        self.drawn = 0
        self.counter_read = 0  # drawn frames whose counter the page read from its canvas
        self.counter_unread = 0  # ... did not read (no counter, or a smeared one)
        self.counter_unmatched = 0  # ... read a number whose frame is not known here

    def new_visit(self) -> None:
        """Forget the last page's figures (a page opens with none open)."""
        for q in (self.capture_to_draw, self.seen_to_draw, self.capture_to_seen, self.encode_s):
            q.clear()
        self.drawn = self.counter_read = self.counter_unread = self.counter_unmatched = 0
        self.frames = self.jpegs = self.forwarded = self.encoded_dropped = 0

    def rate_hz(self, now: float, window_s: float = 2.0) -> float:
        n = sum(1 for t in self.arrivals if now - t <= window_s)
        return round(n / window_s, 1)


class ConsoleServer:
    """The console's server. ``frames``: the video; ``session``: the session's state and
    commands; ``clock``: the expert's clock (the frames' ``t_capture`` are on it)."""

    def __init__(
        self,
        config: ConsoleConfig,
        frames: FrameProvider | None,
        session: ConsoleSession,
        clock=time.monotonic,
        video: str | None = None,
        on_demand: Any = None,
        key: str | None = None,
    ) -> None:
        self.config = config
        self.key = key or key_from_env() or new_key()
        self.video = "none" if frames is None else (video or config.video)
        # Sources that run only while a page is open (sim video: no CPU without a viewer):
        # ``start()`` when the first page connects, ``stop()`` when the last one leaves.
        self.on_demand = on_demand
        self.frames = frames
        self.session = session
        self.clock = clock
        self.port: int | None = None
        self.tracks = {t: _Track() for t in TRACKS}
        self.cine = CineBuffer(config.cine_seconds)
        self.refused: Counter[str] = Counter()
        limits = PageLimits(
            config.max_clients, config.page_rate_hz, MAX_PAGE_MESSAGE,
            "second_console", 409, "the console is open in another window\n",
        )  # fmt: skip
        access = Access(
            Credential(self.key, throttle=False), "key",  # 128 bits: nothing to throttle
            "this console's key is missing or wrong: open the address the expert printed "
            "(it ends in #key=...; each run has its own)",
        )  # fmt: skip
        self.pages = PageSockets(limits, self.refused, _Client, access)
        self.connections: Counter[str] = Counter()  # the connection guard's counts
        self.capture_budget = MessageBudget(config.captures_per_minute / 60.0, CAPTURE_BURST)
        self.captures_bytes: int | None = None  # in captures_dir, counted at the first capture
        self.site = GuardedPages("console", log, self.connections)
        self.events: Counter[str] = Counter()
        self.captures: list[str] = []
        self.items = SessionItems()  # captures and measurements, listed on the page
        self._file_key = Credential(self.key, throttle=False)  # the captured files' reads
        self.clips_writing = 0
        self._tasks: set[asyncio.Future] = set()
        self._clips: set[asyncio.Task] = set()  # clips being written
        self.capture_log = FailureLog(log, "capture")  # a full disk said once, not per capture
        self.clip_log = FailureLog(log, "clip")
        self.in_flight_timeout_s = IN_FLIGHT_TIMEOUT_S
        self._index = (WEB_DIR / "index.html").read_bytes()
        # Encoded frames to forward: a provider that has them (the WebRTC receiver's).
        self.encoded_video = frames is not None and hasattr(frames, "request_keyframe")
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._subscribed = False
        self._jpeg_next: dict[str, Any] = {}
        self._jpeg_busy: dict[str, bool] = dict.fromkeys(TRACKS, False)
        self._jpeg = {t: I420Jpeg(config.jpeg_quality) for t in TRACKS}
        self._subscribers = {t: functools.partial(self._from_provider, t) for t in TRACKS}

    @property
    def clients(self) -> set[PageClient]:
        """The console pages open now (at most ``max_clients``)."""
        return self.pages.clients

    @property
    def coalesced(self) -> int:
        """Unsent messages replaced by newer ones (frames a slow page skipped)."""
        return self.pages.coalesced

    @property
    def address(self) -> str:
        """The page's address without its key (for stats and logs)."""
        host = self.config.host
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}/"

    @property
    def url(self) -> str:
        """The page's address with its key (the fragment stays in the browser): what the
        sonographer opens."""
        return f"{self.address}#key={self.key}"

    @property
    def ws_url(self) -> str:
        """The WebSocket's URL with the key, for a tool on this machine."""
        return f"{self.address.replace('http', 'ws', 1)}ws?key={self.key}"

    def banner(self) -> str:
        return f"console {self.url}"

    # --- server ---------------------------------------------------------------------------

    async def start(self) -> None:
        cfg = self.config
        problem = directory_problem(cfg.captures_dir)  # said now, not at the first capture
        if problem:
            log.error("console: [expert.console] captures_dir %r %s: captures will be refused",
                      cfg.captures_dir, problem)  # fmt: skip

        def routes(app: web.Application) -> None:
            app.router.add_get("/", self._page)
            app.router.add_get("/ws", self._handle)
            app.router.add_get("/captures/{name}", self._captured_file)
            add_page_files(app, WEB_DIR)  # only its own files; any other name: 404

        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self.port = await self.site.start(routes, cfg, (self._host_guard,))
        self.pages.guard = self.site.guard
        self._spawn(self._pump_state())

    async def stop(self) -> None:
        self.pages.closing = True  # a page reconnecting now is turned away (cleanup waits)
        if self._clips:  # a clip being written is finished (and recorded), not cut short
            await asyncio.wait(list(self._clips), timeout=CLIP_FINISH_S)
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*list(self._tasks), return_exceptions=True)
        self._tasks.clear()
        self._unsubscribe()
        await self.pages.close_all()
        await self.site.stop()

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    @web.middleware
    async def _host_guard(self, request: web.Request, handler):
        if not is_loopback(_hostname(request.host or "")):
            self.refused["host"] += 1
            return web.Response(status=403, text="the console answers on loopback names only\n")
        return await handler(request)

    async def _page(self, request: web.Request) -> web.Response:
        return web.Response(
            body=self._index,
            content_type="text/html",
            charset="utf-8",
            headers={
                "Cache-Control": "no-cache",
                "Content-Security-Policy": (
                    "default-src 'self'; script-src 'self'; connect-src 'self'; "
                    "img-src 'self' data: blob:; style-src 'self'; object-src 'none'; "
                    "base-uri 'none'; frame-ancestors 'none'"
                ),
            },
        )

    # --- to the page ----------------------------------------------------------------------

    def _hold(self, client: PageClient, key: str, data: str | bytes) -> bool:
        """Whether a frame waits: its page has ``IN_FLIGHT`` frames of the track not yet
        drawn (the newest is sent when it draws one, or after the in-flight timeout)."""
        if not isinstance(client, _Client):
            return False
        now = time.monotonic()
        if (key == "state" or key.startswith("frame:")) and client.behind(now):
            if now - client.trickle.get(key, -math.inf) < PAGE_BEHIND_EVERY_S:
                self.events["held_page_behind"] += 1
                return True
            client.trickle[key] = now  # the newest, once a second
        track = key[6:] if key.startswith("frame:") else None
        if track not in TRACKS:
            return False
        if not client.can_take(track, now, self.in_flight_timeout_s):
            return True
        client.in_flight[track].append((int.from_bytes(data[4:8], "little"), now))
        return False

    # --- the frames, while a page is open ------------------------------------------------

    def _subscribe(self) -> None:
        if self._subscribed or self.frames is None or not hasattr(self.frames, "subscribe"):
            return
        self._subscribed = True
        for track in TRACKS:  # the figures are those of this page's visit
            self.tracks[track].new_visit()
            self.frames.subscribe(track, self._subscribers[track])

    def _unsubscribe(self) -> None:
        if not self._subscribed or self.frames is None:
            return
        self._subscribed = False
        for track in TRACKS:
            self.frames.unsubscribe(track, self._subscribers[track])
        for track in TRACKS:  # a stale picture must not be sent to the next page
            self._jpeg_next.pop(track, None)
        self.cine.clear()

    def _from_provider(self, track: str, frame: Any, encoded: Any) -> None:
        """A provider's new frame, from its thread or the loop: handled on the loop."""
        if threading.get_ident() == self._loop_thread:
            self._on_frame(track, frame, encoded)
        elif self._loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop closed: the daemon's end
                self._loop.call_soon_threadsafe(self._on_frame, track, frame, encoded)

    def _on_frame(self, track: str, frame: Any, encoded: Any) -> None:
        """A new frame of ``track`` while a page is open: note its times, then to each page
        by its transport (see the module doc)."""
        st = self.tracks[track]
        if not self.clients or frame.seq == st.seq:
            return
        seen = self.clock()
        # When the frame was there: the receiver's decode time (the expert's receipt of a
        # received frame), else now.
        there = getattr(frame, "t_received", None)
        there = seen if there is None or not math.isfinite(there) or there > seen else there
        st.seq, st.t_capture, st.t_seen = frame.seq, frame.t_capture, seen
        st.size, st.spacing = (frame.width, frame.height), _spacing(frame)
        st.depth0 = _depth0(frame)
        st.times[frame.seq] = (frame.t_capture, there)
        while len(st.times) > SEQS_KEPT:
            st.times.popitem(last=False)
        st.arrivals.append(seen)
        st.frames += 1
        jpeg = False
        for c in list(self.clients):
            if not isinstance(c, _Client):
                continue
            if c.transport == "webcodecs":
                self._forward(c, track, frame, encoded)
            elif c.transport == "webrtc":
                if c.peer is not None:
                    c.peer.push(track, frame, encoded)
            else:
                jpeg = True
        if jpeg:  # the cine keeps the JPEGs the page draws
            self._jpeg_next[track] = frame
            if not self._jpeg_busy[track]:
                self._jpeg_busy[track] = True
                self._spawn(self._jpeg_track(track))
        elif track == "us":  # the cine keeps the decoded frame; a JPEG when looked at
            cine = self._cine_frame(frame, None)
            if cine is not None:
                self.cine.add(cine)

    def _forward(self, c: _Client, track: str, frame: Any, encoded: Any) -> None:
        """Send the encoded frame ``frame`` was decoded from to a WebCodecs page, in order,
        from a keyframe on; a backlog is dropped up to the next keyframe."""
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
            self.frames.request_keyframe(track)  # type: ignore[union-attr]
            return
        c.need_key[track] = False
        c.sent_seq[track] = frame.seq
        flags = FLAG_ENCODED | (FLAG_KEYFRAME if encoded.keyframe else 0)
        flags |= FLAG_H264 if encoded.codec.upper() == "H264" else 0
        header = frame_header(
            track, frame.seq, frame.t_capture, _spacing(frame), frame.width, frame.height,
            depth0=_depth0(frame), flags=flags,
        )  # fmt: skip
        c.encoded_sent += 1
        c.post(f"{prefix}{c.encoded_sent}", header + encoded.data)
        st.forwarded += 1

    def _behind(self, c: _Client, track: str) -> bool:
        """Whether page ``c`` has ``ENCODED_LAG`` frames of ``track`` it was sent and has not
        drawn (nor drawn a newer one), and said it drew within ``ENCODED_LAG_S``."""
        sent, drawn = c.sent_seq.get(track), c.last_drawn.get(track)
        if sent is None or drawn is None or sent - drawn <= ENCODED_LAG:
            return False
        return time.monotonic() - c.echo_at.get(track, 0.0) < ENCODED_LAG_S

    async def _jpeg_track(self, track: str) -> None:
        """Encode the newest frame of ``track`` for the JPEG pages, one at a time, latest
        wins; ends when none waits."""
        st = self.tracks[track]
        try:
            while (frame := self._jpeg_next.pop(track, None)) is not None:
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
                for c in list(self.clients):
                    if isinstance(c, _Client) and c.transport == "jpeg":
                        if f"frame:{track}" in c.pending:
                            self.pages.coalesced += 1
                        c.post(f"frame:{track}", packet)
        finally:
            self._jpeg_busy[track] = False

    def _encode(self, track: str, frame: VideoFrame) -> tuple[bytes, CineFrame | None]:
        """The frame message (header + JPEG) and, for the ultrasound, its cine entry."""
        jpeg = frame_jpeg(frame, self.config.jpeg_quality, self._jpeg[track])
        header = frame_header(
            track, frame.seq, frame.t_capture, _spacing(frame), frame.width, frame.height,
            depth0=_depth0(frame),
        )  # fmt: skip
        return header + jpeg, self._cine_frame(frame, jpeg) if track == "us" else None

    def _cine_frame(self, frame: Any, jpeg: bytes | None) -> CineFrame | None:
        quality = self.config.jpeg_quality
        return CineFrame(
            frame.seq, frame.t_capture, jpeg, frame.width, frame.height, _spacing(frame),
            _depth0(frame), raw=None if jpeg is not None else frame,
            to_jpeg=lambda f: frame_jpeg(f, quality),
        )  # fmt: skip

    async def _pump_state(self) -> None:
        period = 1.0 / self.config.state_rate_hz
        while True:
            await asyncio.sleep(period)
            if not self.clients:
                continue
            try:
                snap = self.state()
            except Exception:  # noqa: BLE001 - the session's failure is shown, not raised
                self.refused["snapshot_error"] += 1
                log.exception("console: session snapshot failed")
                snap = {"type": "state", "error": "the expert daemon's state is unavailable"}
            self.pages.post("state", json.dumps(_clean(snap), separators=(",", ":")))

    def state(self) -> dict[str, Any]:
        """The ``state`` message: the session's snapshot, each track's age, the console's."""
        now = self.clock()
        snap = dict(self.session.snapshot())
        stale_ms = self.config.stale_after_s * 1000.0
        video = {}
        for track, st in self.tracks.items():
            age = None if st.t_capture is None else (now - st.t_capture) * 1000.0
            video[track] = {
                "seq": st.seq,
                "age_ms": age,
                "fps": st.rate_hz(now),
                "stale": age is None or age > stale_ms,
                "size": st.size,
                "spacing": st.spacing,  # (for the WebRTC transport, whose frames have no header)
                "depth0": st.depth0,
            }
        link = snap.get("link") or {}
        pose_age = link.get("pose_age_ms")
        link["stale"] = link.get("state") != "connected" or pose_age is None or pose_age > stale_ms
        snap["link"] = link
        if self.video == "sim" and link["stale"]:  # rendered from the follower's pose: no
            for v in video.values():  # fresh pose, no live picture
                v["stale"] = True
        snap.update(
            type="state",
            t=now,
            video=video,
            cine={"frozen": self.cine.frozen, "frames": len(self.cine)},
            captures={
                "saved": len(self.captures),
                "refused": self.refused["capture_rate"] + self.refused["capture_disk"],
                "clips_writing": self.clips_writing,
            },
            stale_after_ms=stale_ms,
        )
        return snap

    # --- from the page --------------------------------------------------------------------

    async def _handle(self, request: web.Request) -> web.StreamResponse:
        _ASKED.set(request.query.get("transport"))  # read by _on_open, in this task
        return await self.pages.serve(
            request, self.on_page_message, self._on_open, self._on_close,
            hold=self._hold, wake_every_s=self.in_flight_timeout_s,
        )  # fmt: skip

    def _on_open(self, client: PageClient) -> None:
        if len(self.clients) == 1 and self.on_demand is not None:
            self.on_demand.start()
        transport = "jpeg"
        if isinstance(client, _Client):
            asked = _ASKED.get()
            transport = asked if asked in TRANSPORTS else self.config.transport
            if not self.encoded_video:
                transport = "jpeg"  # sim or local sources: pictures, not encoded frames
            client.transport = transport
        self._subscribe()
        hello = {
            "type": "hello",
            "cine_seconds": self.config.cine_seconds,
            "stale_after_ms": self.config.stale_after_s * 1000.0,
            "video": self.video,
            "clip_seconds": self.config.clip_seconds,
            "transport": transport,
        }
        client.post("hello", json.dumps(hello))
        client.post("state", json.dumps(_clean(self.state())))
        client.post("items", self._items_message())
        if self.cine.frozen:
            client.post("cine", self._cine_index())
        if transport == "webrtc" and isinstance(client, _Client):
            self._spawn(self._offer(client))
        elif transport == "webcodecs":
            for track in TRACKS:
                self.frames.request_keyframe(track)  # type: ignore[union-attr]

    async def _offer(self, client: _Client) -> None:
        from humantele.expert.console.rtcpeer import PagePeer

        codec = getattr(getattr(getattr(self.frames, "receiver", None), "config", None),
                        "codec", "VP8")  # fmt: skip
        client.peer = PagePeer(codec, self.frames.request_keyframe)  # type: ignore[union-attr]
        sdp = await client.peer.offer()
        client.post("rtc_offer", json.dumps({"type": "rtc_offer", "sdp": sdp}))

    async def _on_close(self, client: PageClient) -> None:
        if isinstance(client, _Client) and client.peer is not None:
            await client.peer.close()
        if not self.clients:
            self._unsubscribe()
        if not self.clients and self.on_demand is not None:
            await asyncio.to_thread(self.on_demand.stop)

    def on_page_message(self, client: _Client, text: str) -> None:
        arrival = self.clock()
        m = validated(PAGE_MESSAGE, text, self.refused)
        if m is None:
            return
        if isinstance(m, Drawn):
            self._on_drawn(client, m, arrival)
        elif isinstance(m, Ping):  # answered at once: the page measures how late we are
            if m.behind_ms is not None:
                client.behind_s, client.behind_at = m.behind_ms / 1000.0, time.monotonic()
            client.post("pong", json.dumps({"type": "pong", "n": m.n, "t": self.clock()}))
        elif isinstance(m, ScanCommand):
            self._on_scan(client, m)
        elif isinstance(m, ClutchCommand):
            self.session.set_clutch(m.on)
            self.events["clutch_on" if m.on else "clutch_off"] += 1
            self._ack(client, "clutch", True, "held" if m.on else "released", m.id)
        elif isinstance(m, Freeze):
            self._on_freeze(m.on)
            self._ack(client, "freeze", True, "frozen" if m.on else "live", m.id)
        elif isinstance(m, CineRequest):
            self._on_cine(client, m.seq)
        elif isinstance(m, Caliper | Annotation | Capture):
            self._on_tool(client, m)
        elif isinstance(m, KeyframeRequest):
            client.need_key[m.track] = True
            self.events["keyframe_asked"] += 1
            if self.encoded_video:
                self.frames.request_keyframe(m.track)  # type: ignore[union-attr]
        elif isinstance(m, RtcAnswer):
            if client.peer is None:
                self.refused["unexpected_answer"] += 1
                return
            self._spawn(client.peer.answer(m.sdp))

    def _on_scan(self, client: _Client, m: ScanCommand) -> None:
        try:
            if m.action == "start":
                n = self.session.start_scan()
                detail = f"scan {n} started"
            else:
                self.session.stop_scan()
                detail = "scan stopped"
        except Exception as exc:  # noqa: BLE001 - said on the page, the daemon goes on
            log.exception("console: scan %s failed", m.action)
            self._ack(client, "scan", False, f"not done: {exc}", m.id)
            return
        self.events[f"scan_{m.action}"] += 1
        self._ack(client, "scan", True, detail, m.id)

    def _on_drawn(self, client: _Client, m: Drawn, arrival: float) -> None:
        client.drawn(m.track, m.seq)
        client.echo_at[m.track] = time.monotonic()
        client.wake.set()
        st = self.tracks[m.track]
        times = st.times.get(m.seq)
        if times is None:
            self.refused["unknown_frame"] += 1
            return
        if m.seq <= client.last_drawn.get(m.track, -1):
            self.refused["repeated_frame"] += 1
            return
        client.last_drawn[m.track] = m.seq
        d = m.draw_to_send_ms / 1000.0
        _, t_seen = times
        to_draw = arrival - d - t_seen
        if not -0.001 <= to_draw <= 10.0:
            self.refused["implausible"] += 1
            return
        st.drawn += 1
        st.seen_to_draw.append(max(0.0, to_draw))
        # Glass to glass as the page shows it: the counter read back from the page's canvas,
        # matched to that frame's capture time.
        if m.counter is None:
            st.counter_unread += 1
            return
        drawn = st.times.get(unwrap(m.counter, m.seq))
        if drawn is None:
            st.counter_unmatched += 1
            return
        st.counter_read += 1
        st.capture_to_draw.append(arrival - d - drawn[0])
        st.capture_to_seen.append(drawn[1] - drawn[0])

    def _on_freeze(self, on: bool) -> None:
        if on:
            self.cine.freeze()
        else:
            self.cine.resume()
        self.events["freeze" if on else "live"] += 1
        newest = self.cine.newest()
        self._record(
            "freeze" if on else "live",
            {} if newest is None else {"seq": newest.seq, "t_capture": newest.t_capture},
        )
        if on:
            self.pages.post("cine", self._cine_index())

    def _cine_index(self) -> str:
        t0 = self.cine.newest().t_capture if len(self.cine) else 0.0
        frames = [[seq, round(t - t0, 4)] for seq, t in self.cine.index()]
        return json.dumps({"type": "cine", "frozen": self.cine.frozen, "frames": frames})

    def _on_cine(self, client: _Client, seq: int) -> None:
        f = self.cine.get(seq)
        if f is None:
            self.refused["unknown_frame"] += 1
            self._result(client, "cine", False, f"frame {seq} is no longer in the cine buffer")
            return
        self._spawn(self._send_cine(client, f))

    async def _send_cine(self, client: _Client, f: CineFrame) -> None:
        try:
            jpeg = f.jpeg if f.jpeg is not None else await asyncio.to_thread(f.image_jpeg)
        except ValueError as exc:
            self.refused["bad_frame"] += 1
            self._result(client, "cine", False, f"frame {f.seq}: {exc}")
            return
        header = frame_header(
            "us", f.seq, f.t_capture, f.pixel_spacing_mm, f.width, f.height, cine=True,
            depth0=f.depth_origin_row,
        )  # fmt: skip
        client.post("frame:cine", header + jpeg)

    def _on_tool(self, client: _Client, m: Caliper | Annotation | Capture) -> None:
        f = self.cine.get(m.seq)
        if f is None:
            self.refused["unknown_frame"] += 1
            self._result(
                client, m.type, False, f"frame {m.seq} is no longer in the cine buffer", id=m.id
            )
            return
        base = {"seq": f.seq, "t_capture": f.t_capture}
        at = [m.a, m.b] if isinstance(m, Caliper) else [m.at] if isinstance(m, Annotation) else []
        off = outside_image(at, f.width, f.height)
        if off is not None:
            self.refused["outside_image"] += 1
            self._result(client, m.type, False, off, id=m.id)
            return
        if isinstance(m, Caliper):
            if f.pixel_spacing_mm is None:
                self._result(
                    client, "caliper", False,
                    "no pixel spacing for this image: set [expert.console] us_pixel_spacing_mm",
                    id=m.id,
                )  # fmt: skip
                return
            row, col = f.pixel_spacing_mm
            mm = math.hypot((m.b[0] - m.a[0]) * col, (m.b[1] - m.a[1]) * row)
            self.events["caliper"] += 1
            self._record("caliper", {**base, "mm": mm, "a_px": m.a, "b_px": m.b})
            self._result(client, "caliper", True, f"{mm:.1f} mm", mm=mm, seq=f.seq, id=m.id)
            self._add_item("caliper", f, mm=round(mm, 2), text=f"{mm:.1f} mm")
        elif isinstance(m, Annotation):
            text = " ".join(m.text.split())
            if not text:
                self._result(client, "annotation", False, "empty text", id=m.id)
                return
            self.events["annotation"] += 1
            self._record("annotation", {**base, "text": text, "a_px": m.at})
            self._result(client, "annotation", True, text, seq=f.seq, id=m.id)
            self._add_item("note", f, text=text)
        else:
            self._spawn(self._capture_when_encoded(client, f, base, m))

    async def _capture_when_encoded(
        self, client: _Client, f: CineFrame, base: dict[str, Any], m: Capture
    ) -> None:
        """The capture, once its frame is a JPEG (made in a thread, off the loop)."""
        if f.jpeg is None:
            try:
                await asyncio.to_thread(f.image_jpeg)
            except ValueError as exc:
                self.refused["capture_failed"] += 1
                self._result(client, "capture", False, f"not saved: {exc}", id=m.id)
                return
        self._capture(client, f, base, m)

    def _capture_refusal(self, directory: Path, size: int) -> str | None:
        """Why a capture of ``size`` bytes is refused now (counted), or None."""
        if self.captures_bytes is None:
            self.captures_bytes = _dir_bytes(directory)
        budget = self.config.captures_max_mb * 1e6
        if self.captures_bytes + size > budget:
            self.refused["capture_disk"] += 1
            return (
                f"not saved: the captures folder holds {self.captures_bytes / 1e6:.0f} MB of its "
                f"{self.config.captures_max_mb:g} MB budget (captures_max_mb); move some away"
            )
        if not self.capture_budget.take():
            self.refused["capture_rate"] += 1
            return (
                f"not saved: more than {self.config.captures_per_minute:g} captures a minute "
                "(captures_per_minute); wait a moment"
            )
        return None

    def _clip_frames(self, f: CineFrame, seconds: float) -> list[CineFrame]:
        """The cine's frames of the ``seconds`` up to ``f`` (oldest first)."""
        out = []
        for seq, t in self.cine.index():
            if seq <= f.seq and f.t_capture - t <= seconds:
                g = self.cine.get(seq)
                if g is not None:
                    out.append(g)
        return out

    def _capture(self, client: _Client, f: CineFrame, base: dict[str, Any], m: Capture) -> None:
        directory = Path(self.config.captures_dir).expanduser()
        assert f.jpeg is not None
        clip_s = min(m.clip_s, self.config.clip_seconds)
        clip = self._clip_frames(f, clip_s) if clip_s > 0 else []
        clip = clip if len(clip) >= 2 else []
        # The clip's size is bounded by its frames' JPEGs (its H.264 is smaller; a frame not
        # yet a JPEG counts as the still's size): the budget holds it.
        size = len(f.jpeg) + 1024 + sum(len(g.jpeg or f.jpeg) for g in clip)
        refusal = self._capture_refusal(directory, size)
        if refusal is not None:
            n = self.refused["capture_rate"] + self.refused["capture_disk"]
            self._result(client, "capture", False, f"{refusal} ({n} refused this run)", id=m.id)
            return
        pose = self.session.pose_at(f.t_capture)
        info: dict[str, Any] = {
            "seq": f.seq,
            "t_capture_s": f.t_capture,
            "pixel_spacing_mm": f.pixel_spacing_mm,
            "width": f.width,
            "height": f.height,
            "frame": "T_patient_probe: patient frame, m; quaternion (x, y, z, w)",
            "pose": pose,
        }
        rec = self.session.recorder
        if rec is not None:
            info["session_id"] = rec.metadata.get("session_id")
        try:
            path = save_capture(directory, f.seq, f.jpeg, _clean(info))
        except OSError as exc:
            self.refused["capture_failed"] += 1
            self.capture_log.failure(exc)
            self._result(client, "capture", False, f"not saved: {exc.strerror or exc}", id=m.id)
            return
        self.capture_log.success()
        self.events["capture"] += 1
        self.captures.append(str(path))
        self.captures_bytes = (self.captures_bytes or 0) + _file_bytes(path)
        payload = {**base, "file": path.name}
        if pose is not None:
            payload.update({k: v for k, v in pose.items() if k in _POSE_FIELDS})
        self._record("capture", payload)
        if rec is not None and hasattr(rec, "attach"):
            rec.attach(path.name, "image/jpeg", f.jpeg, f.t_capture)
        item = self._add_item("capture", f, file=path.name, clip=None, clip_pending=bool(clip))
        detail = path.name + (f" and a {clip_s:g} s clip (writing)" if clip else "")
        self._result(client, "capture", True, detail, seq=f.seq, file=str(path), id=m.id)
        if clip:
            task = asyncio.create_task(self._write_clip(client, path, clip, item, m.id))
            self._clips.add(task)
            task.add_done_callback(self._clips.discard)

    async def _write_clip(
        self, client: _Client, still: Path, frames: list[CineFrame], item: dict, cmd_id: int | None
    ) -> None:
        """The clip beside the still ``still`` (off the loop: ~6 ms a frame); the item and
        the page told when it is there, or why not."""
        from humantele.export.clip import write_clip

        path = clip_path(still)
        self.clips_writing += 1
        try:
            info = await asyncio.to_thread(  # (frames not yet JPEGs are made there too)
                lambda: name_clip(
                    still, write_clip([(g.t_capture, g.image_jpeg()) for g in frames], path)
                )
            )
        except (OSError, ValueError) as exc:
            self.refused["clip_failed"] += 1
            self.clip_log.failure(exc)
            item["clip_error"] = str(exc)[:200]
            self._result(client, "clip", False, f"clip not saved: {exc}", id=cmd_id)
        else:
            self.clip_log.success()
            self.events["clip"] += 1
            self.captures_bytes = (self.captures_bytes or 0) + _size(path)
            item.update(clip=path.name, clip_s=round(info.duration_s, 2), clip_frames=info.frames)
            self._record("clip", {"file": path.name, "still": still.name, "frames": info.frames,
                                  "duration_s": info.duration_s})  # fmt: skip
            self._result(client, "clip", True, f"{path.name} ({info.duration_s:.1f} s, "
                         f"{info.frames} frames)", file=str(path), id=cmd_id)  # fmt: skip
        finally:
            self.clips_writing -= 1
            item["clip_pending"] = False
        self.pages.post("items", self._items_message())

    def _add_item(self, kind: str, f: CineFrame, **fields: Any) -> dict[str, Any]:
        """One more capture or measurement in the session's list (the page is sent it)."""
        item = self.items.add(kind, f.seq, f.t_capture, **fields)
        self.pages.post("items", self._items_message())
        return item

    def _items_message(self) -> str:
        return json.dumps(_clean({"type": "items", "items": self.items.list()}))

    async def _captured_file(self, request: web.Request) -> web.StreamResponse:
        """A still or clip captured this run, for the page's list (with the run's key)."""
        verdict = self._file_key.check(request.query.get("key"), request.remote or "?")
        name = request.match_info["name"]
        known = {Path(c).name for c in self.captures} | self.items.clip_names()
        if verdict is not Verdict.OK:
            self.refused["unauthorized"] += 1
            raise web.HTTPUnauthorized(text="this console's key is missing or wrong\n")
        if name not in known:
            raise web.HTTPNotFound()
        path = Path(self.config.captures_dir).expanduser() / name
        if not path.is_file():
            raise web.HTTPNotFound()
        return web.FileResponse(path, headers={"Cache-Control": "no-store"})

    def _ack(self, client: _Client, of: str, ok: bool, detail: str, cmd_id: int | None) -> None:
        """The answer to a click that asked for one (``id``); the session's state shows the
        effect either way."""
        if cmd_id is not None:
            self._result(client, of, ok, detail, id=cmd_id)

    def _result(self, client: _Client, of: str, ok: bool, detail: str, **more: Any) -> None:
        msg = {"type": "result", "of": of, "ok": ok, "detail": detail, **more}
        if msg.get("id") is None:
            msg.pop("id", None)
            key = f"result:{of}"
        else:  # each click's answer is sent (not replaced by a later one's)
            key = f"result:{of}:{msg['id']}"
        client.post(key, json.dumps(_clean(msg)))

    def _record(self, event: str, payload: dict[str, Any]) -> None:
        rec = self.session.recorder
        if rec is not None:
            rec.write("/expert/console", self.clock(), {"event": event, **payload})

    # --- figures --------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "url": self.address if self.port else None,  # the key stays out of files
            "clients": len(self.clients),
            "sent": self.pages.sent,
            "coalesced": self.pages.coalesced,
            "refused": dict(self.refused),
            "refused_total": sum(self.refused.values()),
            "disconnects": self.pages.disconnects,
            "events": dict(self.events),
            "cine_frames": len(self.cine),
            "captures": len(self.captures),
            "captures_refused": self.refused["capture_rate"] + self.refused["capture_disk"],
            "connections": dict(self.connections),
            "transports": sorted({getattr(c, "transport", "?") for c in self.clients}),
            "subscribed": self._subscribed,
        }
        for track, st in self.tracks.items():
            out[track] = {
                "frames": st.frames,
                "jpegs": st.jpegs,
                "forwarded": st.forwarded,
                "encoded_dropped": st.encoded_dropped,
                "drawn": st.drawn,
                "encode_p50_ms": percentile_ms(st.encode_s, 50, ndigits=2),
                "seen_to_draw_p50_ms": percentile_ms(st.seen_to_draw, 50, ndigits=2),
                "seen_to_draw_p95_ms": percentile_ms(st.seen_to_draw, 95, ndigits=2),
                "capture_to_draw_p50_ms": percentile_ms(st.capture_to_draw, 50, ndigits=2),
                "capture_to_draw_p95_ms": percentile_ms(st.capture_to_draw, 95, ndigits=2),
                "capture_to_seen_p50_ms": percentile_ms(st.capture_to_seen, 50, ndigits=2),
                "capture_to_seen_p95_ms": percentile_ms(st.capture_to_seen, 95, ndigits=2),
                "counter_read": st.counter_read,
                "counter_unread": st.counter_unread,
                "counter_unmatched": st.counter_unmatched,
            }
        return out


_POSE_FIELDS = ("position", "quaternion", "virtual_position", "virtual_quaternion")


def _spacing(frame: Any) -> tuple[float, float] | None:
    spacing = getattr(frame, "pixel_spacing_mm", None)
    if spacing is not None and not all(math.isfinite(s) and s > 0 for s in spacing):
        return None
    return spacing


def _depth0(frame: Any) -> float | None:
    depth0 = getattr(frame, "depth_origin_row", None)
    return None if depth0 is None or not math.isfinite(depth0) else depth0


def _file_bytes(jpeg: Path) -> int:
    """Bytes of a capture on disk: its JPEG and its JSON side file."""
    total = 0
    for p in (jpeg, jpeg.with_suffix(".json")):
        try:
            total += p.stat().st_size
        except OSError:
            pass
    return total


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _dir_bytes(directory: Path) -> int:
    """Bytes of the capture files already in ``directory`` (0 if there is none)."""
    try:
        return sum(p.stat().st_size for p in directory.iterdir() if p.name.startswith("capture-"))
    except OSError:
        return 0


def _hostname(host: str) -> str:
    """The name in a ``Host`` header: ``[::1]:8767`` -> ``::1``, ``localhost:8767`` ->
    ``localhost``."""
    if host.startswith("["):
        return host[1:].split("]", 1)[0]
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def _clean(obj: Any) -> Any:
    """JSON-able copy with non-finite floats as null (JSON has no NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.generic):
        return _clean(obj.item())
    if hasattr(obj, "tolist"):
        return _clean(obj.tolist())
    return obj

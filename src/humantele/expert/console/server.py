"""The sonographer's console: one aiohttp server on loopback, a page and a WebSocket.

``GET /`` is the page (``web/``), ``GET /web/...`` its files, ``GET /captures/<name>`` this
run's captured files (:mod:`.captures`), ``GET /ws`` the WebSocket (:mod:`.messages`). While a
page is open (and only then) the server subscribes to each track of a
:class:`~humantele.expert.console.frames.FrameProvider` and gets each new frame as it comes
(no polling), notes its times (:mod:`.tracks`) and hands it to each page's transport, chosen
by measurement (docs/console.md, "The video path"):

- :mod:`.transport_webcodecs`, the default: the encoded frames the expert received,
  forwarded as they are, decoded by the page's WebCodecs; the expert encodes nothing;
- :mod:`.transport_jpeg`: a JPEG per frame, latest wins; sim video (no encoded frames)
  always, and a page that asks for it (``/ws?...&transport=jpeg``: a browser without
  WebCodecs, the A/B bench).

The parts, each its own module: the page's heartbeat (:mod:`.heartbeat`), the ultrasound
tools on the cine buffer (:mod:`.tools`), captures, clips and the session's list
(:mod:`.captures`), the replies to clicks and the session's commands (:mod:`.protocol`).
This module serves, subscribes, dispatches the page's messages and sends the session's state
(``state_rate_hz`` times a second, each track's age with it, so the page shows stale data as
stale).

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
credentialed page held outside them. Captures are capped in rate and in disk use.
"""

from __future__ import annotations

import asyncio
import contextvars
import json
import logging
import time
from collections import Counter
from importlib import resources
from pathlib import Path
from typing import Any

from aiohttp import web

from humantele.config import directory_problem
from humantele.expert.console import archive_routes
from humantele.expert.console.captures import Captures
from humantele.expert.console.cine import CineBuffer
from humantele.expert.console.config import ConsoleConfig
from humantele.expert.console.frames import FrameProvider
from humantele.expert.console.heartbeat import LoopStalls
from humantele.expert.console.messages import (
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
    ScanCommand,
)
from humantele.expert.console.pageclient import ConsolePage
from humantele.expert.console.protocol import ack, clean, session_command
from humantele.expert.console.session import ConsoleSession
from humantele.expert.console.tools import UltrasoundTools
from humantele.expert.console.video import PageVideo
from humantele.web.connguard import GuardedPages
from humantele.web.credential import Credential, key_from_env, new_key
from humantele.web.loopback import host_name, is_loopback
from humantele.web.pagesocket import Access, PageClient, PageLimits, PageSockets, validated
from humantele.web.static import add_page_files

__all__ = ["ConsoleConfig", "ConsoleServer", "WEB_DIR"]

log = logging.getLogger(__name__)

WEB_DIR = Path(str(resources.files("humantele.expert.console") / "web"))
_ASKED: contextvars.ContextVar[str | None] = contextvars.ContextVar("transport", default=None)
_CSP = (
    "default-src 'self'; script-src 'self'; connect-src 'self'; img-src 'self' data: blob:; "
    "style-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'"
)


class ConsoleServer:
    """The console's server. ``frames``: the video; ``session``: the session's state and
    commands; ``clock``: the expert's clock (the frames' ``t_capture`` are on it);
    ``monotonic``: this process's own (s), for how late a page reads (tests hold it still)."""

    def __init__(
        self,
        config: ConsoleConfig,
        frames: FrameProvider | None,
        session: ConsoleSession,
        clock=time.monotonic,
        video: str | None = None,
        on_demand: Any = None,
        key: str | None = None,
        monotonic=time.monotonic,
    ) -> None:
        self.config = config
        self.monotonic = monotonic
        self.key = key or key_from_env() or new_key()
        self.video = "none" if frames is None else (video or config.video)
        # Sources that run only while a page is open (sim video: no CPU without a viewer):
        # ``start()`` when the first page connects, ``stop()`` when the last one leaves.
        self.on_demand = on_demand
        self.frames = frames
        self.session = session
        self.clock = clock
        self.port: int | None = None
        self.cine = CineBuffer(config.cine_seconds)
        self.refused: Counter[str] = Counter()
        self.events: Counter[str] = Counter()
        limits = PageLimits(
            config.max_clients, config.page_rate_hz, MAX_PAGE_MESSAGE,
            "second_console", 409, "the console is open in another window\n",
        )  # fmt: skip
        access = Access(
            Credential(self.key, throttle=False), "key",  # 128 bits: nothing to throttle
            "this console's key is missing or wrong: open the address the expert printed "
            "(it ends in #key=...; each run has its own)",
        )  # fmt: skip
        self.pages = PageSockets(limits, self.refused, ConsolePage, access)
        self.connections: Counter[str] = Counter()  # the connection guard's counts
        self.site = GuardedPages("console", log, self.connections)
        self.captures = Captures(
            config, self.cine, session, self.pages, self.refused, self.events, self._record,
            self.key,
        )  # fmt: skip
        self.tools = UltrasoundTools(
            self.cine, self.captures, self.pages, self.refused, self.events, self._record,
            self._spawn,
        )  # fmt: skip
        self.video_out = PageVideo(
            config, frames, self.cine, self.pages, self.refused, self._spawn, clock
        )
        self.tracks = self.video_out.tracks  # each track's last frame and figures
        self._tasks: set[asyncio.Future] = set()
        self.stalls = LoopStalls(monotonic)  # how long our event loop was held up, for pongs
        self._index = (WEB_DIR / "index.html").read_bytes()

    @property
    def clients(self) -> set[PageClient]:
        """The console pages open now (at most ``max_clients``)."""
        return self.pages.clients

    @property
    def coalesced(self) -> int:
        """Unsent messages replaced by newer ones (frames a slow page skipped)."""
        return self.pages.coalesced

    @property
    def in_flight_timeout_s(self) -> float:
        """A JPEG page that echoes nothing for this long gets the next frame (s)."""
        return self.video_out.jpeg.in_flight_timeout_s

    @in_flight_timeout_s.setter
    def in_flight_timeout_s(self, value: float) -> None:
        self.video_out.jpeg.in_flight_timeout_s = value

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
            app.router.add_get("/captures/{name}", self.captures.serve_file)
            add_page_files(app, WEB_DIR)  # only its own files; any other name: 404
            archive_routes.add_routes(app, self.archive)  # the exam's archive (or "off")

        self.video_out.started()
        self.port = await self.site.start(routes, cfg, (self._host_guard,))
        self.pages.guard = self.site.guard
        self._spawn(self._pump_state())
        self._spawn(self.stalls.run())
        if self.archive is not None:
            await self.archive.start()

    async def stop(self) -> None:
        self.pages.closing = True  # a page reconnecting now is turned away (cleanup waits)
        await self.captures.finish()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*list(self._tasks), return_exceptions=True)
        self._tasks.clear()
        self.video_out.unsubscribe()
        await self.pages.close_all()
        await self.site.stop()
        if self.archive is not None:  # (after the clips: theirs are queued too)
            await self.archive.stop()

    @property
    def archive(self) -> Any:
        """The exam's archive (archive_routes.ConsoleArchive), or None when it is off."""
        return self.captures.archive

    @archive.setter
    def archive(self, archive: Any) -> None:
        self.captures.archive = archive
        self.video_out.scan_frames = getattr(archive, "scans", None)

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    @web.middleware
    async def _host_guard(self, request: web.Request, handler):
        if not is_loopback(host_name(request.host or "")):
            self.refused["host"] += 1
            return web.Response(status=403, text="the console answers on loopback names only\n")
        return await handler(request)

    async def _page(self, request: web.Request) -> web.Response:
        return web.Response(
            body=self._index, content_type="text/html", charset="utf-8",
            headers={"Cache-Control": "no-cache", "Content-Security-Policy": _CSP},
        )  # fmt: skip

    def _hold(self, client: PageClient, key: str, data: str | bytes) -> bool:
        """Whether a message waits: its page is behind (the heartbeat), or it is a JPEG frame
        and the page has frames of the track in flight."""
        if not isinstance(client, ConsolePage):
            return False
        now = self.monotonic()
        if client.lag.holds(key, now):
            self.events["held_page_behind"] += 1
            return True
        return self.video_out.jpeg.holds(client, key, data, now)

    # --- the session's state --------------------------------------------------------------

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
            self.pages.post("state", json.dumps(clean(snap), separators=(",", ":")))

    def state(self) -> dict[str, Any]:
        """The ``state`` message: the session's snapshot, each track's age, the console's."""
        now = self.clock()
        snap = dict(self.session.snapshot())
        stale_ms = self.config.stale_after_s * 1000.0
        video = {track: st.state(now, stale_ms) for track, st in self.tracks.items()}
        link = snap.get("link") or {}
        pose_age = link.get("pose_age_ms")
        link["stale"] = link.get("state") != "connected" or pose_age is None or pose_age > stale_ms
        snap["link"] = link
        if self.video == "sim" and link["stale"]:  # rendered from the follower's pose: no
            for v in video.values():  # fresh pose, no live picture
                v["stale"] = True
        captures = {"saved": len(self.captures.saved), "refused": self.captures.refused_count,
                    "clips_writing": self.captures.clips_writing}  # fmt: skip
        snap.update(
            type="state", t=now, video=video, captures=captures, stale_after_ms=stale_ms,
            cine={"frozen": self.cine.frozen, "frames": len(self.cine)},
        )  # fmt: skip
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
        if isinstance(client, ConsolePage):
            transport = client.transport = self.video_out.transport(_ASKED.get())
        self.video_out.subscribe()
        hello = {
            "type": "hello",
            "cine_seconds": self.config.cine_seconds,
            "stale_after_ms": self.config.stale_after_s * 1000.0,
            "video": self.video,
            "clip_seconds": self.config.clip_seconds,
            "transport": transport,
        }
        client.post("hello", json.dumps(hello))
        client.post("state", json.dumps(clean(self.state())))
        client.post("items", self.captures.items_message())
        if self.cine.frozen:
            client.post("cine", self.tools.cine_index())
        self.video_out.opened(client)

    async def _on_close(self, client: PageClient) -> None:
        if not self.clients:
            self.video_out.unsubscribe()
        if not self.clients and self.on_demand is not None:
            await asyncio.to_thread(self.on_demand.stop)

    def on_page_message(self, client: ConsolePage, text: str) -> None:
        """One message from page ``client`` (validated; anything else refused, counted)."""
        arrival = self.clock()
        m = validated(PAGE_MESSAGE, text, self.refused)
        if m is None:
            return
        if isinstance(m, Drawn):
            self.video_out.on_drawn(client, m, arrival)
        elif isinstance(m, Ping):  # answered at once: the page measures how late we are
            now = self.monotonic()
            pong = client.lag.on_ping(m, self.clock(), now, self.stalls.longest(now))
            client.post("pong", pong)
        elif isinstance(m, ScanCommand | ClutchCommand):
            session_command(self.session, client, m, self.events)
        elif isinstance(m, Freeze):
            self.tools.freeze(m.on)
            ack(client, "freeze", True, "frozen" if m.on else "live", m.id)
        elif isinstance(m, CineRequest):
            self.tools.send_cine(client, m.seq)
        elif isinstance(m, Caliper | Annotation | Capture):
            self.tools.use(client, m)
        elif isinstance(m, KeyframeRequest):
            self.events["keyframe_asked"] += 1
            self.video_out.keyframe_asked(client, m.track)

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
            "captures": len(self.captures.saved),
            "captures_refused": self.captures.refused_count,
            "connections": dict(self.connections),
            "transports": sorted({getattr(c, "transport", "?") for c in self.clients}),
            "subscribed": self.video_out.subscribed,
        }
        if self.archive is not None:  # counts only: no identity in the stats
            out["archive"] = {k: v for k, v in self.archive.status().items() if k != "last"}
        for track, st in self.tracks.items():
            out[track] = st.stats()
        return out

"""The follower's headset page and its feed: one aiohttp server, ``https`` by default.

``GET /`` is the headset page (:mod:`humantele.follower.web`, three.js vendored in the package);
``GET /web/...`` its files; ``path`` (``/feed``) the feed, a WebSocket on the same origin (a
``https`` page may only open ``wss://``). TLS uses the self-signed certificate kept in the
follower's state dir (:mod:`humantele.web.tls`); plain ``http``/``ws`` is allowed on loopback
only (``tls = false``, for tools and tests).

The feed sends one JSON object per text message, each with a ``type``. Frames: the follower's
**world** frame (the headset's: y up, metres), quaternions (x, y, z, w) as three.js uses them.

``virtual_probe``
    where to draw the virtual transducer: ``position`` (m) and ``quaternion`` of its tip frame
    (origin at the centre of the face, +z along the beam), ``age_ms`` since the expert sent it,
    ``stale`` (no fresh pose for a while or the link is down), ``clutch``, and ``pose_id``
    (new for each new pose; the page echoes it, see below).
``probe``
    the tracked real probe tip, world frame, with the measured force (N) and ``contact``;
    ``device_time_s``: the tracker frame's time on the device's clock, when it has one (which
    recorded frame a replay is at).
``model``
    the fitted patient ellipsoid: ``center`` (m), ``semi_axes`` (m, along the patient frame's
    x, y, z: body, up, lateral), ``quaternion`` (``T_world_patient``), ``bed_y`` (m); sent
    when a calibration exists and on each new one.
``calibration``
    calibration progress: ``step`` (landmark asked for, or null), ``prompt`` (what to do),
    ``event``/``message`` (the last landmark taken or refused, and why), ``calibrated``.
``link``
    the link to the expert: ``state`` (``connected``, ``connecting``, ``disconnected``).
``scan``
    the scan in progress (``scan``, or null).

Newer objects of a type replace older unsent ones (a slow page sees the latest pose, not a
backlog); ``coalesced`` counts those. A new client first gets the latest object of each type.

A page may send ``{"type": "drawn", "pose_id": N, "draw_to_send_ms": D}``:
it drew pose N (first time) and sent this D ms after its draw call. The feed's added latency
is then ``arrival - t_origin(N) - D``, where ``t_origin`` is when the follower received the
pose: an upper bound on pose receipt to draw call that includes the echo's own transit. An
echo later than ``LATE_ECHO_S`` (a starved browser) is counted in ``late_echoes``, apart from
the figures; one drawn before it was received is refused (``implausible``).
A page's ``registration`` and ``viewer_pose`` messages (:mod:`humantele.follower.registration`,
validated here) go to ``page_handler``; the feed publishes ``registration`` objects for them.
Anything else a page sends (malformed, unknown, a flood, an unknown or repeated id, a wrong
``Origin``, too many pages) is refused and counted in ``refused``; the daemon goes on. A page
lost (a reset, no answer to pings) is counted in ``lost``, and a client's TLS handshake that
failed or timed out (a loaded machine's browser, or a scanner) in ``handshake_failed``: neither
is a refusal.

Who may read the feed: a page with the follower's pairing code (:mod:`humantele.web.credential`:
eight digits, kept in the state dir, printed in :meth:`RendererFeed.banner`), which the page asks
for once and keeps; it goes on the feed's URL (``?code=``). A wrong one is refused (4401) and
counted, wrong guesses are throttled. Connections are guarded (:mod:`humantele.web.connguard`):
the TLS handshake and the request's headers within ``header_timeout_s`` of accept, caps in total
and per address, the paired pages held outside them.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import ipaddress
import json
import logging
import math
import re
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

from aiohttp import web
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, model_validator

from humantele.cliargs import socket_error
from humantele.config import ConfigModel, Port
from humantele.follower.registration import RegistrationMessage, ViewerPoseMessage
from humantele.runtime.stats import percentile_ms
from humantele.web.connguard import GuardedPages
from humantele.web.credential import (
    Credential,
    code_from_env,
    normalize_code,
    pairing_code,
    show_code,
)
from humantele.web.guard import MessageBudget
from humantele.web.loopback import is_loopback
from humantele.web.pagesocket import Access, PageClient, PageLimits, PageSockets, validated
from humantele.web.static import add_page_files
from humantele.web.tls import Certificate, HostName, ensure_certificate, local_hosts

log = logging.getLogger(__name__)
WEB_DIR = Path(str(resources.files("humantele.follower") / "web"))
TLS_SUBDIR = "tls"
MAX_PAGE_MESSAGE = 512  # bytes: a "drawn" echo is ~60
ORIGINS_KEPT = 1024  # pose ids whose receipt time is kept for the echoes
LATENCIES_KEPT = 20000
LATE_ECHO_S = 10.0  # an echo later than this: a stalled page, counted apart from the figures


class FeedConfig(ConfigModel):
    """Where the headset page and its feed are served (all interfaces, ``https``, by default:
    the headset is another device on the clinic's network; port 0 picks a free one)."""

    enabled: bool = True
    host: str = Field("0.0.0.0", description="address to listen on ('0.0.0.0': all)")
    port: Port = 8766
    path: str = Field(  # segments of safe characters: no "//", no "/.." nor "/."
        "/feed", max_length=200, pattern=r"^(/[A-Za-z0-9_-][A-Za-z0-9_.-]*)+$"
    )
    tls: bool = Field(True, description="https/wss with the self-signed certificate in state_dir")
    hosts: list[HostName] = Field(
        default_factory=list, description="more names for the certificate, e.g. a DNS name"
    )
    max_clients: int = Field(8, ge=1, le=256, description="pages at once; more are refused")
    page_rate_hz: float = Field(
        30.0, gt=0, le=1000, description="messages a page may send per second (more: dropped)"
    )
    header_timeout_s: float = Field(
        10.0, gt=0, le=120, description="accept to a request's complete headers, TLS included"
    )
    max_connections: int = Field(
        128, ge=8, le=4096, description="open at once, besides the paired pages"
    )
    max_connections_per_address: int = Field(32, ge=2, le=4096)

    @model_validator(mode="after")
    def _plain_only_on_loopback(self) -> FeedConfig:
        if not self.tls and not is_loopback(self.host):
            raise ValueError(
                f"tls = false serves plain http/ws: only on a loopback host, not {self.host!r}"
            )
        if self.path in ("/", "/web") or self.path.startswith("/web/"):
            raise ValueError(f"path {self.path!r} is taken by the page")
        return self


class DrawnEcho(BaseModel):
    """What a page sends: it drew pose ``pose_id`` and sent this ``draw_to_send_ms`` later."""

    model_config = ConfigDict(extra="forbid", strict=True)
    type: Literal["drawn"]
    pose_id: int = Field(ge=1)
    draw_to_send_ms: float = Field(ge=0.0, le=10_000.0, allow_inf_nan=False)


PAGE_MESSAGES = TypeAdapter(
    Annotated[DrawnEcho | RegistrationMessage | ViewerPoseMessage, Field(discriminator="type")]
)


def _clean(obj: Any) -> Any:
    """JSON-able copy with non-finite floats as null (JSON has no NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if hasattr(obj, "tolist"):
        return _clean(obj.tolist())
    return obj


def model_fields(ellipsoid: Any) -> dict[str, Any]:
    """The ``model`` object of a fitted :class:`humantele.haptics.ellipsoid.Ellipsoid` (world)."""
    T = ellipsoid.T_world_patient
    return {
        "center": T.position,
        "semi_axes": ellipsoid.semi_axes,
        "quaternion": T.quaternion,
        "bed_y": float(ellipsoid.center[1] - ellipsoid.semi_axes[1]),
    }


class _Client(PageClient):
    """A headset page: the last pose id it echoed."""

    def __init__(self, ws: web.WebSocketResponse, budget: MessageBudget) -> None:
        super().__init__(ws, budget)
        self.last_echo = 0


class RendererFeed:
    """The page and feed server; ``publish(kind, fields)`` from the daemon's event loop.

    ``cert_dir``: where the TLS certificate is kept (the follower's state dir); needed when
    ``config.tls`` is on."""

    def __init__(
        self, config: FeedConfig | None = None, cert_dir: str | Path | None = None
    ) -> None:
        self.config = config or FeedConfig()
        self.cert_dir = None if cert_dir is None else Path(cert_dir).expanduser() / TLS_SUBDIR
        self.certificate: Certificate | None = None
        self.state_dir = None if cert_dir is None else Path(cert_dir).expanduser()
        # The pairing code: from $HUMANTELE_PAIRING_CODE now (a malformed one: ValueError),
        # else read or made in the state dir by start() (an unwritable one: OSError there).
        self.code = pairing_code(None) if code_from_env() or self.state_dir is None else ""
        self.port: int | None = None
        self.latest: dict[str, str] = {}
        self.refused: Counter[str] = Counter()
        self.pages = PageSockets(
            PageLimits(self.config.max_clients, self.config.page_rate_hz, MAX_PAGE_MESSAGE),
            self.refused,
            _Client,
        )
        self.connections: Counter[str] = Counter()  # the connection guard's counts
        self.site = GuardedPages("headset page", log, self.connections)
        self.echoes = 0
        self.late_echoes = 0  # echoes over LATE_ECHO_S (not in the latency figures)
        self.latencies: deque[float] = deque(maxlen=LATENCIES_KEPT)  # s, receipt to draw
        self.pose_id = 0
        self._pose_key: str | None = None
        self._origins: OrderedDict[int, float] = OrderedDict()
        self._index: bytes = b""
        self._csp = ""

    # --- addresses ------------------------------------------------------------------------

    @property
    def clients(self) -> set[PageClient]:
        """The pages open now."""
        return self.pages.clients

    @property
    def disconnects(self) -> int:
        """Pages that have gone (closed, dropped or refused after opening)."""
        return self.pages.disconnects

    @property
    def coalesced(self) -> int:
        """Unsent objects replaced by newer ones of the same type."""
        return self.pages.coalesced

    @property
    def scheme(self) -> str:
        return "https" if self.config.tls else "http"

    def _local_host(self) -> str:
        h = self.config.host
        return "127.0.0.1" if h in ("", "0.0.0.0") else "::1" if h == "::" else h

    @property
    def address(self) -> str:
        """The feed's WebSocket URL for a tool on this machine, without the pairing code."""
        ws = "wss" if self.config.tls else "ws"
        return f"{ws}://{_url_host(self._local_host())}:{self.port}{self.config.path}"

    @property
    def url(self) -> str:
        """The feed's WebSocket URL for a tool on this machine, with the pairing code."""
        return f"{self.address}?code={self.code}"

    @property
    def page_url(self) -> str:
        """The page's URL for the headset: the first non-loopback address the certificate
        names (the machine's address on the clinic network), else loopback."""
        host = self._local_host()
        if self.certificate is not None and self.config.host in ("", "0.0.0.0", "::"):
            for h in self.certificate.hosts:
                try:
                    ip = ipaddress.ip_address(h)
                except ValueError:
                    continue
                if not ip.is_loopback and ip.version == 4:
                    host = h
                    break
        return f"{self.scheme}://{_url_host(host)}:{self.port}/"

    @property
    def fingerprint(self) -> str | None:
        return None if self.certificate is None else self.certificate.fingerprint_sha256

    def start_error(self, exc: OSError, state_dir: Path) -> str:
        """One line for a feed that cannot start (port taken, unknown host, unwritable
        certificate in ``state_dir``)."""
        if exc.filename is not None:  # the TLS certificate in the state directory
            return (
                f"humantele follower: renderer feed: cannot write {exc.filename}: "
                f"{exc.strerror or exc} (check --state-dir {state_dir})"
            )
        c = self.config
        return socket_error("humantele follower: renderer feed", c.host, c.port, exc)

    def banner(self) -> str:
        """One line for the console: where the page is and the certificate to check."""
        text = f"headset page {self.page_url}"
        if self.certificate is not None:
            text += f" (certificate SHA-256 {self.certificate.fingerprint_sha256})"
        return f"{text}, pairing code {show_code(self.code)}"

    # --- server ---------------------------------------------------------------------------

    async def start(self) -> None:
        """Serve; OSError if the state dir cannot hold the certificate or the pairing code,
        or the address cannot be bound."""
        if not self.code:
            self.code = await asyncio.to_thread(pairing_code, self.state_dir)
        self.pages.access = Access(
            Credential(self.code, normalize=normalize_code), "code",
            "pairing code missing or wrong: type the code the follower printed at its start",
        )  # fmt: skip
        ssl_context = None
        if self.config.tls:
            if self.cert_dir is None:
                raise ValueError("the feed serves TLS (tls = true) but has no cert_dir")
            hosts = local_hosts(self.config.host, self.config.hosts)
            self.certificate = await asyncio.to_thread(ensure_certificate, self.cert_dir, hosts)
            ssl_context = self.certificate.ssl_context()
        self._index, self._csp = _index_page(self.config.path)
        cfg = self.config

        def routes(app: web.Application) -> None:
            app.router.add_get("/", self._page)
            app.router.add_get(cfg.path, self._handle)
            add_page_files(app, WEB_DIR)  # only its own files; any other name: 404

        self.port = await self.site.start(routes, cfg, ssl_context=ssl_context)
        self.pages.guard = self.site.guard

    async def stop(self) -> None:
        await self.pages.close_all()
        await self.site.stop()

    async def _page(self, request: web.Request) -> web.Response:
        return web.Response(
            body=self._index,
            content_type="text/html",
            charset="utf-8",
            headers={"Cache-Control": "no-cache", "Content-Security-Policy": self._csp},
        )

    # --- to the pages ---------------------------------------------------------------------

    def publish(self, kind: str, fields: dict[str, Any], t_origin: float | None = None) -> None:
        """Send ``{"type": kind, **fields}`` to every client (latest wins per type).

        For ``virtual_probe``, a pose that differs from the last one gets a new ``pose_id``;
        ``t_origin`` (``time.monotonic()`` when the follower received it; default now) is what
        the page's echoes are measured from."""
        obj = _clean({"type": kind, **fields})
        if kind == "virtual_probe":
            key = json.dumps([obj.get("position"), obj.get("quaternion"), obj.get("clutch")])
            if key != self._pose_key:
                self._pose_key = key
                self.pose_id += 1
                self._origins[self.pose_id] = time.monotonic() if t_origin is None else t_origin
                while len(self._origins) > ORIGINS_KEPT:
                    self._origins.popitem(last=False)
            obj["pose_id"] = self.pose_id
        text = json.dumps(obj, separators=(",", ":"))
        self.latest[kind] = text
        self.pages.post(kind, text)

    # --- from the pages -------------------------------------------------------------------

    async def _handle(self, request: web.Request) -> web.StreamResponse:
        def on_open(client: PageClient) -> None:
            for kind, text in self.latest.items():  # a new page first gets the latest of each
                client.post(kind, text)

        return await self.pages.serve(request, self._on_page_message, on_open)

    # A page's ``registration`` and ``viewer_pose`` messages (validated) go to this handler
    # (the daemon's :class:`~humantele.follower.registration.HeadsetRegistration`); none set:
    # refused as ``unrouted``.
    page_handler: Callable[[dict[str, Any]], None] | None = None

    def _on_page_message(self, client: _Client, text: str) -> None:
        arrival = time.monotonic()
        msg = validated(PAGE_MESSAGES, text, self.refused)
        if msg is None:
            return
        if not isinstance(msg, DrawnEcho):
            if self.page_handler is None:
                self.refused["unrouted"] += 1
                return
            self.page_handler(msg.model_dump(mode="json"))
            return
        echo = msg
        t_origin = self._origins.get(echo.pose_id)
        if t_origin is None:
            self.refused["unknown_pose"] += 1
            return
        if echo.pose_id <= client.last_echo:
            self.refused["repeated_pose"] += 1
            return
        latency = arrival - t_origin - echo.draw_to_send_ms / 1000.0
        if latency < 0.0:  # drawn before it was received: a page that lies
            self.refused["implausible"] += 1
            return
        client.last_echo = echo.pose_id
        if latency > LATE_ECHO_S:  # a page stalled that long (a starved browser): said apart
            self.late_echoes += 1
            return
        self.echoes += 1
        self.latencies.append(latency)

    # --- figures --------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        """Counters and the latency figures (ms) for the daemon's stats."""
        return {
            "clients": len(self.clients),
            "url": self.address if self.port else None,  # the code stays out of files
            "page_url": self.page_url if self.port else None,
            "certificate_sha256": self.fingerprint,
            "sent": self.pages.sent,
            "coalesced": self.coalesced,
            "echoes": self.echoes,
            "late_echoes": self.late_echoes,
            "draw_latency_p50_ms": percentile_ms(self.latencies, 50),
            "draw_latency_p95_ms": percentile_ms(self.latencies, 95),
            "refused": dict(self.refused),
            "refused_total": sum(self.refused.values()),
            "disconnects": self.disconnects,
            "lost": dict(self.pages.lost),  # pages lost (reset, no answer): not refusals
            "handshake_failed": self.connections["closed:tls_failed"]
            + self.connections["closed:handshake_timeout"],  # a client's, not a refusal
            "connections": dict(self.connections),
        }


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


_IMPORT_MAP = re.compile(rb'<script type="importmap">(.*?)</script>', re.S)


def _index_page(feed_path: str) -> tuple[bytes, str]:
    """The page with the feed's path filled in, and its Content-Security-Policy (the inline
    import map allowed by its hash, nothing else inline)."""
    html = (WEB_DIR / "index.html").read_bytes().replace(b"{{FEED_PATH}}", feed_path.encode())
    hashes = " ".join(
        "'sha256-" + base64.b64encode(hashlib.sha256(m.group(1)).digest()).decode() + "'"
        for m in _IMPORT_MAP.finditer(html)
    )
    csp = (
        f"default-src 'self'; script-src 'self' {hashes}; connect-src 'self'; "
        "img-src 'self' data: blob:; style-src 'self'; object-src 'none'; base-uri 'none'"
    )
    return html, csp

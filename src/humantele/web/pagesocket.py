"""The WebSocket that a daemon's browser pages hold open: accept, send, listen, count.

Both daemons' pages (the expert's console, the follower's headset page) use one
:class:`PageSockets`: it refuses a page of another origin (403) and pages beyond
``max_clients``, gives each accepted page a :class:`PageClient` (a message budget and what
waits to be sent to it, latest per key: a slow page gets the newest, never a backlog), runs a
sender task per page, and reads what the page sends. A message over the budget is dropped
(``flood``; a page flooding ``FLOOD_CLOSE`` times in a row is closed), a binary one is
``malformed``, one over ``max_message`` bytes closes the page (``too_big``); a text message
goes to the server's handler, whose exception is counted (``failed``), never raised; a frame
that breaks the WebSocket protocol closes the page (``bad_frame``). When a page goes (closed
tab, network gone) its sender is cancelled and ``disconnects`` counts it. Everything refused is
counted in the server's ``refused`` counter; the daemon goes on.

A page lost is not a page refused: a connection reset, a TLS error on an open page, or a page
that answered no ping (:mod:`humantele.web.liveness`: judged on the daemon's own running time,
so a loaded machine's stalls do not close answering pages) is counted in ``lost`` by reason
(``reset``, ``tls``, ``no_answer``, ``socket_error``), apart from the refusals.

With an :class:`Access`, a page must carry the server's credential on its WebSocket's URL
(:mod:`humantele.web.credential`): without it, or with a wrong one, the socket is closed at once
with code 4401 and a reason the page shows (``unauthorized``), after too many wrong ones with
4429 (``throttled``); either way before it could take a page's place. An accepted page's
connection is then held outside the connection caps (:mod:`humantele.web.connguard`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import ssl
from collections import Counter
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from aiohttp import WebSocketError, WSCloseCode, WSMsgType, web
from pydantic import BaseModel, TypeAdapter, ValidationError

from humantele.web.connguard import GuardedServer
from humantele.web.credential import CLOSE_THROTTLED, CLOSE_UNAUTHORIZED, Credential, Verdict
from humantele.web.guard import MessageBudget, origin_allowed
from humantele.web.liveness import ANSWER_WITHIN_S, PING_EVERY_S, STEP_S, PageLiveness

log = logging.getLogger(__name__)

FLOOD_CLOSE = 600  # a page refused this many times in a row for flooding is closed
CLOSE_TIMEOUT_S = 5.0  # a page judged gone is closed without its answer after this long


@dataclass(frozen=True)
class PageLimits:
    """What a server takes from its pages: ``max_clients`` open at once (one more is refused
    with ``full_status``/``full_text`` and counted as ``full_reason``), ``rate_hz`` messages
    a second each (bursts of twice that), ``max_message`` bytes a message."""

    max_clients: int
    rate_hz: float
    max_message: int
    full_reason: str = "too_many_clients"
    full_status: int = 503
    full_text: str = "too many pages open\n"


@dataclass(frozen=True)
class Access:
    """A page's credential: ``credential`` checks the ``param`` query parameter of the
    WebSocket's URL; ``refusal``: what a page without it (or with a wrong one) is told."""

    credential: Credential
    param: str
    refusal: str


class PageClient:
    """One open page: its socket, its message budget and what waits to be sent to it
    (``pending``, key -> text or bytes, latest per key)."""

    def __init__(self, ws: web.WebSocketResponse, budget: MessageBudget) -> None:
        self.ws = ws
        self.budget = budget
        self.pending: dict[str, str | bytes] = {}
        self.wake = asyncio.Event()
        self.flooding = 0
        self.liveness = PageLiveness()

    def post(self, key: str, data: str | bytes) -> None:
        """Send ``data`` to this page (replacing unsent data of the same ``key``)."""
        self.pending[key] = data
        self.wake.set()


class PageSockets:
    """The pages of one server (see the module docstring). ``refused``: the server's refusal
    counter; ``make_client(ws, budget)``: a :class:`PageClient` (or a subclass with the
    server's per-page state). ``sent`` counts messages sent, ``coalesced`` unsent ones
    replaced by newer ones; ``lost`` counts pages lost by reason (not refusals). Each page is
    pinged after ``ping_every_s`` of silence and gone after ``answer_within_s`` more (of the
    daemon's running time, watched every ``step_s``: :mod:`humantele.web.liveness`)."""

    def __init__(
        self,
        limits: PageLimits,
        refused: Counter[str],
        make_client: Callable[[web.WebSocketResponse, MessageBudget], PageClient] = PageClient,
        access: Access | None = None,
    ) -> None:
        self.limits = limits
        self.access = access
        self.guard: GuardedServer | None = None  # the server's, once it listens
        self.refused = refused
        self.make_client = make_client
        self.clients: set[PageClient] = set()
        self.closing = False  # a page (re)connecting now is turned away
        self.sent = 0
        self.coalesced = 0
        self.disconnects = 0
        self.lost: Counter[str] = Counter()
        self.ping_every_s = PING_EVERY_S
        self.answer_within_s = ANSWER_WITHIN_S
        self.step_s = STEP_S

    def post(self, key: str, data: str | bytes) -> None:
        """Send ``data`` to every page (latest per ``key`` wins)."""
        for c in self.clients:
            if key in c.pending:
                self.coalesced += 1
            c.post(key, data)

    async def serve(
        self,
        request: web.Request,
        on_text: Callable[[PageClient, str], None],
        on_open: Callable[[PageClient], None] | None = None,
        on_close: Callable[[PageClient], Awaitable[None]] | None = None,
        hold: Callable[[PageClient, str, str | bytes], bool] | None = None,
        wake_every_s: float | None = None,
    ) -> web.StreamResponse:
        """Handle one page's WebSocket request to its end. ``on_open(client)`` when accepted
        (post its first messages there), ``on_text(client, text)`` for each text message
        within the budget, ``await on_close(client)`` once it has gone; ``hold`` and
        ``wake_every_s`` as in :meth:`send_loop`."""
        lim = self.limits
        if not origin_allowed(request):
            self.refused["origin"] += 1
            return web.Response(status=403, text="wrong origin\n")
        if self.closing:
            return web.Response(status=503, text="the daemon is stopping\n")
        if self.access is not None:
            refusal = await self._check_access(request, self.access)
            if refusal is not None:
                return refusal
        if len(self.clients) >= lim.max_clients:
            self.refused[lim.full_reason] += 1
            return web.Response(status=lim.full_status, text=lim.full_text)
        ws = web.WebSocketResponse(
            autoping=False, max_msg_size=lim.max_message, timeout=CLOSE_TIMEOUT_S
        )
        await ws.prepare(request)
        if self.guard is not None and self.access is not None:
            self.guard.established(request.protocol)  # type: ignore[arg-type]
        client = self.make_client(ws, MessageBudget(lim.rate_hz, max(1, int(2 * lim.rate_hz))))
        client.liveness = PageLiveness(self.ping_every_s, self.answer_within_s, self.step_s)
        self.clients.add(client)
        sender = watch = None
        try:
            if on_open is not None:
                on_open(client)
            sender = asyncio.create_task(self.send_loop(client, hold, wake_every_s))
            watch = asyncio.create_task(self._watch(client))
            async for msg in ws:
                client.liveness.heard()
                if msg.type == WSMsgType.ERROR:
                    self._ended_by_error(ws)
                    break
                if not client.budget.take():
                    self.refused["flood"] += 1
                    client.flooding += 1
                    if client.flooding >= FLOOD_CLOSE:
                        self.refused["closed_flooding"] += 1
                        await ws.close(code=WSCloseCode.POLICY_VIOLATION, message=b"flood")
                        break
                    continue
                client.flooding = 0
                if msg.type == WSMsgType.PING:
                    await ws.pong(msg.data)
                    continue
                if msg.type == WSMsgType.PONG:
                    continue
                if msg.type != WSMsgType.TEXT:
                    self.refused["malformed"] += 1
                    continue
                try:
                    on_text(client, msg.data)
                except Exception:  # noqa: BLE001 - never let a page end the daemon
                    self.refused["failed"] += 1
                    log.exception("page message failed")
        finally:
            self.clients.discard(client)
            self.disconnects += 1
            for task in (sender, watch):
                if task is not None:
                    task.cancel()
            await asyncio.gather(*(t for t in (sender, watch) if t), return_exceptions=True)
            if on_close is not None:
                await on_close(client)
        return ws

    def _ended_by_error(self, ws: web.WebSocketResponse) -> None:
        """Count why a page's socket failed: a refusal if the page broke the protocol (a frame
        too big, a bad frame), else a page lost (reset, TLS, other)."""
        exc = ws.exception()
        if _too_big(ws):
            self.refused["too_big"] += 1
        elif isinstance(exc, WebSocketError):
            self.refused["bad_frame"] += 1
        elif isinstance(exc, ssl.SSLError):
            self.lost["tls"] += 1
        elif isinstance(exc, ConnectionError):
            self.lost["reset"] += 1
        else:
            self.lost["socket_error"] += 1

    async def _watch(self, client: PageClient) -> None:
        """Ping a quiet page, close one that answers nothing (:mod:`humantele.web.liveness`)."""
        live = client.liveness
        try:
            while not client.ws.closed:
                await asyncio.sleep(live.step_s)
                verdict = live.step()
                if verdict == "ping":  # (a page that reads nothing may hold the drain)
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(client.ws.ping(), live.step_s)
                elif verdict == "gone":
                    self.lost["no_answer"] += 1
                    await client.ws.close(code=WSCloseCode.GOING_AWAY, message=b"no answer")
                    return
        except (ConnectionError, RuntimeError) as exc:
            log.debug("page gone: %s", exc)

    async def _check_access(
        self, request: web.Request, access: Access
    ) -> web.StreamResponse | None:
        """None if the request carries the credential; else the refusal, counted (a
        WebSocket is accepted and closed with the reason, so the page can say it)."""
        verdict = access.credential.check(request.query.get(access.param), request.remote or "?")
        if verdict is Verdict.OK:
            return None
        throttled = verdict is Verdict.THROTTLED
        self.refused["throttled" if throttled else "unauthorized"] += 1
        reason = (
            "too many wrong attempts: wait a minute, then try again"
            if throttled
            else access.refusal
        )
        ws = web.WebSocketResponse(timeout=2.0)
        if not ws.can_prepare(request).ok:
            return web.Response(status=429 if throttled else 401, text=reason + "\n")
        await ws.prepare(request)
        await ws.close(
            code=CLOSE_THROTTLED if throttled else CLOSE_UNAUTHORIZED,
            message=reason.encode()[:120],
        )
        return ws

    async def send_loop(
        self,
        client: PageClient,
        hold: Callable[[PageClient, str, str | bytes], bool] | None = None,
        wake_every_s: float | None = None,
    ) -> None:
        """Send what is pending to ``client`` whenever there is some, until it goes.
        ``hold(client, key, data)`` True keeps that message pending (sent when the page is
        woken again); ``wake_every_s``: look again at least this often (held messages)."""
        try:
            while not client.ws.closed:
                if wake_every_s is None:
                    await client.wake.wait()
                else:
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(client.wake.wait(), wake_every_s)
                client.wake.clear()
                batch, client.pending = client.pending, {}
                for key, data in batch.items():
                    if hold is not None and hold(client, key, data):
                        client.pending[key] = data
                        continue
                    if isinstance(data, bytes):
                        await client.ws.send_bytes(data)
                    else:
                        await client.ws.send_str(data)
                    self.sent += 1
        except (ConnectionError, RuntimeError) as exc:
            log.debug("page gone: %s", exc)

    async def close_all(self) -> None:
        """Turn new pages away and close the open ones."""
        self.closing = True
        for c in list(self.clients):
            with contextlib.suppress(Exception):
                await c.ws.close()


def validated(model: type[BaseModel] | TypeAdapter, text: str, refused: Counter[str]) -> Any:
    """``text`` as a page message of ``model`` (a pydantic model or a TypeAdapter), or None
    with ``refused["malformed"]`` counted."""
    try:
        if isinstance(model, TypeAdapter):
            return model.validate_json(text)
        return model.model_validate_json(text)
    except ValidationError:
        refused["malformed"] += 1
        return None


def _too_big(ws: web.WebSocketResponse) -> bool:
    exc = ws.exception()
    return getattr(exc, "code", None) == WSCloseCode.MESSAGE_TOO_BIG

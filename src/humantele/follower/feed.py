"""The follower's local feed for renderers: JSON objects over a WebSocket on loopback.

A renderer (the headset page later, a test, a debugging tool) connects to
``ws://HOST:PORT/feed`` and receives one JSON object per text message, each with a ``type``:

``virtual_probe``
    where to draw the virtual transducer: ``position`` (m) and ``quaternion`` (x, y, z, w) of
    its tip frame in the follower's **world** frame, ``age_ms`` since the expert sent it,
    ``stale`` (true when no fresh pose came for a while or the link is down: draw it greyed),
    ``clutch``.
``probe``
    the tracked real probe tip, world frame, with the measured force (N) and ``contact``.
``calibration``
    calibration progress: ``step`` (landmark asked for, or null), ``prompt`` (what to do),
    ``event``/``message`` (the last landmark taken or refused, and why), ``calibrated``.
``link``
    the link to the expert: ``state`` (``connected``, ``connecting``, ``disconnected``).

Newer objects of a type replace older unsent ones (a slow renderer sees the latest pose, not a
backlog); ``coalesced`` counts those. A new client first gets the latest object of each type.
Nothing a client sends is used; the feed never blocks the daemon.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from typing import Any

from aiohttp import WSMsgType, web
from pydantic import Field

from humantele.config import ConfigModel

log = logging.getLogger(__name__)


class FeedConfig(ConfigModel):
    """Where the renderer feed listens (loopback by default; port 0 picks a free one)."""

    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = Field(8766, ge=0, le=65535)
    path: str = Field("/feed", pattern=r"^/[A-Za-z0-9_/.-]*$")


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


class _Client:
    def __init__(self, ws: web.WebSocketResponse) -> None:
        self.ws = ws
        self.pending: dict[str, str] = {}
        self.wake = asyncio.Event()


class RendererFeed:
    """The WebSocket server; ``publish(kind, fields)`` from the daemon's event loop."""

    def __init__(self, config: FeedConfig | None = None) -> None:
        self.config = config or FeedConfig()
        self.port: int | None = None
        self.latest: dict[str, str] = {}
        self.clients: set[_Client] = set()
        self.sent = 0
        self.coalesced = 0
        self._runner: web.AppRunner | None = None

    @property
    def url(self) -> str:
        return f"ws://{self.config.host}:{self.port}{self.config.path}"

    async def start(self) -> None:
        app = web.Application()
        app.router.add_get(self.config.path, self._handle)
        self._runner = web.AppRunner(app, handle_signals=False, access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.config.host, self.config.port)
        await site.start()
        self.port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]

    async def stop(self) -> None:
        for c in list(self.clients):
            await c.ws.close()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    def publish(self, kind: str, fields: dict[str, Any]) -> None:
        """Send ``{"type": kind, **fields}`` to every client (latest wins per type)."""
        text = json.dumps(_clean({"type": kind, **fields}), separators=(",", ":"))
        self.latest[kind] = text
        for c in self.clients:
            if kind in c.pending:
                self.coalesced += 1
            c.pending[kind] = text
            c.wake.set()

    async def _handle(self, request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(heartbeat=5.0, max_msg_size=4096)
        await ws.prepare(request)
        client = _Client(ws)
        client.pending.update(self.latest)
        client.wake.set()
        self.clients.add(client)
        sender = asyncio.create_task(self._send_loop(client))
        try:
            async for msg in ws:  # nothing from a renderer is used; just notice it leave
                if msg.type == WSMsgType.ERROR:
                    break
        finally:
            self.clients.discard(client)
            sender.cancel()
            await asyncio.gather(sender, return_exceptions=True)
        return ws

    async def _send_loop(self, client: _Client) -> None:
        try:
            while not client.ws.closed:
                await client.wake.wait()
                client.wake.clear()
                batch, client.pending = client.pending, {}
                for text in batch.values():
                    await client.ws.send_str(text)
                    self.sent += 1
        except (ConnectionError, RuntimeError) as exc:
            log.debug("feed client gone: %s", exc)

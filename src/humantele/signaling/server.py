"""The signaling server (``humantele signal``): aiohttp WebSocket rooms of one expert and one
follower, relaying complete SDP offers and answers (protocol in :mod:`humantele.signaling`).

A bad peer only loses its own connection: a wrong or missing token, a full room, a malformed,
oversized or out-of-order message each close that socket with a reason; every other room keeps
working. Dead sockets are found by WebSocket pings every ``heartbeat_s``. The token is never
logged.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
from collections import Counter
from dataclasses import dataclass, field

from aiohttp import WSMsgType, web
from pydantic import Field, SecretStr

from humantele.config import ConfigError, ConfigModel, load_config
from humantele.signaling.messages import (
    CLIENT_MESSAGE,
    CLOSE_BAD_MESSAGE,
    CLOSE_JOIN_TIMEOUT,
    CLOSE_OUT_OF_ORDER,
    CLOSE_ROOM_FULL,
    CLOSE_SERVER_FULL,
    CLOSE_UNAUTHORIZED,
    DEV_TOKEN,
    SIGNALING_PROTOCOL,
    Answer,
    Error,
    Join,
    Joined,
    Offer,
    PeerJoined,
    PeerLeft,
    is_loopback,
    parse,
    resolve_token,
    token_matches,
)

log = logging.getLogger(__name__)


class SignalConfig(ConfigModel):
    """Signaling server settings (``configs/signal.toml``)."""

    host: str = "127.0.0.1"
    port: int = Field(8765, ge=0, le=65535)
    path: str = Field("/ws", pattern=r"^/[A-Za-z0-9_/.-]*$")
    token: SecretStr | None = None  # else $HUMANTELE_TOKEN, else the loopback-only dev token
    max_message_bytes: int = Field(65536, ge=1024, le=1 << 22)
    join_timeout_s: float = Field(5.0, gt=0, le=60)
    heartbeat_s: float = Field(2.0, gt=0, le=60)
    max_rooms: int = Field(1000, ge=1)


class _Refuse(Exception):
    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


@dataclass
class _Room:
    peers: dict[str, web.WebSocketResponse] = field(default_factory=dict)


class SignalingServer:
    """Rooms of two peers. ``await start()`` binds (``port`` then holds the bound port, useful
    with port 0); ``await stop()`` closes every socket. ``counters`` counts joins, refusals by
    reason and relayed messages."""

    def __init__(self, config: SignalConfig | None = None, token: str | None = None) -> None:
        self.config = config or SignalConfig()
        self._token = token if token is not None else resolve_token(self.config.token)
        if self._token == DEV_TOKEN and not is_loopback(self.config.host):
            raise ConfigError(
                "token: the development token is only allowed on a loopback host; "
                "set token or $HUMANTELE_TOKEN"
            )
        self.rooms: dict[str, _Room] = {}
        self.counters: Counter[str] = Counter()
        self._runner: web.AppRunner | None = None
        self.port: int | None = None

    def app(self) -> web.Application:
        app = web.Application()
        app.router.add_get(self.config.path, self._handle)
        return app

    @property
    def url(self) -> str:
        """ws:// URL clients connect to (after start)."""
        return f"ws://{self.config.host}:{self.port}{self.config.path}"

    async def start(self) -> None:
        self._runner = web.AppRunner(self.app(), handle_signals=False, access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.config.host, self.config.port)
        await site.start()
        self.port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
        log.info("signaling server listening on %s", self.url)

    async def stop(self) -> None:
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    async def _handle(self, request: web.Request) -> web.WebSocketResponse:
        cfg = self.config
        ws = web.WebSocketResponse(max_msg_size=cfg.max_message_bytes, heartbeat=cfg.heartbeat_s)
        await ws.prepare(request)
        where = request.remote or "?"
        joined: tuple[str, str] | None = None
        try:
            try:
                first = await asyncio.wait_for(ws.receive(), cfg.join_timeout_s)
            except TimeoutError:
                raise _Refuse(CLOSE_JOIN_TIMEOUT, "no join message in time") from None
            msg = self._message(first)
            if msg is None:
                return ws
            if not isinstance(msg, Join):
                raise _Refuse(CLOSE_OUT_OF_ORDER, f"first message must be join, not {msg.type}")
            joined = self._join(msg, ws, where)
            other = self._other(*joined)
            await ws.send_str(
                Joined(
                    room=msg.room, role=msg.role, peer_present=other is not None
                ).model_dump_json()
            )
            if other is not None:
                await self._send_quietly(other, PeerJoined(role=msg.role).model_dump_json())
            while True:
                msg = self._message(await ws.receive())
                if msg is None:
                    break
                await self._relay(msg, *joined)
        except _Refuse as refusal:
            self.counters[f"refused:{refusal.code}"] += 1
            log.info("signaling peer %s refused: %s", where, refusal.reason)
            if not ws.closed:
                await self._send_quietly(ws, Error(reason=refusal.reason).model_dump_json())
                await ws.close(code=refusal.code, message=refusal.reason[:120].encode())
        finally:
            if joined is not None:
                await self._leave(ws, *joined)
        return ws

    def _message(self, m) -> Join | Offer | Answer | None:
        """The parsed client message; None when the socket closed; _Refuse when malformed."""
        if m.type in (WSMsgType.CLOSE, WSMsgType.CLOSING, WSMsgType.CLOSED):
            return None
        if m.type == WSMsgType.ERROR:
            # aiohttp reports oversized frames (and protocol errors) this way and closes.
            self.counters["refused:error_frame"] += 1
            log.info("signaling socket error: %s", m.data)
            return None
        if m.type != WSMsgType.TEXT:
            raise _Refuse(CLOSE_BAD_MESSAGE, "messages must be JSON text")
        try:
            return parse(CLIENT_MESSAGE, m.data)  # type: ignore[return-value]
        except ValueError as exc:
            raise _Refuse(CLOSE_BAD_MESSAGE, f"malformed message: {exc}") from None

    def _join(self, msg: Join, ws: web.WebSocketResponse, where: str) -> tuple[str, str]:
        if not token_matches(msg.token, self._token):
            raise _Refuse(CLOSE_UNAUTHORIZED, "unauthorized: wrong or missing token")
        if msg.protocol != SIGNALING_PROTOCOL:
            raise _Refuse(
                CLOSE_BAD_MESSAGE,
                f"signaling protocol {msg.protocol} not supported (server speaks "
                f"{SIGNALING_PROTOCOL})",
            )
        room = self.rooms.get(msg.room)
        if room is None:
            if len(self.rooms) >= self.config.max_rooms:
                raise _Refuse(CLOSE_SERVER_FULL, "server full: too many rooms")
            room = self.rooms[msg.room] = _Room()
        if len(room.peers) >= 2:
            raise _Refuse(CLOSE_ROOM_FULL, "room full: it already has an expert and a follower")
        if msg.role in room.peers:
            raise _Refuse(CLOSE_ROOM_FULL, f"room full: it already has a {msg.role}")
        room.peers[msg.role] = ws
        self.counters["joined"] += 1
        log.info("room %s: %s joined from %s", msg.room, msg.role, where)
        return msg.room, msg.role

    def _other(self, room: str, role: str) -> web.WebSocketResponse | None:
        peers = self.rooms[room].peers
        return next((ws for r, ws in peers.items() if r != role), None)

    async def _relay(self, msg: Join | Offer | Answer, room: str, role: str) -> None:
        if isinstance(msg, Join):
            raise _Refuse(CLOSE_OUT_OF_ORDER, "already joined")
        if isinstance(msg, Offer) and role != "expert":
            raise _Refuse(CLOSE_OUT_OF_ORDER, "only the expert sends offers")
        if isinstance(msg, Answer) and role != "follower":
            raise _Refuse(CLOSE_OUT_OF_ORDER, "only the follower sends answers")
        other = self._other(room, role)
        if other is None:
            self.counters["dropped:no_peer"] += 1
            return
        await self._send_quietly(other, msg.model_dump_json())
        self.counters[f"relayed:{msg.type}"] += 1

    async def _leave(self, ws: web.WebSocketResponse, room: str, role: str) -> None:
        r = self.rooms.get(room)
        if r is None or r.peers.get(role) is not ws:
            return
        del r.peers[role]
        log.info("room %s: %s left", room, role)
        if not r.peers:
            del self.rooms[room]
            return
        for other in r.peers.values():
            await self._send_quietly(other, PeerLeft(role=role).model_dump_json())

    @staticmethod
    async def _send_quietly(ws: web.WebSocketResponse, text: str) -> None:
        """Send, ignoring a socket that is closing (its own handler cleans it up)."""
        if ws.closed:
            return
        try:
            await ws.send_str(text)
        except (ConnectionError, RuntimeError) as exc:
            log.debug("signaling send failed: %s", exc)


# --- command line -----------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="TOML/JSON file with the server settings")
    parser.add_argument("--host", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="TCP port (default 8765; 0 picks one)")


async def serve(config: SignalConfig, stop: asyncio.Event | None = None) -> None:
    """Run a server until ``stop`` is set (or forever)."""
    server = SignalingServer(config)
    await server.start()
    print(f"humantele signal: listening on {server.url}", flush=True)
    try:
        await (stop or asyncio.Event()).wait()
    finally:
        await server.stop()


def run(args: argparse.Namespace) -> int:
    config = load_config(SignalConfig, args.config)
    updates = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
    if updates:
        from humantele.config import validate_config

        config = validate_config(SignalConfig, {**config.model_dump(), **updates}, "command line")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        await serve(config, stop)

    asyncio.run(main())
    return 0

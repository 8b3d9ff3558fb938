"""The signaling server (``humantele signal``): aiohttp WebSocket rooms of one expert and one
follower, relaying complete SDP offers and answers (protocol in :mod:`humantele.signaling`).

A bad peer only loses its own connection: a wrong or missing token, a full room, a malformed,
oversized or out-of-order message each close that socket with a reason; every other room keeps
working. Every connection has a deadline at each stage: the WebSocket handshake (TLS included)
within ``handshake_timeout_s`` of accept, the join within ``join_timeout_s`` of the upgrade,
then a peer quiet for ``heartbeat_s`` is pinged and one that answers nothing for twice as long
is dropped, judged on the server's running time (:mod:`humantele.web.liveness`: aiohttp's own
heartbeat closed answering peers after a loop stall on a loaded machine). Open connections are
capped in total and per client address (:mod:`humantele.web.connguard`).

With ``tls_cert`` (and ``tls_key``) it serves ``wss://``; a non-loopback host without TLS is
refused unless ``insecure`` (for a server behind a TLS proxy, see docs/signaling.md). Logs quote
every client-supplied value and never show the token.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import ssl
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Self

from aiohttp import WSCloseCode, WSMsgType, web
from pydantic import Field, FilePath, SecretStr, model_validator

from humantele.cliargs import port, socket_error
from humantele.config import ConfigError, ConfigModel, Port, load_config, validate_config
from humantele.signaling.guard import (
    ACCEPT_BACKLOG,
    FD_RESERVE,
    AcceptErrorLog,
    GuardedServer,
    RateLimitedLog,
    fd_soft_limit,
)
from humantele.signaling.messages import (
    CLIENT_MESSAGE,
    CLOSE_BAD_MESSAGE,
    CLOSE_JOIN_TIMEOUT,
    CLOSE_OUT_OF_ORDER,
    CLOSE_ROOM_FULL,
    CLOSE_SERVER_FULL,
    CLOSE_UNAUTHORIZED,
    DEV_TOKEN,
    MAX_CLOSE_REASON_BYTES,
    SIGNALING_PROTOCOL,
    Answer,
    Error,
    IceServers,
    Join,
    Joined,
    Offer,
    PeerJoined,
    PeerLeft,
    clip_utf8,
    parse,
    resolve_token,
    safe_reason,
    token_matches,
)
from humantele.signaling.turn import TurnConfig, TurnIssuer
from humantele.web.liveness import PageLiveness, receive_answering, watch_socket
from humantele.web.loopback import is_loopback
from humantele.web.text import printable

log = logging.getLogger(__name__)


class SignalConfig(ConfigModel):
    """Signaling server settings (``configs/signal.toml``)."""

    host: str = "127.0.0.1"
    port: Port = 8765
    path: str = Field("/ws", pattern=r"^/[A-Za-z0-9_/.-]*$")
    token: SecretStr | None = None  # else $HUMANTELE_TOKEN, else the loopback-only dev token
    tls_cert: FilePath | None = None  # PEM certificate (chain): serve wss://
    tls_key: FilePath | None = None  # PEM private key of tls_cert (if not inside tls_cert)
    insecure: bool = False  # allow plain ws:// on a non-loopback host (behind a TLS proxy only)
    max_message_bytes: int = Field(65536, ge=1024, le=1 << 22)
    handshake_timeout_s: float = Field(10.0, gt=0, le=120)  # accept -> WebSocket upgrade
    join_timeout_s: float = Field(5.0, gt=0, le=60)  # upgrade -> join message
    heartbeat_s: float = Field(2.0, gt=0, le=60)
    max_rooms: int = Field(1000, ge=1)
    max_connections: int = Field(512, ge=2)  # open at once (lowered to fit `ulimit -n`)
    max_connections_per_address: int = Field(16, ge=2)  # from one client address
    turn: TurnConfig = Field(default_factory=TurnConfig)  # time-limited TURN credentials

    @model_validator(mode="after")
    def _tls_pair(self) -> Self:
        if self.tls_key is not None and self.tls_cert is None:
            raise ValueError("tls_key needs tls_cert")
        return self

    @property
    def scheme(self) -> str:
        return "ws" if self.tls_cert is None else "wss"


def server_tls_context(config: SignalConfig) -> ssl.SSLContext | None:
    """The TLS context serving ``config.tls_cert``; None without TLS; ConfigError naming the
    field if the certificate or key cannot be loaded."""
    if config.tls_cert is None:
        return None
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(config.tls_cert, config.tls_key)
    except (ssl.SSLError, OSError) as exc:
        field_name = "tls_cert" if config.tls_key is None else "tls_cert/tls_key"
        raise ConfigError(
            f"{field_name}: cannot load the certificate and key: {exc.strerror or exc}"
        ) from None
    return ctx


class _Refuse(Exception):
    def __init__(self, code: int, reason: str) -> None:
        reason = safe_reason(reason)  # it quotes client input: keep it one short line
        super().__init__(reason)
        self.code = code
        self.reason = reason


@dataclass
class _Room:
    peers: dict[str, web.WebSocketResponse] = field(default_factory=dict)


class SignalingServer:
    """Rooms of two peers. ``await start()`` binds (``port`` then holds the bound port, useful
    with port 0); ``await stop()`` closes every socket. ``counters`` counts joins, refusals by
    reason and relayed messages.

    With ``[turn]`` (or ``turn_issuer``) each admitted peer gets time-limited TURN credentials
    in its ``joined`` message, and fresh ones every ``ttl_s / 2`` while it stays
    (:mod:`humantele.signaling.turn`); a socket that is not admitted gets none."""

    def __init__(
        self,
        config: SignalConfig | None = None,
        token: str | None = None,
        *,
        turn_issuer: TurnIssuer | None = None,
    ) -> None:
        self.config = config or SignalConfig()
        # ConfigError (never showing the secret) if [turn] is on and its secret is unusable
        self._turn = turn_issuer or TurnIssuer.from_config(self.config.turn)
        self._token = token if token is not None else resolve_token(self.config.token)
        host = self.config.host
        if self._token == DEV_TOKEN and not is_loopback(host):
            raise ConfigError(
                "token: the development token is only allowed on a loopback host; "
                "set token or $HUMANTELE_TOKEN"
            )
        self._ssl = server_tls_context(self.config)
        if self._ssl is None and not is_loopback(host) and not self.config.insecure:
            raise ConfigError(
                f"host: {host} is not a loopback address and there is no TLS, so the token "
                "would cross the network in clear; set tls_cert and tls_key (--tls-cert, "
                "--tls-key) to serve wss://, or insecure = true (--insecure) only behind a TLS "
                "proxy (docs/signaling.md)"
            )
        self.rooms: dict[str, _Room] = {}
        self.counters: Counter[str] = Counter()
        self.guard: GuardedServer | None = None
        self._runner: web.ServerRunner | None = None
        self._listener: asyncio.Server | None = None
        self._accept_errors: AcceptErrorLog | None = None
        self._sockets: set[web.WebSocketResponse] = set()
        self._refusals = RateLimitedLog(log)
        self.port: int | None = None

    @property
    def url(self) -> str:
        """ws:// or wss:// URL clients connect to (after start)."""
        host = self.config.host
        host = f"[{host}]" if ":" in host else host
        return f"{self.config.scheme}://{host}:{self.port}{self.config.path}"

    def connection_cap(self) -> int:
        """``max_connections``, lowered to fit this process's descriptor limit."""
        cap = self.config.max_connections
        limit = fd_soft_limit()
        if limit is not None and cap > limit - FD_RESERVE:
            cap = max(2, limit - FD_RESERVE)
            log.warning(
                "signaling: max_connections lowered from %d to %d to fit the descriptor limit "
                "(ulimit -n %d)", self.config.max_connections, cap, limit,
            )  # fmt: skip
        return cap

    async def start(self) -> None:
        """Bind and serve; OSError if the address cannot be bound (in use, unresolvable)."""
        cfg = self.config
        loop = asyncio.get_running_loop()
        self.guard = GuardedServer(
            self._handle,
            max_connections=self.connection_cap(),
            max_per_address=cfg.max_connections_per_address,
            handshake_timeout_s=cfg.handshake_timeout_s,
            counters=self.counters,
            logger=log,
            access_log=None,
            keepalive_timeout=cfg.handshake_timeout_s,  # aiohttp's idle timer agrees with ours
            max_headers=64,
        )
        self._runner = web.ServerRunner(self.guard, shutdown_timeout=2.0)
        await self._runner.setup()
        try:
            self._listener = await loop.create_server(
                self.guard, cfg.host, cfg.port, ssl=self._ssl, backlog=ACCEPT_BACKLOG,
                ssl_handshake_timeout=cfg.handshake_timeout_s if self._ssl else None,
            )  # fmt: skip
        except BaseException:
            await self._runner.cleanup()
            self._runner = None
            raise
        self._accept_errors = AcceptErrorLog(loop, log, self.counters)
        self.port = self._listener.sockets[0].getsockname()[1]
        log.info("signaling server listening on %s", self.url)

    async def stop(self) -> None:
        """Stop listening, tell every connected peer the server is going away, close."""
        if self._listener is not None:
            self._listener.close()
        await asyncio.gather(
            *(
                ws.close(code=WSCloseCode.GOING_AWAY, message=b"server stopping")
                for ws in self._sockets
            ),
            return_exceptions=True,
        )
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self._listener is not None:
            await self._listener.wait_closed()
            self._listener = None
        if self._accept_errors is not None:
            self._accept_errors.remove()
            self._accept_errors = None

    async def _handle(self, request: web.BaseRequest) -> web.StreamResponse:
        cfg = self.config
        if request.path != cfg.path:
            return web.Response(status=404, text="not found\n")
        if request.method != "GET":
            return web.Response(status=405, text="method not allowed\n")
        ws = web.WebSocketResponse(
            max_msg_size=cfg.max_message_bytes, autoping=False, timeout=2.0
        )  # timeout: for the close handshake; pings: our watch (web.liveness)
        await ws.prepare(request)
        live = PageLiveness(cfg.heartbeat_s, 2.0 * cfg.heartbeat_s, min(0.5, cfg.heartbeat_s / 4))
        watch = asyncio.create_task(watch_socket(ws, live, self.counters))
        if self.guard is not None:
            self.guard.handshake_done(request.protocol)
        self._sockets.add(ws)
        where = request.remote or "?"
        joined: tuple[str, str] | None = None
        refresher: asyncio.Task | None = None
        try:
            try:
                first = await asyncio.wait_for(receive_answering(ws, live), cfg.join_timeout_s)
            except TimeoutError:
                raise _Refuse(CLOSE_JOIN_TIMEOUT, "no join message in time") from None
            msg = self._message(first)
            if msg is None:
                return ws
            if not isinstance(msg, Join):
                raise _Refuse(CLOSE_OUT_OF_ORDER, f"first message must be join, not {msg.type}")
            joined = self._join(msg, ws, where)
            other = self._other(*joined)
            peer_id = None if self._turn is None else self._turn.new_peer_id(msg.role)
            await ws.send_str(
                Joined(
                    room=msg.room, role=msg.role, peer_present=other is not None,
                    ice_servers=None if peer_id is None else self._issue(msg.room, peer_id),
                ).model_dump_json(exclude_none=True)
            )  # fmt: skip
            if peer_id is not None:
                refresher = asyncio.create_task(self._refresh_turn(ws, msg.room, peer_id))
            if other is not None:
                await self._send_quietly(other, PeerJoined(role=msg.role).model_dump_json())
            while True:
                msg = self._message(await receive_answering(ws, live))
                if msg is None:
                    break
                await self._relay(msg, *joined)
        except _Refuse as refusal:
            self.counters[f"refused:{refusal.code}"] += 1
            self._refusals.log(
                logging.INFO, refusal.code, "signaling peer %s refused: %s",
                printable(where), refusal.reason,
            )  # fmt: skip
            if not ws.closed:
                await self._send_quietly(ws, Error(reason=refusal.reason).model_dump_json())
                close_reason = clip_utf8(refusal.reason, MAX_CLOSE_REASON_BYTES)
                await ws.close(code=refusal.code, message=close_reason.encode())
        finally:
            watch.cancel()
            if refresher is not None:
                refresher.cancel()
            self._sockets.discard(ws)
            if joined is not None:
                await self._leave(ws, *joined)
        return ws

    def _issue(self, room: str, peer_id: str) -> list:
        """The ``ice_servers`` list of one admitted peer (a fresh credential); logged without
        the credential."""
        entry = self._turn.issue(peer_id)  # type: ignore[union-attr]
        self.counters["turn:issued"] += 1
        until = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(entry.expires))
        log.info("room %s: TURN credential for %s until %s UTC", room, peer_id, until)
        return [entry.model_dump(mode="json")]

    async def _refresh_turn(self, ws: web.WebSocketResponse, room: str, peer_id: str) -> None:
        """Send a joined peer a fresh credential every ``ttl_s / 2`` (before the last one
        expires), for the peer connections it makes later."""
        while not ws.closed:
            await asyncio.sleep(self._turn.refresh_after_s)  # type: ignore[union-attr]
            msg = IceServers(ice_servers=self._issue(room, peer_id))
            await self._send_quietly(ws, msg.model_dump_json())

    def _message(self, m) -> Join | Offer | Answer | None:
        """The parsed client message; None when the socket closed; _Refuse when malformed."""
        if m.type in (WSMsgType.CLOSE, WSMsgType.CLOSING, WSMsgType.CLOSED):
            return None
        if m.type == WSMsgType.ERROR:
            # aiohttp reports oversized frames (and protocol errors) this way and closes.
            self.counters["refused:error_frame"] += 1
            log.info("signaling socket error: %s", printable(str(m.data)))
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
    parser.add_argument("--port", type=port, help="TCP port (default 8765; 0 picks one)")
    parser.add_argument("--tls-cert", help="PEM certificate (chain): serve wss://")
    parser.add_argument("--tls-key", help="PEM private key of --tls-cert")
    parser.add_argument(
        "--insecure",
        action="store_true",
        default=None,
        help="allow plain ws:// on a non-loopback host (only behind a TLS proxy)",
    )


async def serve(config: SignalConfig, stop: asyncio.Event | None = None) -> None:
    """Run a server until ``stop`` is set (or forever)."""
    server = SignalingServer(config)
    await server.start()
    print(f"humantele signal: listening on {server.url}", flush=True)
    try:
        await (stop or asyncio.Event()).wait()
    finally:
        await server.stop()


def _bind_error(config: SignalConfig, exc: OSError) -> str:
    return socket_error("humantele signal", config.host, config.port, exc)


def run(args: argparse.Namespace) -> int:
    config = load_config(SignalConfig, args.config)
    flags = {
        "host": args.host,
        "port": args.port,
        "tls_cert": args.tls_cert,
        "tls_key": args.tls_key,
        "insecure": args.insecure,
    }
    updates = {k: v for k, v in flags.items() if v is not None}
    if updates:
        config = validate_config(SignalConfig, {**config.model_dump(), **updates}, "command line")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        await serve(config, stop)

    try:
        asyncio.run(main())
    except OSError as exc:
        print(_bind_error(config, exc), file=sys.stderr)
        return 1
    return 0

"""Signaling client: join a room, send offers/answers, receive what the server relays.

async with SignalingClient(url, room, role, token) as sig:
    joined = await sig.join()          # Joined(peer_present=...) or SignalingRefused
    await sig.send(Offer(sdp=..., id=1))
    msg = await sig.receive()          # PeerJoined | PeerLeft | Offer | Answer

``wss://`` URLs are verified against the system's CAs, or against ``ca_file`` (a PEM CA or
self-signed certificate) when given. Joining (TCP, TLS, WebSocket handshake, join, joined) must
finish within ``connect_timeout_s``, else SignalingError; :meth:`close` from another task ends a
join in progress the same way.
"""

from __future__ import annotations

import asyncio
import contextlib
import ssl
from pathlib import Path
from typing import Annotated

import aiohttp
from pydantic import AfterValidator, BaseModel, FilePath

from humantele.signaling.messages import (
    FATAL_CLOSE_CODES,
    SERVER_MESSAGE,
    SIGNALING_PROTOCOL,
    Answer,
    Error,
    Join,
    Joined,
    Offer,
    PeerJoined,
    PeerLeft,
    parse,
    printable,
)
from humantele.web.liveness import PageLiveness, receive_answering, watch_socket


def _loadable_ca(path: Path) -> Path:
    try:
        ssl.create_default_context(cafile=str(path))
    except (ssl.SSLError, ValueError) as exc:
        raise ValueError(f"{path} holds no PEM certificate: {exc}") from None
    return path


CaFile = Annotated[FilePath, AfterValidator(_loadable_ca)]
"""A config field's type: a PEM file of CA (or self-signed) certificates to trust for wss://."""


class SignalingError(ConnectionError):
    """The signaling connection failed or closed."""


class SignalingRefused(SignalingError):
    """The server refused us; ``reason`` says why, ``code`` is the close code, ``fatal`` is True
    when retrying cannot help (bad token, unsupported protocol)."""

    def __init__(self, reason: str, code: int | None) -> None:
        reason = printable(reason)  # the server's words end up in our log
        super().__init__(f"signaling refused: {reason}")
        self.reason = reason
        self.code = code

    @property
    def fatal(self) -> bool:
        return self.code in FATAL_CLOSE_CODES


class SignalingClient:
    """One WebSocket to the signaling server, for one peer in one room."""

    def __init__(
        self,
        url: str,
        room: str,
        role: str,
        token: str,
        *,
        ca_file: str | Path | None = None,
        connect_timeout_s: float = 10.0,
        heartbeat_s: float = 2.0,
        max_message_bytes: int = 1 << 20,
    ) -> None:
        self.url = url
        self.room = room
        self.role = role
        self._token = token
        self._ssl: ssl.SSLContext | bool = (
            True if ca_file is None else ssl.create_default_context(cafile=str(ca_file))
        )
        self._connect_timeout_s = connect_timeout_s
        self._heartbeat_s = heartbeat_s
        self._max = max_message_bytes
        self._session: aiohttp.ClientSession | None = None
        self._ws: aiohttp.ClientWebSocketResponse | None = None
        self._joining: asyncio.Task[Joined] | None = None
        self._live = PageLiveness()
        self._watch: asyncio.Task | None = None

    def __repr__(self) -> str:
        return f"SignalingClient({self.url!r}, room={self.room!r}, role={self.role!r})"

    async def __aenter__(self) -> SignalingClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def join(self) -> Joined:
        """Connect and join; SignalingRefused if the server says no, SignalingError if it cannot
        be reached, does not answer within ``connect_timeout_s``, or :meth:`close` is called."""
        self._joining = joining = asyncio.ensure_future(self._join())
        try:
            await asyncio.wait({joining}, timeout=self._connect_timeout_s)
        except asyncio.CancelledError:
            await self._abort(joining)
            raise
        finally:
            self._joining = None
        if not joining.done():
            await self._abort(joining)
            raise SignalingError(
                f"signaling server {self.url} did not answer within {self._connect_timeout_s:g} s"
            )
        if joining.cancelled():  # close() from another task
            await self.close()
            raise SignalingError("signaling connection closed while joining")
        return joining.result()

    async def _abort(self, joining: asyncio.Task[Joined]) -> None:
        joining.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await joining
        await self.close()

    async def _join(self) -> Joined:
        self._session = aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=None))
        try:
            self._ws = await self._session.ws_connect(
                self.url,
                ssl=self._ssl,
                autoping=False,  # pings: our watch (web.liveness), on running time
                max_msg_size=self._max,
                timeout=aiohttp.ClientWSTimeout(ws_close=2.0),
            )
        except (aiohttp.ClientError, OSError) as exc:
            await self.close()
            raise SignalingError(f"cannot reach signaling server {self.url}: {exc}") from None
        hb = self._heartbeat_s
        self._live = PageLiveness(hb, 2.0 * hb, min(0.5, hb / 4))
        self._watch = asyncio.create_task(watch_socket(self._ws, self._live))
        join = Join(room=self.room, role=self.role, token=self._token, protocol=SIGNALING_PROTOCOL)
        await self._ws.send_str(join.model_dump_json())
        reply = await self.receive()
        if not isinstance(reply, Joined):
            await self.close()
            raise SignalingError(f"expected joined, got {reply.type}")
        return reply

    async def send(self, msg: Offer | Answer) -> None:
        if self._ws is None or self._ws.closed:
            raise SignalingError("signaling connection is closed")
        try:
            await self._ws.send_str(msg.model_dump_json())
        except (ConnectionError, RuntimeError) as exc:
            raise SignalingError(f"signaling send failed: {exc}") from None

    async def receive(self) -> Joined | PeerJoined | PeerLeft | Offer | Answer:
        """The next server message; SignalingRefused on an error message, SignalingError when
        the connection closes or the server sends garbage."""
        if self._ws is None:
            raise SignalingError("not connected")
        m = await receive_answering(self._ws, self._live)
        if m.type != aiohttp.WSMsgType.TEXT:
            code = self._ws.close_code
            await self.close()
            raise SignalingError(f"signaling connection closed (code {code})")
        try:
            msg: BaseModel = parse(SERVER_MESSAGE, m.data)
        except ValueError as exc:
            await self.close()
            raise SignalingError(
                f"bad message from the signaling server: {printable(str(exc))}"
            ) from None
        if isinstance(msg, Error):
            # the close frame carries the code; read it
            close = await receive_answering(self._ws, self._live)
            code = close.data if close.type == aiohttp.WSMsgType.CLOSE else self._ws.close_code
            await self.close()
            raise SignalingRefused(msg.reason, code)
        return msg  # type: ignore[return-value]

    async def close(self) -> None:
        """Close the connection; a join in progress (in another task) ends with
        SignalingError."""
        if self._joining is not None and self._joining is not asyncio.current_task():
            self._joining.cancel()
        if self._watch is not None:
            self._watch.cancel()
            self._watch = None
        if self._ws is not None and not self._ws.closed:
            await self._ws.close()
        if self._session is not None:
            await self._session.close()
        self._ws = None
        self._session = None

    @property
    def closed(self) -> bool:
        return self._ws is None or self._ws.closed

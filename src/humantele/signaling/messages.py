"""Signaling messages (pydantic), close codes, and the deployment token.

The token is a shared secret per deployment: from configuration, else the environment variable
``HUMANTELE_TOKEN``, else a development token that only a loopback server accepts. It is never
logged or printed; compare it only with :func:`token_matches`.
"""

from __future__ import annotations

import hmac
import logging
import os
from typing import Annotated, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    JsonValue,
    SecretStr,
    TypeAdapter,
    ValidationError,
)

from humantele.web.text import printable

log = logging.getLogger(__name__)

SIGNALING_PROTOCOL = 1
TOKEN_ENV = "HUMANTELE_TOKEN"
DEV_TOKEN = "humantele-development-token"  # noqa: S105 - only accepted on loopback

# WebSocket close codes (4000-4999 are free for applications).
CLOSE_BAD_MESSAGE = 4400
CLOSE_UNAUTHORIZED = 4401
CLOSE_ROOM_FULL = 4403
CLOSE_JOIN_TIMEOUT = 4408
CLOSE_OUT_OF_ORDER = 4409
CLOSE_SERVER_FULL = 4503
FATAL_CLOSE_CODES = frozenset({CLOSE_UNAUTHORIZED, CLOSE_BAD_MESSAGE})
"""Refusals a client should not retry (retrying cannot help)."""

ROOM_PATTERN = r"^[A-Za-z0-9_.-]{1,64}$"
MAX_SDP_CHARS = 60_000
MAX_REASON_CHARS = 200
"""Longest ``error`` reason (characters)."""
MAX_CLOSE_REASON_BYTES = 123
"""Longest close-frame reason (UTF-8 bytes): RFC 6455 5.5 allows 125 payload bytes, 2 of them
the close code."""

Role = Literal["expert", "follower"]


class _Msg(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Join(_Msg):
    type: Literal["join"] = "join"
    room: Annotated[str, Field(pattern=ROOM_PATTERN)]
    role: Role
    token: Annotated[str, Field(max_length=512)] = ""
    protocol: int = SIGNALING_PROTOCOL

    def __repr__(self) -> str:  # never show the token
        return f"Join(room={self.room!r}, role={self.role!r}, protocol={self.protocol})"

    __str__ = __repr__


class Offer(_Msg):
    type: Literal["offer"] = "offer"
    sdp: Annotated[str, Field(min_length=1, max_length=MAX_SDP_CHARS)]
    id: Annotated[int, Field(ge=0)] = 0


class Answer(_Msg):
    type: Literal["answer"] = "answer"
    sdp: Annotated[str, Field(min_length=1, max_length=MAX_SDP_CHARS)]
    id: Annotated[int, Field(ge=0)] = 0


class Joined(_Msg):
    """The admission. ``ice_servers``: time-limited TURN credentials for this peer (entries
    of :class:`humantele.signaling.turn.IssuedIceServer`, checked one by one by the peer, so a
    bad entry is dropped without refusing the admission); absent when the server issues none."""

    type: Literal["joined"] = "joined"
    room: str
    role: Role
    peer_present: bool
    ice_servers: list[JsonValue] | None = None


class IceServers(_Msg):
    """Fresh TURN credentials for a joined peer (sent before the last ones expire); they
    replace the previous ones for the next peer connection."""

    type: Literal["ice_servers"] = "ice_servers"
    ice_servers: list[JsonValue]


class PeerJoined(_Msg):
    type: Literal["peer_joined"] = "peer_joined"
    role: Role


class PeerLeft(_Msg):
    type: Literal["peer_left"] = "peer_left"
    role: Role


class Error(_Msg):
    type: Literal["error"] = "error"
    reason: Annotated[str, Field(max_length=MAX_REASON_CHARS)]


ClientMessage = Annotated[Join | Offer | Answer, Field(discriminator="type")]
ServerMessage = Annotated[
    Joined | IceServers | PeerJoined | PeerLeft | Offer | Answer | Error,
    Field(discriminator="type"),
]
CLIENT_MESSAGE = TypeAdapter(ClientMessage)
SERVER_MESSAGE = TypeAdapter(ServerMessage)


def parse(adapter: TypeAdapter, text: str) -> BaseModel:
    """Validate one JSON message; ValueError with a short reason (never echoing the token)."""
    try:
        return adapter.validate_json(text)
    except ValidationError as exc:
        err = exc.errors(include_input=False)[0]
        loc = ".".join(str(p) for p in err["loc"]) or "(message)"
        raise ValueError(f"{loc}: {err['msg']}") from None


def clip_utf8(text: str, max_bytes: int) -> str:
    """The longest prefix of ``text`` whose UTF-8 encoding fits in ``max_bytes`` (never cuts a
    character in two)."""
    data = text.encode("utf-8", "backslashreplace")
    if len(data) <= max_bytes:
        return data.decode("utf-8")
    return data[:max_bytes].decode("utf-8", "ignore")


def safe_reason(text: str) -> str:
    """A refusal reason fit for a log line and an ``error`` message: printable, at most
    :data:`MAX_REASON_CHARS` characters."""
    text = printable(text)
    return text if len(text) <= MAX_REASON_CHARS else text[: MAX_REASON_CHARS - 3] + "..."


def resolve_token(configured: SecretStr | str | None) -> str:
    """The deployment token: configured value, else $HUMANTELE_TOKEN, else the development
    token (with a warning)."""
    if isinstance(configured, SecretStr):
        configured = configured.get_secret_value()
    if configured:
        return configured
    env = os.environ.get(TOKEN_ENV, "")
    if env:
        return env
    log.warning("no token configured and %s is unset: using the development token", TOKEN_ENV)
    return DEV_TOKEN


def token_matches(given: str, expected: str) -> bool:
    """Constant-time comparison of two tokens."""
    return hmac.compare_digest(given.encode("utf-8"), expected.encode("utf-8"))

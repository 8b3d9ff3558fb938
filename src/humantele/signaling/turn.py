"""Time-limited TURN credentials that the signaling server hands each admitted peer.

The scheme is coturn's ``use-auth-secret`` (the TURN REST API draft,
draft-uberti-behave-turn-rest-00; coturn's README.turnserver, "TURN REST API"): the signaling
server and every coturn server share one secret (coturn: ``static-auth-secret=...``); for a peer
the signaling server makes

    username   = "<unix expiry, s>:<peer id>"
    credential = base64(HMAC-SHA1(key = secret, message = username))

and coturn, which knows the secret, recomputes the credential from the username and refuses the
allocation once the timestamp is in the past (coturn ``userdb.c`` ``get_user_key``:
``turn_time_before(ts, time(NULL))``). Nothing long-lived sits on the peers' machines: what they
get expires after ``ttl_s``. An allocation made before the expiry keeps working after it
(coturn keeps the session's key, README.turnserver: "the original password becomes the session
parameter"); a new peer connection needs a fresh credential, so the server sends a new one to
each joined peer every ``ttl_s / 2`` (:class:`humantele.signaling.messages.IceServers`).

Server side: :class:`TurnConfig` (``[turn]`` of ``configs/signal.toml``), :func:`load_secret`,
:class:`TurnIssuer`. Peer side: :class:`IssuedIceServer` (the wire entry, validated with
pydantic) and :func:`accept_issued`. The secret is never logged, printed, put in a message or a
counter; the credential is only ever sent to the peer it was made for.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import logging
import os
import secrets
import stat
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Self

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    model_validator,
)

from humantele.config import ConfigError, ConfigModel

log = logging.getLogger(__name__)

TURN_SECRET_ENV = "HUMANTELE_TURN_SECRET"
MIN_SECRET_CHARS = 16
"""Shortest shared secret accepted (characters); ``openssl rand -hex 32`` gives 64."""
MAX_SECRET_CHARS = 512
MIN_TTL_S = 60.0
MAX_TTL_S = 86400.0  # the draft's recommended lifetime: one day
MAX_URLS = 8
MAX_ISSUED = 8
"""Most TURN server entries a peer takes from one message (the rest are dropped)."""
PEER_ID_PATTERN = r"^[A-Za-z0-9_.-]{1,64}$"
USERNAME_PATTERN = r"^[0-9]{1,12}:[A-Za-z0-9_.-]{1,64}$"
CREDENTIAL_PATTERN = r"^[A-Za-z0-9+/]{27}=$"  # base64 of the 20 bytes of an HMAC-SHA1


def rest_username(expires: int, peer_id: str) -> str:
    """The TURN REST username ``"<expires>:<peer_id>"`` (``expires``: unix time, s)."""
    return f"{int(expires)}:{peer_id}"


def rest_credential(secret: str, username: str) -> str:
    """base64(HMAC-SHA1(secret, username)): the password coturn computes for ``username``
    under ``use-auth-secret`` with ``static-auth-secret=<secret>``."""
    mac = hmac.new(secret.encode("utf-8"), username.encode("utf-8"), hashlib.sha1).digest()
    return base64.b64encode(mac).decode("ascii")


def _turn_url(url: str) -> str:
    if not url.startswith(("turn:", "turns:")):
        raise ValueError(f"{url[:80]!r} is not a turn: or turns: URL")
    if len(url) > 256 or not url.isprintable() or any(c.isspace() for c in url):
        raise ValueError(f"{url[:80]!r}: a URL of at most 256 printable characters, no spaces")
    return url


TurnUrl = Annotated[str, AfterValidator(_turn_url)]


class TurnConfig(ConfigModel):
    """``[turn]``: time-limited TURN credentials for the peers (off while ``urls`` is empty).

    ``urls``: the coturn servers the peers use, all sharing the secret (``turn:`` or
    ``turns:``). The secret comes from ``secret_file`` (its first line), else from
    $HUMANTELE_TURN_SECRET; it is the ``static-auth-secret`` of those servers. ``ttl_s``: how
    long a credential is valid (s); a fresh one goes to each joined peer every ``ttl_s / 2``.
    """

    urls: list[TurnUrl] = Field(default_factory=list, max_length=MAX_URLS)
    secret_file: Path | None = None
    ttl_s: float = Field(3600.0, ge=MIN_TTL_S, le=MAX_TTL_S)

    @model_validator(mode="after")
    def _secret_needs_urls(self) -> Self:
        if self.secret_file is not None and not self.urls:
            raise ValueError("secret_file is set but urls is empty: list the TURN servers")
        return self

    @property
    def enabled(self) -> bool:
        return bool(self.urls)


def _check_secret(secret: str, where: str) -> str:
    if not secret:
        raise ConfigError(f"turn: the shared secret in {where} is empty")
    if len(secret) < MIN_SECRET_CHARS:
        raise ConfigError(
            f"turn: the shared secret in {where} is {len(secret)} characters; at least "
            f"{MIN_SECRET_CHARS} are needed (make one with `openssl rand -hex 32`)"
        )
    if len(secret) > MAX_SECRET_CHARS:
        raise ConfigError(f"turn: the shared secret in {where} is over {MAX_SECRET_CHARS} chars")
    if not secret.isascii() or not secret.isprintable() or any(c.isspace() for c in secret):
        raise ConfigError(
            f"turn: the shared secret in {where} must be printable ASCII without spaces "
            "(as in coturn's static-auth-secret line)"
        )
    return secret


def load_secret(config: TurnConfig, environ: dict[str, str] | None = None) -> str | None:
    """The shared secret (None when ``config`` is off); ConfigError, which never shows the
    secret, if it cannot be read, is missing, empty, short or not printable ASCII."""
    if not config.enabled:
        return None
    env = os.environ if environ is None else environ
    path = config.secret_file
    if path is not None:
        where = f"turn.secret_file {str(path)!r}"
        try:
            mode = path.expanduser().stat().st_mode
            if not stat.S_ISREG(mode):  # a directory, or a FIFO that would block the read
                raise ConfigError(f"{where}: not a regular file")
            with open(path.expanduser(), encoding="utf-8") as f:
                text = f.read(MAX_SECRET_CHARS + 2)
        except (OSError, UnicodeDecodeError) as exc:
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise ConfigError(f"{where}: cannot read it: {why}") from None
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            log.warning("%s can be read by others (mode %o): chmod 600 it", where, mode & 0o777)
        lines = text.splitlines()
        return _check_secret(lines[0].strip() if lines else "", where)
    secret = env.get(TURN_SECRET_ENV)
    if secret is None:
        raise ConfigError(
            f"turn.urls: the TURN servers need their shared secret: set turn.secret_file or "
            f"${TURN_SECRET_ENV}"
        )
    return _check_secret(secret.strip(), f"${TURN_SECRET_ENV}")


class IssuedIceServer(BaseModel):
    """One TURN server entry as it crosses the wire (``joined`` and ``ice_servers`` messages),
    in the shape of the WebRTC ``RTCIceServer`` dictionary."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    urls: Annotated[list[TurnUrl], Field(min_length=1, max_length=MAX_URLS)]
    username: Annotated[str, Field(pattern=USERNAME_PATTERN)]
    credential: Annotated[str, Field(pattern=CREDENTIAL_PATTERN, repr=False)]

    @property
    def expires(self) -> int:
        """Unix time (s) after which coturn refuses this credential."""
        return int(self.username.split(":", 1)[0])

    def __str__(self) -> str:  # the credential never shows
        return f"{' '.join(self.urls)} as {self.username}"


def _signer(secret: str) -> Callable[[str], str]:
    """``rest_credential`` with the secret bound in a closure (not an attribute, so no
    ``repr``, ``vars`` or stats dump of the issuer shows it)."""

    def sign(username: str) -> str:
        return rest_credential(secret, username)

    return sign


class TurnIssuer:
    """Makes the credentials of :class:`TurnConfig` (the secret stays private to it).

    ``clock`` gives unix time (s); tests shift it to make credentials that have expired.
    """

    def __init__(
        self, config: TurnConfig, secret: str, clock: Callable[[], float] = time.time
    ) -> None:
        if not config.enabled:
            raise ValueError("TurnIssuer needs turn.urls")
        self.urls = list(config.urls)
        self.ttl_s = config.ttl_s
        self.refresh_after_s = config.ttl_s / 2.0
        self.clock = clock
        self._sign = _signer(_check_secret(secret, "the argument"))  # holds it out of vars()

    def __repr__(self) -> str:
        return f"TurnIssuer(urls={self.urls!r}, ttl_s={self.ttl_s:g})"

    @classmethod
    def from_config(cls, config: TurnConfig) -> TurnIssuer | None:
        """The issuer of ``config``, None when it is off; ConfigError as :func:`load_secret`."""
        secret = load_secret(config)
        return None if secret is None else cls(config, secret)

    @staticmethod
    def new_peer_id(role: str) -> str:
        """A fresh peer id for one admission: the role and 8 random hex digits (what coturn's
        log shows after the timestamp; the signaling server's log ties it to the room)."""
        return f"{role}-{secrets.token_hex(4)}"

    def issue(self, peer_id: str) -> IssuedIceServer:
        """A credential for ``peer_id`` valid until now + ``ttl_s``."""
        expires = int(self.clock() + self.ttl_s)
        username = rest_username(expires, peer_id)
        return IssuedIceServer(urls=self.urls, username=username, credential=self._sign(username))


def accept_issued(
    raw: list[Any] | None, now: float | None = None
) -> tuple[list[IssuedIceServer], list[str]]:
    """The valid, unexpired entries of a server's ``ice_servers`` list, and one line for each
    entry dropped (malformed, expired by this machine's clock, or beyond :data:`MAX_ISSUED`).
    The lines never show a credential."""
    now = time.time() if now is None else now
    good: list[IssuedIceServer] = []
    problems: list[str] = []
    for i, item in enumerate(raw or []):
        if i >= MAX_ISSUED:
            problems.append(f"entries beyond the first {MAX_ISSUED} dropped")
            break
        try:
            entry = IssuedIceServer.model_validate(item)
        except ValidationError as exc:
            err = exc.errors(include_input=False)[0]
            loc = ".".join(str(p) for p in err["loc"]) or "(entry)"
            problems.append(f"entry {i}: {loc}: {err['msg']}")
            continue
        if entry.expires <= now:
            problems.append(
                f"entry {i} ({entry.username}): expired {now - entry.expires:.0f} s ago by this "
                "machine's clock (are the clocks of this machine and the signaling server set?)"
            )
            continue
        good.append(entry)
    return good, problems

"""Who may use a daemon's page: the credential its WebSocket must carry.

The console's is a per-run key (:func:`new_key`), in the address the expert prints
(``http://127.0.0.1:8767/#key=...``: a fragment, which the browser never sends in a request;
the page passes it on its WebSocket). The headset page's is a pairing code (:func:`new_code`,
eight digits), printed by the follower beside its address and certificate fingerprint, typed
once on the headset and kept there. Either goes on the WebSocket's URL (``?key=`` /
``?code=``); :class:`Credential` compares it in constant time, throttles wrong guesses (per
client address and in total, so the eight digits cannot be tried in bulk; the total not for an
address that has given the right code, so a flood of wrong ones from other addresses does not
lock a paired headset out), and never logs it.
"""

from __future__ import annotations

import hmac
import logging
import os
import secrets
import time
from collections import OrderedDict
from collections.abc import Callable
from enum import Enum
from pathlib import Path

from humantele.config import ConfigError
from humantele.web.guard import MessageBudget

CONSOLE_KEY_ENV = "HUMANTELE_CONSOLE_KEY"
PAIRING_CODE_ENV = "HUMANTELE_PAIRING_CODE"
PAIRING_FILE = "pairing_code"
CODE_DIGITS = 8
CLOSE_UNAUTHORIZED = 4401  # WebSocket close code: missing or wrong credential
CLOSE_THROTTLED = 4429  # WebSocket close code: too many wrong ones, wait
ADDRESSES_KEPT = 1024
PAIRED_KEPT = 64  # addresses seen with the right code (headsets), the most recent kept

log = logging.getLogger(__name__)


def new_key() -> str:
    """A per-run console key (128 bits, URL-safe)."""
    return secrets.token_urlsafe(16)


def new_code() -> str:
    """A pairing code: ``CODE_DIGITS`` random digits."""
    return "".join(secrets.choice("0123456789") for _ in range(CODE_DIGITS))


def normalize_code(text: str) -> str:
    """A typed code without the spaces and dashes people add (``1234 5678``)."""
    return "".join(ch for ch in text if ch not in " -\t")


def show_code(code: str) -> str:
    """The code as printed: two groups of four (``1234 5678``)."""
    return f"{code[:4]} {code[4:]}" if len(code) == CODE_DIGITS else code


def valid_code(code: str) -> bool:
    return len(code) == CODE_DIGITS and code.isascii() and code.isdigit()


def key_from_env() -> str | None:
    """The console key the caller chose (``$HUMANTELE_CONSOLE_KEY``: the demo, supervisors),
    or None; ConfigError if it is too short to be a secret."""
    key = os.environ.get(CONSOLE_KEY_ENV)
    if key is None:
        return None
    if len(key) < 16 or not key.isascii() or not key.isprintable() or " " in key:
        raise ConfigError(f"${CONSOLE_KEY_ENV}: at least 16 printable ASCII characters")
    return key


def code_from_env() -> str | None:
    """``$HUMANTELE_PAIRING_CODE`` (spaces and dashes dropped), None if unset; ValueError if
    it is not ``CODE_DIGITS`` digits (ConfigError)."""
    env = os.environ.get(PAIRING_CODE_ENV)
    if env is None:
        return None
    code = normalize_code(env)
    if not valid_code(code):
        raise ConfigError(f"${PAIRING_CODE_ENV}: {CODE_DIGITS} digits, not {len(code)} characters")
    return code


def pairing_code(state_dir: Path | None) -> str:
    """The follower's pairing code: ``$HUMANTELE_PAIRING_CODE`` if set, else the one kept in
    ``state_dir`` (created there, owner-only, on first use: a headset paired once stays
    paired across restarts), else a new one for this run (also when the state dir cannot
    hold it: logged). ValueError for a malformed ``$HUMANTELE_PAIRING_CODE``."""
    code = code_from_env()
    if code is not None:
        return code
    if state_dir is None:
        return new_code()
    path = state_dir / PAIRING_FILE
    try:
        code = normalize_code(path.read_text(encoding="ascii").strip())
        if valid_code(code):
            return code
    except (OSError, UnicodeDecodeError):
        pass
    code = new_code()
    try:
        state_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as f:
            f.write(code + "\n")
    except OSError as exc:  # best effort: this run's code still pairs
        log.warning(
            "pairing code not kept in %s (%s): a new one at the next start", path,
            exc.strerror or exc,
        )  # fmt: skip
    return code


def _has_token(b: MessageBudget) -> bool:
    """Whether ``b`` has a whole token now (refilled, none taken)."""
    now = b.clock()
    b.tokens = min(b.burst, b.tokens + (now - b.t) * b.rate_hz)
    b.t = now
    return b.tokens >= 1.0


class Verdict(Enum):
    OK = "ok"
    MISSING = "missing"
    WRONG = "wrong"
    THROTTLED = "throttled"


class Credential:
    """Checks what a page offers against ``secret``. Wrong guesses spend a budget per client
    address (``burst`` at once, ``rate_hz`` a second after) and, from an address never seen
    with the right code, one in total (ten times that); a client out of its own budget, or a
    new one while the total is out, is refused unchecked (``THROTTLED``) until it refills.
    An address that gave the right code (:data:`PAIRED_KEPT` of them, the latest) answers to
    its own budget only: wrong codes from other addresses cannot keep a paired headset that
    reconnects out. ``throttle=False`` for a secret too long to guess (the console's key),
    where a throttle would only let wrong guesses lock the right page out."""

    def __init__(
        self,
        secret: str,
        rate_hz: float = 0.2,
        burst: int = 5,
        normalize: Callable[[str], str] = lambda s: s,
        clock: Callable[[], float] = time.monotonic,
        throttle: bool = True,
    ) -> None:
        self._secret = secret.encode()
        self.throttle = throttle
        self._normalize = normalize
        self._rate = rate_hz
        self._burst = burst
        self._clock = clock
        self._per_address: OrderedDict[str, MessageBudget] = OrderedDict()
        self._total = MessageBudget(10 * rate_hz, 10 * burst, clock)
        self._paired: OrderedDict[str, None] = OrderedDict()  # addresses seen with the secret

    @property
    def secret(self) -> str:
        return self._secret.decode()

    def _budget(self, where: str) -> MessageBudget:
        b = self._per_address.get(where)
        if b is None:
            b = self._per_address[where] = MessageBudget(self._rate, self._burst, self._clock)
            while len(self._per_address) > ADDRESSES_KEPT:
                self._per_address.popitem(last=False)
        self._per_address.move_to_end(where)
        return b

    def check(self, offered: str | None, where: str) -> Verdict:
        """Whether ``offered`` (None: nothing offered) from client ``where`` is the secret."""
        if not offered:
            return Verdict.MISSING
        if not self.throttle:
            given = offered.encode("utf-8", "replace")
            return Verdict.OK if hmac.compare_digest(given, self._secret) else Verdict.WRONG
        b = self._budget(where)
        paired = where in self._paired
        if not _has_token(b) or not (paired or _has_token(self._total)):
            return Verdict.THROTTLED
        given = self._normalize(offered).encode("utf-8", "replace")
        if hmac.compare_digest(given, self._secret):
            self._paired[where] = None
            self._paired.move_to_end(where)
            while len(self._paired) > PAIRED_KEPT:
                self._paired.popitem(last=False)
            return Verdict.OK
        b.take()
        if not paired:
            self._total.take()
        return Verdict.WRONG

"""A coturn ``turnserver`` process on loopback, for tests and benchmarks of relayed links.

Started with a fresh random user password (long-term credentials), UDP/TCP on one free port,
no TLS/DTLS, no CLI, loopback peers allowed (both peers are on this machine), a config file
and log in a private temporary directory (so the password is on no command line), and
SIGTERM if this process dies. Readiness is a STUN binding request answered on the port.

Usage::

    async with TurnServer() as turn:          # TurnServerError if it cannot start
        cfg = LinkConfig(ice_servers=[turn.ice_server()], relay_only=True)

``TurnServer(auth_secret=S)`` runs it as a deployment would with time-limited credentials
(coturn's ``use-auth-secret`` + ``static-auth-secret=S``, the TURN REST scheme of
:mod:`humantele.signaling.turn`) instead of the one long-term user; a list of secrets gives
one ``static-auth-secret`` line each (coturn accepts any of them: how a secret is rotated).

``TurnServer.available()`` says whether ``turnserver`` is installed (Debian package coturn).
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import logging
import os
import secrets
import shutil
import signal
import socket
import struct
import tempfile
import time
from pathlib import Path

from humantele.runtime.signal_child import signal_child
from humantele.transport.config import IceServer

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1
_STUN_MAGIC = 0x2112A442


class TurnServerError(RuntimeError):
    """turnserver is missing, exited, or did not answer in time (the message has its log)."""


def _free_port(host: str) -> int:
    """A port free for both UDP and TCP on ``host`` (turnserver listens on both)."""
    for _ in range(50):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
            u.bind((host, 0))
            port = u.getsockname()[1]
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as t:
                try:
                    t.bind((host, port))
                except OSError:
                    continue
        return port
    raise TurnServerError(f"no free UDP+TCP port on {host}")


def _die_with_parent() -> None:  # runs in the child between fork and exec
    with contextlib.suppress(Exception):
        ctypes.CDLL(None).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


class _StunProbe(asyncio.DatagramProtocol):
    def __init__(self, txid: bytes) -> None:
        self.txid = txid
        self.answered = asyncio.get_running_loop().create_future()

    def datagram_received(self, data: bytes, addr: object) -> None:
        # a Binding success response (0x0101) to our transaction
        if len(data) >= 20 and data[:2] == b"\x01\x01" and data[8:20] == self.txid:
            if not self.answered.done():
                self.answered.set_result(True)


async def stun_binding_answered(host: str, port: int, timeout: float = 0.5) -> bool:
    """True if a STUN server answers a Binding request on udp ``host:port`` within timeout."""
    loop = asyncio.get_running_loop()
    txid = secrets.token_bytes(12)
    transport, probe = await loop.create_datagram_endpoint(
        lambda: _StunProbe(txid), remote_addr=(host, port)
    )
    try:
        transport.sendto(struct.pack("!HHI", 0x0001, 0, _STUN_MAGIC) + txid)
        await asyncio.wait_for(asyncio.shield(probe.answered), timeout)
        return True
    except TimeoutError:
        return False
    finally:
        transport.close()


class TurnServer:
    """One ``turnserver`` process on ``host`` (see the module docstring)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        username: str = "humantele",
        realm: str = "humantele",
        start_timeout_s: float = 15.0,
        auth_secret: str | list[str] | None = None,
    ) -> None:
        self.host = host
        self.port = port
        self.username = username
        self.realm = realm
        self.start_timeout_s = start_timeout_s
        self._password = secrets.token_urlsafe(18)
        # use-auth-secret: no static user at all
        self._auth_secrets = [auth_secret] if isinstance(auth_secret, str) else auth_secret
        if self._auth_secrets is not None and (
            not self._auth_secrets or any(not x.isprintable() for x in self._auth_secrets)
        ):
            raise ValueError("auth_secret: one or more printable secrets (one line each)")
        self._dir: tempfile.TemporaryDirectory | None = None
        self._proc: asyncio.subprocess.Process | None = None

    @staticmethod
    def available() -> bool:
        """Whether the ``turnserver`` program is installed."""
        return shutil.which("turnserver") is not None

    @property
    def url(self) -> str:
        """The ``turn:`` URL (UDP) of this server."""
        return f"turn:{self.host}:{self.port}?transport=udp"

    @property
    def log_path(self) -> Path | None:
        return None if self._dir is None else Path(self._dir.name) / "turnserver.log"

    def ice_server(self, host: str | None = None, port: int | None = None) -> IceServer:
        """The link's ICE server entry for this server, or for a relay in front of it at
        ``host:port`` (same credentials). Only without ``auth_secret`` (whose credentials
        are issued: :mod:`humantele.signaling.turn`)."""
        if self._auth_secrets is not None:
            raise TurnServerError("this turnserver has no static user (use-auth-secret)")
        url = f"turn:{host or self.host}:{port or self.port}?transport=udp"
        return IceServer(urls=[url], username=self.username, credential=self._password)

    def log_tail(self, chars: int = 3000) -> str:
        path = self.log_path
        try:
            return path.read_text(errors="replace")[-chars:] if path else ""
        except OSError:
            return ""

    async def start(self) -> TurnServer:
        """Start the process and wait until it answers STUN; TurnServerError if it cannot."""
        exe = shutil.which("turnserver")
        if exe is None:
            raise TurnServerError("turnserver is not installed (Debian package coturn)")
        self._dir = tempfile.TemporaryDirectory(prefix="humantele-turn-")
        work = Path(self._dir.name)
        if not self.port:
            self.port = _free_port(self.host)
        conf = work / "turnserver.conf"
        conf.write_text(
            "\n".join(
                [
                    f"listening-ip={self.host}",
                    f"relay-ip={self.host}",
                    f"listening-port={self.port}",
                    *(
                        ["lt-cred-mech", f"user={self.username}:{self._password}"]
                        if self._auth_secrets is None
                        else [
                            "use-auth-secret",
                            *(f"static-auth-secret={x}" for x in self._auth_secrets),
                        ]
                    ),
                    f"realm={self.realm}",
                    "no-tls",
                    "no-dtls",
                    "no-cli",
                    "verbose",
                    "allow-loopback-peers",
                    "no-multicast-peers",
                    f"log-file={work / 'turnserver.log'}",
                    "simple-log",
                    "no-stdout-log",
                    f"pidfile={work / 'turnserver.pid'}",
                    f"userdb={work / 'turndb.sqlite'}",
                ]
            )
            + "\n"
        )
        os.chmod(conf, 0o600)
        self._proc = await asyncio.create_subprocess_exec(
            exe,
            "-c",
            str(conf),
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.DEVNULL,
            preexec_fn=_die_with_parent,
        )
        end = time.monotonic() + self.start_timeout_s
        while True:
            if self._proc.returncode is not None:
                tail = self.log_tail()
                await self.stop()
                raise TurnServerError(f"turnserver exited at start:\n{tail}")
            if await stun_binding_answered(self.host, self.port, 0.2):
                break
            if time.monotonic() > end:
                tail = self.log_tail()
                await self.stop()
                raise TurnServerError(f"turnserver did not answer on {self.url}:\n{tail}")
        log.info("turnserver pid %d on %s", self._proc.pid, self.url)
        return self

    async def stop(self) -> None:
        """Terminate the process (kill after 5 s) and remove its directory."""
        proc, self._proc = self._proc, None
        if proc is not None and proc.returncode is None:
            signal_child(proc, signal.SIGTERM)
            try:
                await asyncio.wait_for(proc.wait(), 5.0)
            except TimeoutError:
                signal_child(proc, signal.SIGKILL)
                await proc.wait()
        if self._dir is not None:
            self._dir.cleanup()
            self._dir = None

    async def __aenter__(self) -> TurnServer:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

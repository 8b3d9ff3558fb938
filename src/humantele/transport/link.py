"""One WebRTC link between the expert and the follower: a peer connection with three data
channels, negotiated through the signaling server, that comes back by itself.

Channels (negotiated=True with fixed ids, so both sides create them and nothing races):

- ``pose``    id 0, expert -> follower, unordered, maxRetransmits=0: :class:`PoseMessage`
- ``state``   id 1, follower -> expert, unordered, maxRetransmits=0: :class:`StateMessage`
- ``control`` id 2, both ways, reliable and ordered: JSON control messages (humantele.wire)

Usage, inside the daemon's asyncio loop::

    link = PeerLink("expert", LinkConfig(), on_state=..., on_control=...)
    task = asyncio.create_task(link.run())     # joins the room, (re)negotiates forever
    ...
    link.send_pose(PoseMessage(seq, link.now(), position, quaternion))   # at the pose rate
    age = link.age_of(state_msg.t_sent)        # one-way latency (s) via clock sync, or None
    ...
    await link.close()                         # says bye, leaves the room

Behaviour:

- The expert makes the offers (when it joins and the follower is there, when the follower
  joins, after a lost link); the follower answers. Every negotiation uses a new
  RTCPeerConnection, so a peer whose process died and came back gets a fresh link.
- ``state`` is ``"new"``, ``"connecting"``, ``"connected"``, ``"disconnected"`` (lost, waiting
  for the peer), ``"unreachable"`` (no link and the signaling server cannot be reached or does
  not answer; retried with backoff), ``"failed"`` (refused: bad token or protocol) or
  ``"closed"``; ``on_link_state(state)`` is called on every change.
- Heartbeats every ``heartbeat_interval_s`` on ``control``; with no message at all from the
  peer for ``heartbeat_timeout_s`` the link is declared lost, even when ICE has not noticed
  (judged on a watchdog tick that came on time: after this daemon stalled, what the peer sent
  meanwhile is read first).
- Clock sync: ping/pong on ``control`` (``clock``: a :class:`ClockSync`, offset and rtt).
- Poses and states never queue behind a stall: once aiortc holds more than
  ``newest_only_above_bytes`` of unsent ones (SCTP's congestion window is full, e.g. after a
  loss), the newest waits in a one-message slot and goes out as soon as the buffer drains
  back; the one it replaces is counted as ``"<channel>:superseded"``. A stalled transport
  therefore delays the stream by at most a couple of messages, and when it resumes the
  freshest pose goes next.
- Messages that fail to parse or validate, arrive late (an older sequence than one already
  delivered), or cannot be sent (not connected, send buffer full, NaN) are dropped and
  counted in ``counters.dropped`` under ``"<channel>:<reason>"``; nothing raises into the loop.
  Callbacks that raise are logged and counted as ``"<channel>:callback_error"``.
- Control messages are not queued while disconnected: resend what the peer must know (e.g.
  the ellipsoid model) when ``on_control`` receives the peer's :class:`Hello`.
- ICE servers: ``config.ice_servers``, then the TURN servers with time-limited credentials
  the signaling server issues (in ``joined``, renewed by ``ice_servers`` messages); each new
  peer connection takes the latest unexpired ones. A malformed or expired entry is dropped,
  logged and counted as ``"signaling:bad_ice_server"``.
- ``media(pc, role)`` (optional) is called for each new peer connection so a daemon can add
  video: the expert's call comes before its offer (add recvonly transceivers there), the
  follower's after the remote offer is set and before its answer (add tracks there).

Times are seconds of ``now()`` (``time.monotonic`` unless another clock is given).
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import logging
import time
from collections import Counter
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Literal

from aiortc import (
    RTCConfiguration,
    RTCDataChannel,
    RTCIceServer,
    RTCPeerConnection,
    RTCSessionDescription,
)
from aiortc.rtcconfiguration import RTCIceTransportPolicy

from humantele.signaling.client import SignalingClient, SignalingError, SignalingRefused
from humantele.signaling.messages import (
    Answer,
    IceServers,
    Offer,
    PeerJoined,
    PeerLeft,
    resolve_token,
)
from humantele.signaling.turn import IssuedIceServer, accept_issued
from humantele.transport.clocksync import ClockSync
from humantele.transport.config import LinkConfig
from humantele.wire import (
    PROTOCOL_VERSION,
    Bye,
    ControlMessage,
    Heartbeat,
    Hello,
    Ping,
    Pong,
    PoseMessage,
    StateMessage,
    WireError,
    encode_control,
    parse_control,
)

log = logging.getLogger(__name__)

Role = Literal["expert", "follower"]
LinkState = Literal[
    "new", "connecting", "connected", "disconnected", "unreachable", "failed", "closed"
]

CHANNEL_IDS = {"pose": 0, "state": 1, "control": 2}
FAST_SYNC_PINGS = 8  # first pings after connecting go every 0.1 s, to sync quickly
_TICK_S = 0.1
_LATE_TICK_S = 5 * _TICK_S  # a watchdog tick this long after the last: the daemon stalled


@dataclass
class LinkCounters:
    """What the link sent, received and dropped, per channel (dropped per channel:reason)."""

    sent: Counter[str] = field(default_factory=Counter)
    received: Counter[str] = field(default_factory=Counter)
    dropped: Counter[str] = field(default_factory=Counter)
    connections: int = 0  # peer connections that reached "connected"
    negotiations: int = 0  # offers made (expert) or answered (follower)

    def as_dict(self) -> dict[str, object]:
        return {
            "sent": dict(self.sent),
            "received": dict(self.received),
            "dropped": dict(self.dropped),
            "connections": self.connections,
            "negotiations": self.negotiations,
        }


def _serial_newer(seq: int, last: int | None) -> bool:
    """u32 sequence ``seq`` comes after ``last`` (RFC 1982 serial arithmetic)."""
    if last is None:
        return True
    d = (seq - last) & 0xFFFFFFFF
    return 0 < d < 0x80000000


class _Peer:
    """One RTCPeerConnection and its channels; replaced on every negotiation."""

    def __init__(self, pc: RTCPeerConnection, channels: dict[str, RTCDataChannel]) -> None:
        self.pc = pc
        self.channels = channels
        self.offer_id = 0
        self.started = 0.0
        self.last_seq: dict[str, int | None] = {"pose": None, "state": None}
        self.pending: dict[str, bytes] = {}  # newest pose/state waiting for the buffer to drain
        self.open = False


def link_refusal(task: asyncio.Task) -> str | None:
    """Why a finished :meth:`PeerLink.run` task was refused by the signaling server (wrong
    token, room full), or None (it did not end that way)."""
    if not task.done() or task.cancelled():
        return None
    exc = task.exception()
    if isinstance(exc, SignalingRefused):
        return f"refused by the signaling server: {exc.reason}"
    return None


class PeerLink:
    """The expert's or the follower's end of the session link (see the module docstring)."""

    def __init__(
        self,
        role: Role,
        config: LinkConfig | None = None,
        *,
        on_pose: Callable[[PoseMessage], None] | None = None,
        on_state: Callable[[StateMessage], None] | None = None,
        on_control: Callable[[ControlMessage], None] | None = None,
        on_link_state: Callable[[LinkState], None] | None = None,
        media: Callable[[RTCPeerConnection, Role], Awaitable[None] | None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        software: str = "humantele",
    ) -> None:
        if role not in ("expert", "follower"):
            raise ValueError(f"role must be 'expert' or 'follower', not {role!r}")
        self.role: Role = role
        self.config = config or LinkConfig()
        self.on_pose = on_pose
        self.on_state = on_state
        self.on_control = on_control
        self.on_link_state = on_link_state
        self.media = media
        self.now = clock
        self.software = software
        self.clock = ClockSync(clock)
        self.counters = LinkCounters()
        self.peer_present = False
        self._state: LinkState = "new"
        self._state_changed = asyncio.Event()
        self._token = resolve_token(self.config.token)
        self._peer: _Peer | None = None
        self._sig: SignalingClient | None = None
        self._lock = asyncio.Lock()
        self._closing = False
        self._wake = asyncio.Event()
        self._run_task: asyncio.Task | None = None
        self._last_rx = 0.0
        self._last_heartbeat = 0.0
        self._last_ping = 0.0
        self._pings = 0
        self._offer_seq = 0
        self._tasks: set[asyncio.Task] = set()
        self._issued: list[IssuedIceServer] = []  # TURN credentials from the signaling server
        self._wall_clock: Callable[[], float] = time.time  # unix s: credential expiry

    def __repr__(self) -> str:
        return f"PeerLink({self.role!r}, room={self.config.room!r}, state={self._state!r})"

    # --- public -------------------------------------------------------------------------------

    @property
    def state(self) -> LinkState:
        return self._state

    @property
    def connected(self) -> bool:
        return self._state == "connected"

    @property
    def peer_connection(self) -> RTCPeerConnection | None:
        """The current RTCPeerConnection (replaced on every negotiation), or None."""
        return None if self._peer is None else self._peer.pc

    async def wait_state(self, *states: LinkState, timeout: float | None = None) -> LinkState:
        """Wait until ``state`` is one of ``states``; TimeoutError after ``timeout`` s."""

        async def _wait() -> LinkState:
            while self._state not in states:
                self._state_changed.clear()
                await self._state_changed.wait()
            return self._state

        return await asyncio.wait_for(_wait(), timeout)

    def age_of(self, t_sent_remote: float) -> float | None:
        """Age (s) now of a message the peer stamped ``t_sent_remote`` (its clock), or None
        before the first clock-sync exchange."""
        return self.clock.age_of(t_sent_remote, self.now())

    def send_pose(self, msg: PoseMessage) -> bool:
        """Send a pose on the unreliable ``pose`` channel; False (and counted) if dropped."""
        return self._send_binary("pose", msg)

    def send_state(self, msg: StateMessage) -> bool:
        """Send a state on the unreliable ``state`` channel; False (and counted) if dropped."""
        return self._send_binary("state", msg)

    def send_control(self, msg: ControlMessage) -> bool:
        """Send a control message (reliable, ordered); False (and counted) if not connected."""
        ch = self._channel("control")
        if ch is None:
            self.counters.dropped["control:not_connected"] += 1
            return False
        try:
            ch.send(encode_control(msg))
        except Exception as exc:  # aiortc raises InvalidStateError when closing
            log.debug("control send failed: %s", exc)
            self.counters.dropped["control:send_error"] += 1
            return False
        self.counters.sent["control"] += 1
        return True

    async def run(self) -> None:
        """Join the room and keep the link up until :meth:`close`. Reconnects to signaling
        with backoff, also after an error it did not expect (logged with its traceback,
        counted as ``signaling:error``); raises SignalingRefused only when retrying cannot
        help (bad token)."""
        self._run_task = asyncio.current_task()
        self._set_state("connecting")
        watchdog = asyncio.create_task(self._watchdog())
        delay = self.config.reconnect_delay_s
        try:
            while not self._closing:
                try:
                    await self._signaling_session()
                except SignalingRefused as exc:
                    if exc.fatal:
                        log.error("%s link refused by signaling: %s", self.role, exc.reason)
                        self._set_state("failed")
                        raise
                    log.warning("%s link: %s; retrying in %.1f s", self.role, exc, delay)
                except SignalingError as exc:
                    if self._closing:
                        break
                    log.warning("%s link: %s; retrying in %.1f s", self.role, exc, delay)
                    if self._state != "connected":
                        self._set_state("unreachable")
                except Exception as exc:  # an error signaling does not wrap: retry, never end
                    if self._closing:
                        break
                    self.counters.dropped["signaling:error"] += 1
                    log.exception("%s link: unexpected %s; retrying in %.1f s", self.role,
                                  type(exc).__name__, delay)  # fmt: skip
                    if self._state != "connected":
                        self._set_state("unreachable")
                else:
                    delay = self.config.reconnect_delay_s
                if self._closing:
                    break
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), delay)
                delay = min(delay * 2.0, self.config.reconnect_max_delay_s)
        finally:
            watchdog.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await watchdog
            await self._drop_peer()
            if self._state != "failed":
                self._set_state("closed")

    async def close(self, reason: str = "closing") -> None:
        """Say bye to the peer, leave the room, close the peer connection."""
        if self._closing:
            return
        self._closing = True
        self._wake.set()
        if self.send_control(Bye(reason=reason)):
            await asyncio.sleep(0.05)  # let aiortc put the bye on the wire
        if self._sig is not None:
            await self._sig.close()
        if self._run_task is not None and self._run_task is not asyncio.current_task():
            with contextlib.suppress(Exception, asyncio.CancelledError):
                await asyncio.wait_for(asyncio.shield(self._run_task), 5.0)
        await self._drop_peer()
        if self._state != "failed":
            self._set_state("closed")

    # --- signaling ----------------------------------------------------------------------------

    async def _signaling_session(self) -> None:
        cfg = self.config
        sig = SignalingClient(
            cfg.signaling_url, cfg.room, self.role, self._token,
            ca_file=cfg.signaling_ca_file, connect_timeout_s=cfg.connect_timeout_s,
        )  # fmt: skip
        self._sig = sig  # so that close() ends a join in progress
        try:
            joined = await sig.join()
            if self._closing:
                return
            if self._state == "unreachable":
                self._set_state("connecting")
            self.peer_present = joined.peer_present
            self._take_issued(joined.ice_servers)
            log.info("%s joined room %s (peer present: %s)", self.role, cfg.room, self.peer_present)
            if self.role == "expert" and self.peer_present and self._state != "connected":
                await self._offer()
            while not self._closing:
                msg = await sig.receive()
                await self._on_signal(msg)
        finally:
            self._sig = None
            self.peer_present = False
            await sig.close()

    async def _on_signal(self, msg: object) -> None:
        if isinstance(msg, PeerJoined):
            self.peer_present = True
            log.info("%s: the %s joined the room", self.role, msg.role)
            if self.role == "expert":
                await self._offer()  # the follower is new: its old connection is gone
        elif isinstance(msg, PeerLeft):
            self.peer_present = False
            log.info("%s: the %s left the room", self.role, msg.role)
        elif isinstance(msg, IceServers):
            self._take_issued(msg.ice_servers)
        elif isinstance(msg, Offer) and self.role == "follower":
            await self._answer(msg)
        elif isinstance(msg, Answer) and self.role == "expert":
            await self._accept(msg)
        else:
            self.counters.dropped["signaling:unexpected"] += 1

    def _take_issued(self, raw: list | None) -> None:
        """Keep the valid TURN credentials of a ``joined`` or ``ice_servers`` message (none:
        the server issues none); drop the others with a clear error."""
        good, problems = accept_issued(raw, self._wall_clock())
        for problem in problems:
            log.error("%s: TURN server from the signaling server dropped: %s", self.role, problem)
            self.counters.dropped["signaling:bad_ice_server"] += 1
        if good or not problems:  # keep the last good ones if a refresh was all bad
            self._issued = good
        if good:
            log.info("%s: TURN credentials from the signaling server: %s",
                     self.role, "; ".join(str(e) for e in good))  # fmt: skip

    def _ice_servers(self) -> list[RTCIceServer]:
        """The configured ICE servers, then the issued TURN servers still valid."""
        servers = [
            RTCIceServer(
                urls=s.urls,
                username=s.username,
                credential=s.credential.get_secret_value() if s.credential else None,
            )
            for s in self.config.ice_servers
        ]
        now = self._wall_clock()
        for e in self._issued:
            if e.expires <= now:
                log.error("%s: the signaling server's TURN credential %s has expired and no "
                          "fresh one came", self.role, e.username)  # fmt: skip
                self.counters.dropped["signaling:expired_ice_server"] += 1
                continue
            servers.append(RTCIceServer(urls=e.urls, username=e.username, credential=e.credential))
        if self.config.relay_only and not any(
            u.startswith(("turn:", "turns:"))
            for s in servers
            for u in ([s.urls] if isinstance(s.urls, str) else s.urls)
        ):
            log.error("%s: relay_only but no TURN server: none in ice_servers and the signaling "
                      "server issued none ([turn] in its config)", self.role)  # fmt: skip
            self.counters.dropped["ice:no_turn_server"] += 1
        return servers

    async def _offer(self) -> None:
        async with self._lock:
            sig = self._sig
            if sig is None or self._closing:
                return
            await self._drop_peer_locked()
            peer = self._new_peer()
            self._offer_seq += 1
            peer.offer_id = self._offer_seq
            self._set_state("connecting")
            try:
                await self._call_media(peer.pc)
                await peer.pc.setLocalDescription(await peer.pc.createOffer())
            except Exception as exc:
                log.error("expert: cannot make an offer: %s", exc)
                await self._drop_peer_locked()
                return
            self.counters.negotiations += 1
            await sig.send(Offer(sdp=peer.pc.localDescription.sdp, id=peer.offer_id))

    async def _answer(self, offer: Offer) -> None:
        async with self._lock:
            sig = self._sig
            if sig is None or self._closing:
                return
            await self._drop_peer_locked()
            peer = self._new_peer()
            peer.offer_id = offer.id
            self._set_state("connecting")
            try:
                await peer.pc.setRemoteDescription(RTCSessionDescription(offer.sdp, "offer"))
                await self._call_media(peer.pc)
                await peer.pc.setLocalDescription(await peer.pc.createAnswer())
            except Exception as exc:
                log.warning("follower: bad offer dropped: %s", exc)
                self.counters.dropped["signaling:bad_offer"] += 1
                await self._drop_peer_locked()
                self._set_state("disconnected")
                return
            self.counters.negotiations += 1
            await sig.send(Answer(sdp=peer.pc.localDescription.sdp, id=offer.id))

    async def _accept(self, answer: Answer) -> None:
        async with self._lock:
            peer = self._peer
            if (
                peer is None
                or answer.id != peer.offer_id
                or peer.pc.signalingState != ("have-local-offer")
            ):
                self.counters.dropped["signaling:stale_answer"] += 1
                return
            try:
                await peer.pc.setRemoteDescription(RTCSessionDescription(answer.sdp, "answer"))
            except Exception as exc:
                log.warning("expert: bad answer dropped: %s", exc)
                self.counters.dropped["signaling:bad_answer"] += 1
                await self._drop_peer_locked()
                self._set_state("disconnected")

    async def _call_media(self, pc: RTCPeerConnection) -> None:
        if self.media is not None:
            result = self.media(pc, self.role)
            if inspect.isawaitable(result):
                await result

    # --- peer connection ----------------------------------------------------------------------

    def _new_peer(self) -> _Peer:
        cfg = self.config
        servers = self._ice_servers()
        policy = RTCIceTransportPolicy.RELAY if cfg.relay_only else RTCIceTransportPolicy.ALL
        # an explicit (possibly empty) list: aiortc would otherwise try a public STUN server
        pc = RTCPeerConnection(RTCConfiguration(iceServers=servers, iceTransportPolicy=policy))
        unreliable = {"ordered": False, "maxRetransmits": 0}
        channels = {
            "pose": pc.createDataChannel("pose", negotiated=True, id=0, **unreliable),
            "state": pc.createDataChannel("state", negotiated=True, id=1, **unreliable),
            "control": pc.createDataChannel("control", negotiated=True, id=2, ordered=True),
        }
        peer = _Peer(pc, channels)
        peer.started = self.now()
        self._peer = peer
        for name in ("pose", "state"):
            self._watch_binary(peer, name)
        channels["control"].on("message", lambda d: self._on_control(peer, d))
        channels["control"].on("open", lambda: self._on_open(peer))
        pc.on("connectionstatechange", lambda: self._on_pc_state(peer))
        return peer

    def _watch_binary(self, peer: _Peer, name: str) -> None:
        """Receive on channel ``name`` and send its pending message when its buffer drains."""
        ch = peer.channels[name]
        ch.bufferedAmountLowThreshold = self.config.newest_only_above_bytes
        ch.on("message", lambda d: self._on_binary(peer, name, d))
        ch.on("bufferedamountlow", lambda: self._send_pending(peer, name))

    def _send_pending(self, peer: _Peer, name: str) -> None:
        data = peer.pending.pop(name, None)
        if data is None or peer is not self._peer:
            return
        ch = self._channel(name)
        if ch is None:
            self.counters.dropped[f"{name}:not_connected"] += 1
            return
        self._send_now(ch, name, data)

    def _on_open(self, peer: _Peer) -> None:
        if peer is not self._peer or peer.open:
            return
        peer.open = True
        now = self.now()
        self._last_rx = now
        self._last_heartbeat = now
        self._last_ping = 0.0
        self._pings = 0
        self.clock.reset()
        self.counters.connections += 1
        self._set_state("connected")
        self.send_control(Hello(protocol=PROTOCOL_VERSION, role=self.role, software=self.software))

    def _on_pc_state(self, peer: _Peer) -> None:
        state = peer.pc.connectionState
        if peer is not self._peer:
            return
        log.debug("%s: peer connection %s", self.role, state)
        if state == "failed":
            self._spawn(self._lost(peer, "ICE/DTLS failed"))

    async def _lost(self, peer: _Peer, reason: str) -> None:
        """The link through ``peer`` is gone: drop it; the expert offers again if it can."""
        async with self._lock:
            if peer is not self._peer or self._closing:
                return
            log.warning("%s: link lost (%s)", self.role, reason)
            await self._drop_peer_locked()
            self._set_state("disconnected")
        if self.role == "expert" and self.peer_present:
            await self._offer()

    async def _drop_peer(self) -> None:
        async with self._lock:
            await self._drop_peer_locked()

    async def _drop_peer_locked(self) -> None:
        peer, self._peer = self._peer, None
        if peer is not None:
            with contextlib.suppress(Exception):
                await peer.pc.close()

    def _channel(self, name: str) -> RTCDataChannel | None:
        peer = self._peer
        if peer is None or not peer.open:
            return None
        ch = peer.channels[name]
        return ch if ch.readyState == "open" else None

    def _send_binary(self, name: str, msg: PoseMessage | StateMessage) -> bool:
        ch = self._channel(name)
        if ch is None:
            self.counters.dropped[f"{name}:not_connected"] += 1
            return False
        try:
            data = msg.encode()
        except WireError as exc:
            self.counters.dropped[f"{name}:invalid_{exc.reason}"] += 1
            return False
        if self.config.send_newest_only:
            if ch.bufferedAmount > self.config.newest_only_above_bytes:  # stalled: replace
                peer = self._peer
                if peer.pending.get(name) is not None:
                    self.counters.dropped[f"{name}:superseded"] += 1
                peer.pending[name] = data
                return True
        elif ch.bufferedAmount > self.config.max_buffered_bytes:
            self.counters.dropped[f"{name}:backpressure"] += 1
            return False
        return self._send_now(ch, name, data)

    def _send_now(self, ch: RTCDataChannel, name: str, data: bytes) -> bool:
        try:
            ch.send(data)
        except Exception as exc:
            log.debug("%s send failed: %s", name, exc)
            self.counters.dropped[f"{name}:send_error"] += 1
            return False
        self.counters.sent[name] += 1
        return True

    # --- receiving ----------------------------------------------------------------------------

    def _on_binary(self, peer: _Peer, name: str, data: object) -> None:
        if peer is not self._peer:
            return
        self._last_rx = self.now()
        decode = PoseMessage.decode if name == "pose" else StateMessage.decode
        callback = self.on_pose if name == "pose" else self.on_state
        if not isinstance(data, bytes):
            self.counters.dropped[f"{name}:type"] += 1
            return
        try:
            msg = decode(data)
        except WireError as exc:
            self.counters.dropped[f"{name}:{exc.reason}"] += 1
            return
        if not _serial_newer(msg.seq, peer.last_seq[name]):
            self.counters.dropped[f"{name}:stale"] += 1
            return
        peer.last_seq[name] = msg.seq
        self.counters.received[name] += 1
        if callback is None:
            self.counters.dropped[f"{name}:unexpected"] += 1
            return
        self._call(name, callback, msg)

    def _on_control(self, peer: _Peer, data: object) -> None:
        if peer is not self._peer:
            return
        t = self.now()
        self._last_rx = t
        if not isinstance(data, str):
            self.counters.dropped["control:type"] += 1
            return
        try:
            msg = parse_control(data)
        except WireError as exc:
            self.counters.dropped[f"control:{exc.reason}"] += 1
            return
        self.counters.received["control"] += 1
        if isinstance(msg, Ping):
            self.send_control(self.clock.answer(msg, t))
        elif isinstance(msg, Pong):
            if self.clock.on_pong(msg, t) is None:
                self.counters.dropped["control:bad_pong"] += 1
        elif isinstance(msg, Heartbeat):
            pass
        else:
            if isinstance(msg, Hello) and (
                msg.protocol != PROTOCOL_VERSION or msg.role == self.role
            ):
                log.error(
                    "%s: peer speaks protocol %s as %s; we speak %s as %s",
                    self.role, msg.protocol, msg.role, PROTOCOL_VERSION, self.role,
                )  # fmt: skip
                self.counters.dropped["control:incompatible_peer"] += 1
                self._spawn(self._incompatible(peer))
                return
            if isinstance(msg, Bye):
                log.info("%s: peer said bye (%s)", self.role, msg.reason)
                self._spawn(self._bye(peer))
            if self.on_control is not None:
                self._call("control", self.on_control, msg)

    async def _bye(self, peer: _Peer) -> None:
        async with self._lock:
            if peer is self._peer:
                await self._drop_peer_locked()
                self._set_state("disconnected")

    async def _incompatible(self, peer: _Peer) -> None:
        async with self._lock:
            if peer is self._peer:
                await self._drop_peer_locked()
                self._set_state("failed")

    def _call(self, name: str, callback: Callable, msg: object) -> None:
        try:
            callback(msg)
        except Exception:
            log.exception("%s callback raised", name)
            self.counters.dropped[f"{name}:callback_error"] += 1

    # --- housekeeping -------------------------------------------------------------------------

    async def _watchdog(self) -> None:
        cfg = self.config
        last_tick = self.now()
        while True:
            await asyncio.sleep(_TICK_S)
            peer = self._peer
            now = self.now()
            # A tick that came late: this daemon did not run (a loaded machine, the host's
            # steal), and what the peer sent meanwhile waits in the socket, read after this
            # tick in the loop's turn: judge the silence at the next tick, not now.
            late, last_tick = now - last_tick > _LATE_TICK_S, now
            if self._state == "connected" and peer is not None and peer.open:
                if now - self._last_rx > cfg.heartbeat_timeout_s and not late:
                    await self._lost(peer, f"no message for {cfg.heartbeat_timeout_s:.1f} s")
                    continue
                if now - self._last_heartbeat >= cfg.heartbeat_interval_s:
                    self._last_heartbeat = now
                    self.send_control(Heartbeat(t=now))
                interval = _TICK_S if self._pings < FAST_SYNC_PINGS else cfg.clock_sync_interval_s
                if now - self._last_ping >= interval:
                    self._last_ping = now
                    self._pings += 1
                    self.send_control(self.clock.make_ping())
            elif (
                self.role == "expert"
                and self._state == "connecting"
                and peer is not None
                and self.peer_present
                and now - peer.started > cfg.connect_timeout_s
            ):
                log.warning(
                    "expert: no link %.0f s after the offer; offering again", now - peer.started
                )
                await self._offer()

    def _spawn(self, coro: Awaitable[None]) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _set_state(self, state: LinkState) -> None:
        if state == self._state:
            return
        log.info("%s link: %s -> %s", self.role, self._state, state)
        self._state = state
        self._state_changed.set()
        if self.on_link_state is not None:
            try:
                self.on_link_state(state)
            except Exception:
                log.exception("on_link_state callback raised")

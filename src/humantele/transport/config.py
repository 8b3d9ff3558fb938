"""Link configuration: where signaling is, which room, the token, ICE servers, rates, timeouts."""

from __future__ import annotations

from typing import Self

from pydantic import Field, SecretStr, field_validator, model_validator

from humantele.config import ConfigModel
from humantele.signaling.client import CaFile
from humantele.signaling.messages import ROOM_PATTERN


class IceServer(ConfigModel):
    """One STUN or TURN server, as in the WebRTC ``RTCIceServer`` dictionary."""

    urls: list[str] = Field(min_length=1)
    username: str | None = None
    credential: SecretStr | None = None

    @field_validator("urls")
    @classmethod
    def _scheme(cls, urls: list[str]) -> list[str]:
        for url in urls:
            if not url.startswith(("stun:", "stuns:", "turn:", "turns:")):
                raise ValueError(f"{url!r} is not a stun:, stuns:, turn: or turns: URL")
        return urls


class LinkConfig(ConfigModel):
    """Settings of one peer link (one per daemon). Defaults run the loopback demo.

    ``ice_servers`` defaults to an explicit empty list: aiortc would otherwise try a public
    STUN server. The TURN servers the signaling server issues time-limited credentials for
    (its ``[turn]``) come on top of these, with each admission; a static ``username`` and
    ``credential`` here still work (a TURN server the signaling server does not cover) but
    are long-lived secrets on this machine: prefer the issued ones (docs/signaling.md).
    ``relay_only`` sets iceTransportPolicy="relay" (needs a TURN server: one here, or issued).
    ``token`` falls back to $HUMANTELE_TOKEN, then to the loopback development token.
    ``pose_rate_hz`` paces the expert's poses; the follower's state goes out with each
    tracker image (``[follower] sensing_rate_hz``).
    """

    signaling_url: str = Field("ws://127.0.0.1:8765/ws", pattern=r"^wss?://\S+$")
    signaling_ca_file: CaFile | None = None  # PEM CA/certificate to trust for wss:// (self-signed)
    room: str = Field("demo", pattern=ROOM_PATTERN)
    token: SecretStr | None = None
    ice_servers: list[IceServer] = Field(default_factory=list)
    relay_only: bool = False
    pose_rate_hz: float = Field(250.0, gt=0, le=1000)
    heartbeat_interval_s: float = Field(0.5, gt=0, le=10)
    heartbeat_timeout_s: float = Field(2.0, gt=0, le=60)
    clock_sync_interval_s: float = Field(1.0, gt=0, le=60)
    connect_timeout_s: float = Field(10.0, gt=0, le=120)  # joining signaling; a link after an offer
    reconnect_delay_s: float = Field(0.5, gt=0, le=60)
    reconnect_max_delay_s: float = Field(5.0, gt=0, le=600)
    # pose/state bytes allowed to wait in the sender (~28 poses): newer ones are dropped beyond
    # it, so a stall never turns into a backlog of stale poses
    max_buffered_bytes: int = Field(2048, ge=100)
    # once SCTP holds more than newest_only_above_bytes of unsent poses/states (~2 poses: a
    # stall, not a burst), keep only the newest in one slot, sent when the buffer drains back,
    # instead of queueing each behind the last; False: plain FIFO up to max_buffered_bytes
    # (the old behaviour, for comparison in `bench session --fifo`)
    send_newest_only: bool = True
    newest_only_above_bytes: int = Field(200, ge=0, le=65536)
    # SCHED_FIFO priority of the daemon's event-loop thread, which sends and receives the
    # poses (below the servo's 80); 0: normal priority. Refused without the privilege (the
    # daemon then runs at normal priority and says so in its stats, `loop_priority`).
    realtime_priority: int = Field(10, ge=0, le=79)

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        if self.heartbeat_timeout_s <= self.heartbeat_interval_s:
            raise ValueError("heartbeat_timeout_s must be longer than heartbeat_interval_s")
        return self

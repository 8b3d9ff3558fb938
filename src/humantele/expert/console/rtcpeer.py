"""The console's WebRTC transport (``transport = "webrtc"``): the page as a WebRTC receiver of
the two tracks, the expert forwarding the encoded frames it received without decoding them
again or re-encoding them, as an SFU does.

One :class:`PagePeer` per page: an aiortc peer connection offering two send-only video
tracks (``us`` then ``pov``) in the received codec, signalled over the console's WebSocket
(``rtc_offer`` to the page, ``rtc_answer`` back; aiortc has no trickle ICE, so the offer
is complete). Each track's ``recv()`` gives ``av.Packet`` s, which aiortc's sender only
packetises (``Encoder.pack``). A track starts at a keyframe (asked of the follower with a
PLI); a backlog (the sender slower than the frames) is dropped up to the next keyframe.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from fractions import Fraction
from typing import Any

import av
from aiortc import RTCConfiguration, RTCPeerConnection, RTCRtpSender, RTCSessionDescription
from aiortc.mediastreams import MediaStreamTrack

from humantele.expert.console.frames import TRACKS

log = logging.getLogger(__name__)
BACKLOG = 8  # packets of a track waiting for the sender; more: dropped to the next keyframe
TIME_BASE = Fraction(1, 90000)


class RelayTrack(MediaStreamTrack):
    """A video track of encoded frames (``av.Packet``, 90 kHz pts) pushed by the console."""

    kind = "video"

    def __init__(self, need_keyframe: Callable[[], Any]) -> None:
        super().__init__()
        self.queue: asyncio.Queue[av.Packet] = asyncio.Queue()
        self.need_keyframe = need_keyframe
        self.waiting_key = True
        self.forwarded = 0
        self.dropped = 0

    def push(self, data: bytes, keyframe: bool, pts: int) -> None:
        """Queue one encoded frame (on the loop)."""
        if self.waiting_key and not keyframe:
            self.dropped += 1
            self.need_keyframe()
            return
        if self.queue.qsize() >= BACKLOG:
            self.dropped += self.queue.qsize()
            while not self.queue.empty():
                self.queue.get_nowait()
            self.waiting_key = True
            self.need_keyframe()
            if not keyframe:
                self.dropped += 1
                return
        self.waiting_key = False
        packet = av.Packet(data)
        packet.pts = pts
        packet.time_base = TIME_BASE
        self.queue.put_nowait(packet)
        self.forwarded += 1

    async def recv(self) -> av.Packet:  # type: ignore[override]
        return await self.queue.get()


class PagePeer:
    """One page's peer connection: ``offer()`` (the SDP for the page), ``answer(sdp)``,
    ``push(track, frame, encoded)``, ``close()``. ``codec``: the received codec ('VP8')."""

    def __init__(self, codec: str, need_keyframe: Callable[[str], Any]) -> None:
        self.codec = codec
        self.pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))  # loopback, no STUN
        self.tracks = {t: RelayTrack(lambda t=t: need_keyframe(t)) for t in TRACKS}
        prefs = [c for c in RTCRtpSender.getCapabilities("video").codecs
                 if c.mimeType.lower() == f"video/{codec.lower()}"]  # fmt: skip
        for t in TRACKS:
            transceiver = self.pc.addTransceiver(self.tracks[t], direction="sendonly")
            transceiver.setCodecPreferences(prefs)

    async def offer(self) -> str:
        await self.pc.setLocalDescription(await self.pc.createOffer())
        return self.pc.localDescription.sdp

    async def answer(self, sdp: str) -> None:
        await self.pc.setRemoteDescription(RTCSessionDescription(sdp, "answer"))

    def push(self, track: str, frame: Any, encoded: Any) -> None:
        av_frame = getattr(frame, "av_frame", None)
        if encoded is None or av_frame is None or av_frame.pts is None:
            return
        self.tracks[track].push(encoded.data, encoded.keyframe, int(av_frame.pts))

    def stats(self) -> dict[str, Any]:
        return {t: {"forwarded": r.forwarded, "dropped": r.dropped} for t, r in self.tracks.items()}

    async def close(self) -> None:
        with contextlib.suppress(Exception):
            await self.pc.close()

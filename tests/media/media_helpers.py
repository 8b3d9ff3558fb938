"""Helpers of the media tests: small sim sources, a follower link with video, waiting."""

import asyncio
import contextlib

from aiortc import RTCPeerConnection

from humantele.media.config import FollowerVideoConfig
from humantele.media.sender import VideoSender
from humantele.transport import LinkConfig, PeerLink
from humantele.video.sim_pov import SimPovConfig
from humantele.video.sim_ultrasound import SimUltrasoundConfig


def small_video_config(**kw) -> FollowerVideoConfig:
    """Small, slow sim sources so the tests are light on a loaded machine (threads unless
    ``process=True``)."""
    base = dict(
        process=False,
        us=SimUltrasoundConfig(width=320, height=240, fps=10, beams=64, samples=128),
        pov=SimPovConfig(width=320, height=180, fps=10),
        record_us_hz=0,
        record_pov_hz=0,
    )
    base.update(kw)
    return FollowerVideoConfig(**base)


def video_follower(url: str, room: str, token: str, config=None, scene=None, record=None):
    """(PeerLink, VideoSender): a follower link whose peer connections carry the two tracks."""
    from humantele.video.scene import DEFAULT_PATIENT

    sender = VideoSender(config or small_video_config(), scene, record, DEFAULT_PATIENT)
    link = PeerLink(
        "follower",
        LinkConfig(signaling_url=url, room=room, token=token),
        media=lambda pc, role: sender.attach(pc),
    )
    return link, sender


async def close_video_link(follower, expert, tx, rx, tasks) -> None:
    """End a test's video link: both peers, the sender (its close may block: a thread) and
    the receiver, then the link tasks (each given 5 s)."""
    await follower.close()
    await expert.close()
    await asyncio.to_thread(tx.close)
    await rx.close()
    for t in tasks:
        with contextlib.suppress(BaseException):
            await asyncio.wait_for(t, 5)


class SyncErrorBound:
    """The largest error the link's clock sync could have had while a test ran (s): half the
    round trip of the exchange its offset came from, the most that ever was (each sample's
    offset is within half its round trip of the truth). One process on loopback has one clock,
    so a capture time mapped to the expert's clock is off by at most this: milliseconds on a
    quiet machine, tens on a loaded one."""

    def __init__(self, clock) -> None:
        self.clock, self.worst_s = clock, 0.0
        on_pong = clock.on_pong

        def watched(*args, **kw):
            sample = on_pong(*args, **kw)
            if clock.best is not None:
                self.worst_s = max(self.worst_s, clock.best.rtt / 2.0)
            return sample

        clock.on_pong = watched


@contextlib.asynccontextmanager
async def two_senders_sending():
    """Two video senders of one RTCPeerConnection (one transport, as with BUNDLE) whose
    transport's sends are recorded instead of going through SRTP to a socket: yields (first
    sender, second sender, the list of the plain RTP packets sent); the connection closed
    after."""
    pc = RTCPeerConnection()
    try:
        a = pc.addTransceiver("video").sender
        b = pc.addTransceiver("video").sender
        sent: list[bytes] = []

        async def fake_send(data: bytes) -> None:  # in place of SRTP and the socket
            sent.append(data)

        a.transport._send_rtp = fake_send
        yield a, b, sent
    finally:
        await pc.close()

"""Two PeerLinks in one process over real aiortc on loopback, through a real signaling server."""

import asyncio
import struct
import time

import pytest
from link_helpers import running_links

from humantele.signaling.client import SignalingRefused
from humantele.signaling.server import SignalConfig, SignalingServer
from humantele.transport import LinkConfig, PeerLink
from humantele.wire import (
    EllipsoidModel,
    Hello,
    PoseMessage,
    Scan,
    StateMessage,
    TrackingStatus,
)
from waits import until

TOKEN = "link-test-token"
Q = (0.0, 0.0, 0.0, 1.0)


@pytest.fixture
async def server():
    s = SignalingServer(SignalConfig(port=0), TOKEN)
    await s.start()
    yield s
    await s.stop()


def _config(server, **kw) -> LinkConfig:
    base = dict(signaling_url=server.url, token=TOKEN, room="t")
    base.update(kw)
    return LinkConfig(**base)


async def test_streams_control_and_clock_sync_with_an_injected_offset(server):
    poses, states, controls = [], [], []
    offset = 37.25  # the follower's clock runs this far ahead of the expert's
    expert = PeerLink("expert", _config(server), on_state=states.append)
    follower = PeerLink(
        "follower",
        _config(server),
        on_pose=poses.append,
        on_control=controls.append,
        clock=lambda: time.monotonic() + offset,
    )
    async with running_links(expert, follower, timeout=20):
        for i in range(200):
            assert expert.send_pose(PoseMessage(i, expert.now(), (0.0, 0.1, 0.0), Q, clutch=i % 2))
            if i % 4 == 0:
                follower.send_state(
                    StateMessage(i, follower.now(), (0, 0, 0), Q, TrackingStatus.TRACKED, (0, 1, 0))
                )
            await asyncio.sleep(0.002)
        model = {"center": [0, 0.1, 0], "semi_axes": [10.0, 0.1, 0.15], "heading": 0.0}
        assert expert.send_control(EllipsoidModel(model=model))
        assert expert.send_control(Scan(action="start"))
        await until(lambda: len(poses) >= 195 and len(controls) >= 3 and follower.clock.synced)
        await until(lambda: expert.clock.synced)
        # the peer's hello arrives first, then the messages in order
        assert isinstance(controls[0], Hello) and controls[0].role == "expert"
        assert [type(c).__name__ for c in controls[1:3]] == ["EllipsoidModel", "Scan"]
        assert [p.seq for p in poses] == sorted(p.seq for p in poses)
        assert len(states) >= 45
        # clock sync finds the injected offset from both sides, within half the round trip
        # of the exchange it uses (NTP's bound: sub-millisecond on an idle loopback)
        assert abs(follower.clock.offset + offset) <= follower.clock.rtt / 2
        assert abs(expert.clock.offset - offset) <= expert.clock.rtt / 2
        # a pose the expert stamps now is (about) zero seconds old on the follower
        t0 = time.monotonic()
        age = follower.age_of(expert.now())
        assert abs(age) <= follower.clock.rtt / 2 + (time.monotonic() - t0)
        assert expert.counters.dropped == {} and follower.counters.dropped == {}
        assert follower.counters.received["pose"] == len(poses)


async def test_bad_messages_are_dropped_and_counted_never_raised(server):
    poses, controls = [], []

    def flaky_control(msg):
        controls.append(msg)
        if isinstance(msg, Scan):
            raise RuntimeError("daemon bug")

    expert = PeerLink("expert", _config(server))
    follower = PeerLink("follower", _config(server), on_pose=poses.append, on_control=flaky_control)
    async with running_links(expert, follower, timeout=20):
        raw = expert.peer_connection
        assert raw is not None
        channels = expert._peer.channels  # the raw aiortc channels, to send garbage
        good = PoseMessage(10, expert.now(), (0.0, 0.0, 0.0), Q).encode()
        nan = good[:14] + struct.pack("<d", float("nan")) + good[22:]
        channels["pose"].send(good)
        channels["pose"].send(good[:-3])  # short
        channels["pose"].send(good + b"xx")  # long
        channels["pose"].send(bytes([99]) + good[1:])  # wrong version
        channels["pose"].send(nan)
        channels["pose"].send("text on a binary channel")
        channels["pose"].send(PoseMessage(9, expert.now(), (0.0, 0.0, 0.0), Q).encode())  # late
        channels["control"].send("{broken json")
        channels["control"].send('{"type": "scan", "action": "explode"}')
        expert.send_control(Scan(action="stop"))  # callback raises: counted, link lives
        await until(lambda: follower.counters.dropped.total() >= 9)
        dropped = follower.counters.dropped
        assert dropped["pose:size"] == 2
        assert dropped["pose:version"] == 1
        assert dropped["pose:nonfinite"] == 1
        assert dropped["pose:type"] == 1
        assert dropped["pose:stale"] == 1
        assert dropped["control:json"] == 1
        assert dropped["control:schema"] == 1
        assert dropped["control:callback_error"] == 1
        assert [p.seq for p in poses] == [10]
        # the link still works
        assert expert.send_pose(PoseMessage(11, expert.now(), (0.0, 0.0, 0.0), Q))
        await until(lambda: len(poses) == 2)
        assert follower.state == "connected"
        # sending a NaN is refused at the sender
        assert not expert.send_pose(PoseMessage(12, expert.now(), (float("nan"), 0.0, 0.0), Q))
        assert expert.counters.dropped["pose:invalid_nonfinite"] == 1


async def test_sending_while_not_connected_is_counted(server):
    link = PeerLink("expert", _config(server))
    assert not link.send_pose(PoseMessage(1, 0.0, (0.0, 0.0, 0.0), Q))
    assert not link.send_control(Scan(action="start"))
    assert link.counters.dropped == {"pose:not_connected": 1, "control:not_connected": 1}
    assert link.age_of(1.0) is None


async def test_heartbeat_finds_a_silent_peer_and_the_link_comes_back(server):
    cfg = _config(server, heartbeat_interval_s=0.2, heartbeat_timeout_s=0.8)
    states = []
    expert = PeerLink("expert", cfg, on_link_state=states.append)
    follower = PeerLink("follower", cfg, on_pose=lambda m: None)
    async with running_links(expert, follower, timeout=20):
        # the follower goes silent while ICE and SCTP stay up (a hung process, say)
        silent = follower._peer
        follower._peer = None
        t0 = time.monotonic()
        await expert.wait_state("disconnected", "connecting", timeout=5)
        assert time.monotonic() - t0 < 3.0  # generous; the timeout is 0.8 s
        await silent.pc.close()
        # the expert offers again (the follower is still in the room) and both reconnect
        await expert.wait_state("connected", timeout=20)
        await follower.wait_state("connected", timeout=20)
        assert expert.counters.connections == 2
        assert expert.send_pose(PoseMessage(1, expert.now(), (0.0, 0.0, 0.0), Q))
        await until(lambda: follower.counters.received["pose"] == 1)
    assert states[:2] == ["connecting", "connected"] and "disconnected" in states


async def test_bye_on_close_and_wrong_token_fails(server):
    expert = PeerLink("expert", _config(server))
    follower = PeerLink("follower", _config(server))
    async with running_links(expert, follower, timeout=20):
        await expert.close()
        await follower.wait_state("disconnected", timeout=5)
        assert expert.state == "closed"
    bad = PeerLink("expert", _config(server, token="nope"))
    with pytest.raises(SignalingRefused, match="token"):
        await asyncio.wait_for(bad.run(), 10)
    assert bad.state == "failed"


async def test_a_stalled_daemon_does_not_take_its_own_stall_for_a_silent_peer():
    """Both daemons' loop stalls (here one loop: the whole process starved) longer than the
    heartbeat timeout: the watchdog's first tick after it comes late, and the messages sent
    meanwhile are read before the silence is judged; the link stays up. (The signaling
    server's own heartbeat is taken out of this test: it has its own.)"""
    s = SignalingServer(SignalConfig(port=0, heartbeat_s=30.0), TOKEN)
    await s.start()
    try:
        cfg = _config(s, heartbeat_interval_s=0.1, heartbeat_timeout_s=0.5)
        states = []
        expert = PeerLink("expert", cfg, on_link_state=states.append)
        follower = PeerLink("follower", cfg, on_pose=lambda m: None)
        async with running_links(expert, follower, timeout=20):
            await asyncio.sleep(0.5)  # heartbeats flowing
            for _ in range(3):
                time.sleep(0.9)  # the loop stalls (under the signaling client's 1 s pong wait)
                await asyncio.sleep(1.0)
            assert expert.state == "connected" and follower.state == "connected"
            assert expert.counters.connections == 1 and "disconnected" not in states
    finally:
        await s.stop()

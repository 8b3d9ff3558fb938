"""Two PeerLinks with relay_only=True through a real coturn ``turnserver`` on loopback, then
through the user-space delay relay in front of it (the WAN emulation of the 750 km link)."""

import asyncio
import contextlib
import statistics
import time

import pytest
from link_helpers import running_links

from humantele.signaling.server import SignalConfig, SignalingServer
from humantele.transport import LinkConfig, PeerLink
from humantele.transport.netem import NetemConfig, UdpRelay
from humantele.transport.turnserver import TurnServer, TurnServerError
from humantele.wire import PoseMessage
from waits import until

TOKEN = "turn-test-token"
Q = (0.0, 0.0, 0.0, 1.0)

pytestmark = pytest.mark.skipif(
    not TurnServer.available(),
    reason="no turnserver (system package coturn)",
)


@pytest.fixture
async def signaling():
    s = SignalingServer(SignalConfig(port=0), TOKEN)
    await s.start()
    yield s
    await s.stop()


@pytest.fixture
async def turn():
    server = TurnServer()
    await server.start()
    yield server
    await server.stop()


def _config(signaling, ice_server, **kw) -> LinkConfig:
    return LinkConfig(
        signaling_url=signaling.url,
        token=TOKEN,
        room="turn",
        ice_servers=[ice_server],
        relay_only=True,
        **kw,
    )


def _ice_snapshot(link: PeerLink) -> dict:
    """Local candidate types and the nominated ICE pair of the link's data transport (aiortc
    has no ICE stats, so the pair is read from the aioice connection under RTCIceTransport)."""
    ice = link.peer_connection.sctp.transport.transport
    pair = ice._connection._nominated[1]
    return {
        "local_types": {c.type for c in ice.iceGatherer.getLocalCandidates()},
        "local": pair.local_candidate,
        "remote": pair.remote_candidate,
    }


async def _stream_poses(expert: PeerLink, follower: PeerLink, ages: list, n: int) -> None:
    """Wait for clock sync (the fast pings), then send n poses at ~500 Hz."""
    end = time.monotonic() + 10
    while not (follower.clock.synced and follower.clock.rtt is not None):
        assert time.monotonic() < end, "no clock sync"
        await asyncio.sleep(0.05)
    await asyncio.sleep(1.0)  # all fast sync pings: the min-rtt filter settles
    ages.clear()
    for i in range(n):
        expert.send_pose(PoseMessage(i, expert.now(), (0.0, 0.1, 0.0), Q))
        await asyncio.sleep(0.002)
    with contextlib.suppress(TimeoutError):  # all in, or 0.5 s (unreliable: a few may be lost)
        await until(lambda: len(ages) >= n, timeout=0.5)


async def _run(signaling, expert_ice, follower_ice, n=200):
    ages: list[float] = []
    follower: PeerLink
    expert = PeerLink("expert", _config(signaling, expert_ice))
    follower = PeerLink(
        "follower",
        _config(signaling, follower_ice),
        on_pose=lambda m: ages.append(follower.age_of(m.t_sent)),
    )
    async with running_links(expert, follower, timeout=30):
        pairs = [_ice_snapshot(link) for link in (expert, follower)]
        await _stream_poses(expert, follower, ages, n)
        rtt, offset = follower.clock.rtt, follower.clock.offset
    return ages, pairs, rtt, offset


@pytest.mark.slow
async def test_links_connect_through_turn_only_and_poses_arrive(signaling, turn):
    ages, pairs, rtt, offset = await _run(signaling, turn.ice_server(), turn.ice_server())
    assert len(ages) >= 0.9 * 200  # unreliable channel on loopback: nearly all arrive
    assert all(a is not None for a in ages)
    for pair in pairs:
        assert pair["local_types"] == {"relay"}
        assert pair["local"].type == "relay"
        assert pair["remote"].type == "relay"
    # each side's nominated local candidate is the other side's remote one
    assert pairs[0]["local"].port == pairs[1]["remote"].port
    assert pairs[1]["local"].port == pairs[0]["remote"].port
    assert statistics.median(ages) < 0.05  # loopback through coturn: well under 50 ms
    assert abs(offset) <= rtt / 2  # one machine: the true offset is 0 (NTP's error bound)
    # coturn really allocated relays for both peers (its own log)
    assert turn.log_tail(200_000).count("ALLOCATE processed, success") >= 2


@pytest.mark.slow
async def test_the_delay_relay_in_front_of_turn_adds_its_one_way_delay(signaling, turn):
    base, _pairs, base_rtt, _ = await _run(signaling, turn.ice_server(), turn.ice_server(), 100)
    delay = 0.020
    async with UdpRelay((turn.host, turn.port), NetemConfig(delay_s=delay, seed=3)) as relay:
        host, port = relay.address
        # only the expert goes through the relay: each direction crosses it once
        ages, pairs, rtt, offset = await _run(
            signaling, turn.ice_server(host, port), turn.ice_server(), 200
        )
        counters = relay.counters
    assert counters.clients >= 1 and counters.up.forwarded > 200 and counters.down.forwarded > 0
    assert all(p["local"].type == p["remote"].type == "relay" for p in pairs)
    p50, p50_base = statistics.median(ages), statistics.median(base)
    assert 0.015 <= p50 <= 0.200
    assert p50 - p50_base >= 0.015  # grew by about the injected one-way delay
    assert rtt >= 2 * delay - 0.002  # the sync's round trip crosses the relay both ways
    assert abs(offset) < 0.010  # symmetric delay: the offset estimate stays ~0
    assert len(ages) >= 0.9 * 200


async def test_a_turn_server_that_cannot_start_raises_with_its_log():
    # the port is held by another UDP socket: turnserver cannot listen and never answers
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        server = TurnServer(port=port, start_timeout_s=1.0)
        with pytest.raises(TurnServerError) as info:
            await server.start()
    assert f"did not answer on turn:127.0.0.1:{port}" in str(info.value)
    assert "Cannot bind" in str(info.value)  # coturn's own log says why
    assert server._proc is None  # nothing left running

"""Time-limited TURN credentials against the real coturn: ``turnserver`` started with
``use-auth-secret`` and ``static-auth-secret`` (no static user), the signaling server issuing
the credentials (humantele.signaling.turn). A fresh credential allocates a relay and the two
links connect through it; an expired one, or one made with another secret, is refused by
coturn itself (its 401 and its log line)."""

import asyncio
import time

import pytest
from aioice.stun import TransactionFailed
from aioice.turn import create_turn_endpoint
from link_helpers import running_links

from humantele.signaling.server import SignalConfig, SignalingServer
from humantele.signaling.turn import TurnConfig, TurnIssuer
from humantele.transport import LinkConfig, PeerLink
from humantele.transport.turnserver import TurnServer
from waits import until

TOKEN = "turn-rest-test-token"
SECRET = "4f0c9d1e7a2b6c3d8e5f0a1b2c3d4e5f"  # the deployment's shared secret (tests only)

pytestmark = [
    pytest.mark.skipif(
        not TurnServer.available(),
        reason="no turnserver (system package coturn)",
    ),
    pytest.mark.e2e,
    pytest.mark.slow,
]


@pytest.fixture
async def turn():
    server = TurnServer(auth_secret=SECRET)
    await server.start()
    yield server
    await server.stop()


def _issuer(turn: TurnServer, shift_s: float = 0.0, secret: str = SECRET) -> TurnIssuer:
    """The signaling server's issuer for ``turn``; ``shift_s`` moves its clock (s)."""
    return TurnIssuer(
        TurnConfig(urls=[turn.url], ttl_s=600), secret, clock=lambda: time.time() + shift_s
    )


async def _allocate(turn: TurnServer, username: str, credential: str) -> tuple[str, int]:
    """Allocate a relay on ``turn`` with these credentials; its relayed address."""
    transport, _ = await create_turn_endpoint(
        asyncio.DatagramProtocol, (turn.host, turn.port), username, credential
    )
    try:
        return transport.get_extra_info("sockname")
    finally:
        transport.close()


async def test_coturn_allocates_for_a_fresh_credential_and_refuses_an_expired_one(turn):
    fresh = _issuer(turn).issue("expert-fresh")
    host, port = await _allocate(turn, fresh.username, fresh.credential)
    assert host == turn.host and port > 0

    # issued 20 min ago with a 10 min lifetime: expired 10 min ago
    expired = _issuer(turn, shift_s=-1200).issue("expert-expired")
    assert expired.expires < time.time()
    with pytest.raises(TransactionFailed, match="401"):
        await _allocate(turn, expired.username, expired.credential)

    # right format, unexpired, but another secret: refused too
    forged = _issuer(turn, secret="another-secret-of-32-characters!").issue("expert-forged")
    with pytest.raises(TransactionFailed, match="401"):
        await _allocate(turn, forged.username, forged.credential)

    log = turn.log_tail(200_000)
    assert f"user <{fresh.username}>: incoming packet ALLOCATE processed, success" in log
    for refused in (expired, forged):
        assert f"Cannot find credentials of user <{refused.username}>" in log
        assert f"user <{refused.username}>: incoming packet ALLOCATE processed, success" not in log
    assert SECRET not in log


async def test_an_allocation_outlives_its_credential_but_a_new_one_is_refused(turn):
    # what docs/signaling.md promises: a relay made before the expiry is refreshed after it
    # (coturn keeps the session's key), a new allocation with the same credential is refused
    from aioice import stun

    entry = _issuer(turn, shift_s=-598).issue("expert-short")  # expires in 2 s
    transport, _ = await create_turn_endpoint(
        asyncio.DatagramProtocol, (turn.host, turn.port), entry.username, entry.credential
    )
    try:
        await until(lambda: time.time() > entry.expires + 1, timeout=30, poll=0.1)
        refresh = stun.Message(message_method=stun.Method.REFRESH, message_class=stun.Class.REQUEST)
        refresh.attributes["LIFETIME"] = 600
        protocol = transport._TurnTransport__inner_protocol  # aioice keeps it private
        response, _ = await protocol.request_with_retry(refresh)
        assert response.attributes["LIFETIME"] == 600
    finally:
        transport.close()
    try:
        granted = await _allocate(turn, entry.username, entry.credential)
    except TransactionFailed as exc:
        assert "401" in str(exc), exc
    else:  # seen once in a whole suite (16:36 UTC 2026-11-28), not reproduced: say what it was
        pytest.fail(
            f"a new allocation with a credential expired {time.time() - entry.expires:.1f} s "
            f"ago was granted ({granted}); coturn's log:\n{turn.log_tail(6000)}"
        )
    log = turn.log_tail(200_000)
    assert f"user <{entry.username}>: incoming packet REFRESH processed, success" in log


async def test_several_coturn_servers_behind_one_secret_and_its_rotation(turn):
    # a second coturn with the same secret: every issued credential works on both
    async with TurnServer(auth_secret=SECRET) as other:
        issuer = TurnIssuer(TurnConfig(urls=[turn.url, other.url], ttl_s=600), SECRET)
        entry = issuer.issue("follower-both")
        for server in (turn, other):
            await _allocate(server, entry.username, entry.credential)
    # rotation: a coturn with the old and the new secret takes credentials made with either
    new = "0123456789abcdef0123456789abcdef"
    async with TurnServer(auth_secret=[SECRET, new]) as rotating:
        for secret in (SECRET, new):
            e = _issuer(rotating, secret=secret).issue("expert-rotating")
            await _allocate(rotating, e.username, e.credential)
        stranger = _issuer(rotating, secret="not-one-of-them-0123456789abcdef").issue("x")
        with pytest.raises(TransactionFailed, match="401"):
            await _allocate(rotating, stranger.username, stranger.credential)


def _links(signaling: SignalingServer) -> tuple[PeerLink, PeerLink]:
    """Two relay-only links with no ICE server of their own: TURN comes from signaling."""
    cfg = {"signaling_url": signaling.url, "token": TOKEN, "room": "rest", "relay_only": True}
    return PeerLink("expert", LinkConfig(**cfg)), PeerLink("follower", LinkConfig(**cfg))


async def test_links_connect_through_coturn_with_credentials_from_signaling(turn):
    signaling = SignalingServer(SignalConfig(port=0), TOKEN, turn_issuer=_issuer(turn))
    await signaling.start()
    try:
        expert, follower = _links(signaling)
        async with running_links(expert, follower, timeout=30):
            users = [link._issued[0].username for link in (expert, follower)]
            for link in (expert, follower):
                ice = link.peer_connection.sctp.transport.transport
                pair = ice._connection._nominated[1]
                assert pair.local_candidate.type == pair.remote_candidate.type == "relay"
    finally:
        await signaling.stop()
    assert users[0] != users[1]
    assert users[0].split(":")[1].startswith("expert-")
    assert users[1].split(":")[1].startswith("follower-")
    log = turn.log_tail(400_000)
    for user in users:  # coturn allocated for each peer with its own issued credential
        assert f"user <{user}>: incoming packet ALLOCATE processed, success" in log
    assert signaling.counters["turn:issued"] >= 2


async def test_links_do_not_get_through_coturn_with_expired_credentials(turn):
    # the signaling server's clock is 2 h behind (its credentials expired 1 h 50 min ago by
    # coturn's clock); the peers' clocks agree with it, so they use them and coturn refuses
    shift = -7200.0
    signaling = SignalingServer(SignalConfig(port=0), TOKEN, turn_issuer=_issuer(turn, shift))
    await signaling.start()
    expert, follower = _links(signaling)
    tasks = []
    try:
        for link in (expert, follower):
            link._wall_clock = lambda: time.time() + shift
            tasks.append(asyncio.create_task(link.run()))
        await until(lambda: expert._issued and follower._issued, timeout=30)
        user = expert._issued[0].username
        refusal = f"user <{user}>: incoming packet message processed, error 401: Unauthorized"
        # coturn refuses the expert's allocation (the one it makes for its offer)
        await until(lambda: refusal in turn.log_tail(400_000), timeout=60)
        assert not expert.connected and not follower.connected
    finally:
        for link in (expert, follower):
            await link.close()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await signaling.stop()
    log = turn.log_tail(400_000)
    assert "ALLOCATE processed, success" not in log


async def test_the_peer_drops_credentials_its_own_clock_says_have_expired(turn):
    # the signaling server's clock is 2 h behind and the peers' clocks are right: they drop
    # the credentials with a clear error instead of trying them, and count it
    signaling = SignalingServer(SignalConfig(port=0), TOKEN, turn_issuer=_issuer(turn, -7200))
    await signaling.start()
    expert, _ = _links(signaling)
    task = asyncio.create_task(expert.run())
    try:
        await until(lambda: expert.counters.dropped["signaling:bad_ice_server"] >= 1, timeout=30)
        assert expert._issued == []
    finally:
        await expert.close()
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        await signaling.stop()

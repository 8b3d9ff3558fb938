"""wss:// served directly, a client trusting a given CA, and no token in clear off loopback.

Certificates are made in the test with ``cryptography`` (already installed with aiortc, no
external tool): a CA and a server certificate for 127.0.0.1 it signed (signaling_helpers)."""

import asyncio

import pytest
from pydantic import ValidationError
from signaling_helpers import make_certificates, running_server

from humantele.config import ConfigError
from humantele.signaling.client import SignalingClient, SignalingError
from humantele.signaling.messages import Offer
from humantele.signaling.server import SignalConfig, SignalingServer
from humantele.transport import LinkConfig, PeerLink

TOKEN = "tls-token"


@pytest.fixture
def certs(tmp_path):
    return make_certificates(tmp_path)


@pytest.fixture
async def wss_server(certs):
    _, cert, key = certs
    async with running_server(TOKEN, tls_cert=cert, tls_key=key) as s:
        yield s


async def test_wss_join_and_relay_trusting_the_deployment_ca(wss_server, certs):
    ca, _, _ = certs
    assert wss_server.url.startswith("wss://127.0.0.1:")
    expert = SignalingClient(wss_server.url, "r", "expert", TOKEN, ca_file=ca)
    follower = SignalingClient(wss_server.url, "r", "follower", TOKEN, ca_file=ca)
    await expert.join()
    assert (await follower.join()).peer_present
    await expert.receive()  # peer_joined
    await expert.send(Offer(sdp="v=0", id=3))
    assert await asyncio.wait_for(follower.receive(), 5) == Offer(sdp="v=0", id=3)
    await expert.close()
    await follower.close()


async def test_a_client_without_the_ca_or_speaking_plain_ws_gets_no_room(wss_server):
    stranger = SignalingClient(wss_server.url, "r", "expert", TOKEN)  # system CAs only
    with pytest.raises(SignalingError, match="(?i)certificate"):
        await stranger.join()
    plain = SignalingClient(wss_server.url.replace("wss:", "ws:"), "r", "expert", TOKEN)
    with pytest.raises(SignalingError):
        await plain.join()
    assert wss_server.rooms == {}


async def test_links_negotiate_through_wss(wss_server, certs):
    """signaling_ca_file reaches the client through LinkConfig and PeerLink."""
    ca, _, _ = certs
    cfg = {"signaling_url": wss_server.url, "signaling_ca_file": ca, "token": TOKEN}
    expert, follower = (
        PeerLink("expert", LinkConfig(**cfg)),
        PeerLink("follower", LinkConfig(**cfg)),
    )
    tasks = [asyncio.create_task(expert.run()), asyncio.create_task(follower.run())]
    try:
        await expert.wait_state("connected", timeout=30)
        await follower.wait_state("connected", timeout=30)
    finally:
        await expert.close()
        await follower.close()
        await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), 10)


def test_a_non_loopback_bind_needs_tls_or_insecure(certs):
    _, cert, key = certs
    with pytest.raises(ConfigError, match="tls_cert.*--insecure"):
        SignalingServer(SignalConfig(host="0.0.0.0"), token="real")
    SignalingServer(SignalConfig(host="0.0.0.0", tls_cert=cert, tls_key=key), token="real")
    SignalingServer(SignalConfig(host="0.0.0.0", insecure=True), token="real")  # behind a proxy
    SignalingServer(SignalConfig(host="::1"), token="real")  # loopback: fine


def test_unusable_certificates_are_config_errors_naming_the_field(tmp_path, certs):
    ca, cert, key = certs
    junk = tmp_path / "junk.pem"
    junk.write_text("not a certificate\n")
    with pytest.raises(ConfigError, match="tls_cert"):
        SignalingServer(SignalConfig(tls_cert=junk), token="real")
    with pytest.raises(ConfigError, match="tls_cert/tls_key"):
        SignalingServer(SignalConfig(tls_cert=cert, tls_key=ca), token="real")  # wrong key
    with pytest.raises(ValidationError, match="tls_key needs tls_cert"):
        SignalConfig(tls_key=key)
    with pytest.raises(ValidationError, match="tls_cert"):
        SignalConfig(tls_cert=tmp_path / "missing.pem")
    with pytest.raises(ValidationError, match="signaling_ca_file"):
        LinkConfig(signaling_ca_file=junk)

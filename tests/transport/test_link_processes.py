"""Real aiortc between two OS processes: the follower process is killed and restarted, and the
expert's link comes back by itself through signaling."""

import asyncio
import contextlib
import os
import signal
import sys

import pytest

from humantele.signaling.messages import TOKEN_ENV
from humantele.signaling.server import SignalConfig, SignalingServer
from humantele.transport import LinkConfig, PeerLink
from humantele.wire import PoseMessage, StateMessage
from waits import until

TOKEN = "process-test-token"
Q = (0.0, 0.0, 0.0, 1.0)


async def _spawn_follower(url: str, room: str) -> asyncio.subprocess.Process:
    env = {**os.environ, TOKEN_ENV: TOKEN}
    return await asyncio.create_subprocess_exec(
        sys.executable, "-m", "humantele.bench.session", "--child", "echo-follower",
        "--url", url, "--room", room,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE, env=env,
    )  # fmt: skip


@pytest.mark.slow
async def test_rejoin_after_the_follower_process_is_killed_and_restarted():
    server = SignalingServer(SignalConfig(port=0), TOKEN)
    await server.start()
    echoes: list[StateMessage] = []
    expert = PeerLink(
        "expert",
        LinkConfig(
            signaling_url=server.url,
            room="proc",
            token=TOKEN,
            heartbeat_interval_s=0.25,
            heartbeat_timeout_s=1.0,
        ),  # fmt: skip
        on_state=echoes.append,
    )
    run = asyncio.create_task(expert.run())
    seq = 0

    async def send_poses() -> None:
        nonlocal seq
        while True:
            seq += 1
            expert.send_pose(PoseMessage(seq, expert.now(), (0.0, 0.1, 0.0), Q))
            await asyncio.sleep(0.01)

    sender = asyncio.create_task(send_poses())
    procs = []
    try:
        procs.append(await _spawn_follower(server.url, "proc"))
        await expert.wait_state("connected", timeout=60)
        await until(lambda: len(echoes) >= 20, 30)
        # the echo carries our sequence back: the other process really got our poses
        assert all(e.seq <= seq for e in echoes)
        await until(lambda: expert.clock.synced, 10)
        # one machine: the true offset is 0, found within half the round trip (NTP's bound)
        assert abs(expert.clock.offset) <= expert.clock.rtt / 2
        first_connections = expert.counters.connections

        procs[0].send_signal(signal.SIGKILL)
        await procs[0].wait()
        await expert.wait_state("disconnected", "connecting", timeout=10)
        n_before = len(echoes)

        procs.append(await _spawn_follower(server.url, "proc"))
        await expert.wait_state("connected", timeout=60)
        await until(lambda: len(echoes) >= n_before + 20, 30)
        assert expert.counters.connections == first_connections + 1
        assert echoes[-1].seq > echoes[n_before - 1].seq
    finally:
        sender.cancel()
        await expert.close()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(run, 10)
        for p in procs:
            if p.returncode is None:
                p.send_signal(signal.SIGTERM)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(p.wait(), 5)
                if p.returncode is None:
                    p.kill()
                    await p.wait()
        await server.stop()

"""A daemon that was not asked to stop never exits 0 (issue 20 §2): a supervisor reads 0 as a
requested stop. Under load the expert once exited 0 in the middle of a run: its link's task
had ended (an error the signaling retry loop did not expect), which ended the main loop, and
the exit code did not look at why."""

import asyncio
import types

from humantele.cliargs import EXIT_FAILED, EXIT_OK
from humantele.daemons.common import Daemon
from humantele.signaling.client import SignalingClient
from humantele.transport import LinkConfig, PeerLink


class _Link:
    """A link whose ``run`` raises ``fail`` after ``after_s`` (None: runs until closed)."""

    def __init__(self, fail: BaseException | None, after_s: float = 0.05) -> None:
        self.fail, self.after_s = fail, after_s
        self.closed = asyncio.Event()

    async def run(self) -> None:
        if self.fail is None:
            await self.closed.wait()
            return
        await asyncio.sleep(self.after_s)
        raise self.fail

    async def close(self, reason: str) -> None:
        self.closed.set()


class _Daemon(Daemon):
    """The daemons' run() shape (daemons.common): ticks until stopped or the link ends."""

    role = "test"

    def __init__(self, link: _Link) -> None:
        config = types.SimpleNamespace(session=None, recording=None)
        super().__init__(config)
        self.link = link
        self.ticks = 0

    def stats(self) -> dict:
        return {"ticks": self.ticks}

    async def run(self, duration_s: float | None = None, stop_after: int | None = None) -> int:
        link_task = asyncio.create_task(self.link.run())
        try:
            async for _ in self.loop_ticks(100.0, duration_s, link_task):
                self.ticks += 1
                if stop_after is not None and self.ticks >= stop_after:
                    self.stop()
        finally:
            await self.close_link(self.link, link_task)
            self.stats_out.close(self.stats())
        return self.run_result(link_task)


async def test_a_link_task_that_raises_ends_the_run_with_failure_not_0(capsys):
    d = _Daemon(_Link(ConnectionResetError(104, "Connection reset by peer")))
    assert await asyncio.wait_for(d.run(), 60.0) == EXIT_FAILED
    err = capsys.readouterr().err
    assert "link ended unexpectedly" in err and "ConnectionResetError" in err


async def test_a_link_task_that_returns_by_itself_is_a_failure_too():
    class Returns(_Link):
        async def run(self) -> None:
            await asyncio.sleep(0.05)

    assert await asyncio.wait_for(_Daemon(Returns(None)).run(), 60.0) == EXIT_FAILED


async def test_a_requested_stop_and_the_duration_exit_0():
    assert await asyncio.wait_for(_Daemon(_Link(None)).run(stop_after=5), 60.0) == EXIT_OK
    assert await asyncio.wait_for(_Daemon(_Link(None)).run(duration_s=0.1), 60.0) == EXIT_OK


async def test_the_link_retries_after_an_error_signaling_did_not_wrap(monkeypatch):
    """An OSError while joining (the socket reset under load, outside the part of the join
    that wraps errors) is retried with back-off, as an unreachable server is: the link's
    task keeps running, so the daemon does too."""
    calls = []

    async def join(self):
        calls.append(1)
        raise ConnectionResetError(104, "Connection reset by peer")

    monkeypatch.setattr(SignalingClient, "join", join)
    link = PeerLink(
        "expert",
        LinkConfig(signaling_url="ws://127.0.0.1:9/ws", reconnect_delay_s=0.01,
                   reconnect_max_delay_s=0.02),
    )  # fmt: skip
    task = asyncio.create_task(link.run())
    for _ in range(3000):
        if len(calls) >= 3 or task.done():
            break
        await asyncio.sleep(0.01)
    assert not task.done(), task.exception()
    assert len(calls) >= 3 and link.counters.dropped["signaling:error"] >= 3
    assert link.state == "unreachable"
    await link.close()
    await asyncio.wait_for(task, 30.0)

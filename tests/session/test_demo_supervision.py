"""The demo supervises its daemons: a killed one comes back (issue 9 §5). The follower
SIGKILLed during a whole demo: tests/test_wheel_install.py, on the installed demo's session."""

from __future__ import annotations

import os
import socket
import time

import pytest

from humantele.demo_report import CountWindow
from humantele.runtime.supervise import SupervisedDaemon


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("HUMANTELE_TOKEN", None)
    return env


async def _run_until_done(d: SupervisedDaemon, timeout_s: float = 120.0) -> str | None:
    import asyncio

    await d.start()
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        reason = await d.check(time.monotonic())
        if reason:
            return reason
        await asyncio.sleep(0.05)
    return None


@pytest.mark.e2e  # starts the signaling daemon four times (the fast lane leaves it out)
async def test_restarts_are_bounded_and_fatal_exits_are_not_restarted(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = str(busy.getsockname()[1])
        argv = ["signal", "--port", port]
        d = SupervisedDaemon("signal", argv, tmp_path / "s.json", tmp_path / "s.log", _env(),
                             max_restarts=2, backoff_s=0.05)  # fmt: skip
        reason = await _run_until_done(d)
    assert reason == "signal exited with code 1 after 2 restart(s); giving up"
    assert d.restarts == 2 and d.exit_codes == [1, 1, 1]
    assert (tmp_path / "s.log").read_text().count("the port is in use") == 3
    fatal = SupervisedDaemon("signal", ["signal", "--port", "70000"], tmp_path / "f.json",
                             tmp_path / "f.log", _env(), backoff_s=0.05)  # fmt: skip
    assert await _run_until_done(fatal) == "signal exited with code 2"  # bad arguments
    assert fatal.restarts == 0


def test_count_window_takes_both_ends_from_the_rejoin():
    class D:
        def __init__(self, restarts):
            self.restarts = restarts

    w = CountWindow()
    e = {"poses_sent": 500, "states_received": 480}
    w.update({"expert": D(0), "follower": D(0)}, {"expert": e, "follower": {}}, 5.0)
    assert w.since_s is None
    # The follower was killed and restarted; its first stats appear at 12 s.
    e = {"poses_sent": 900, "states_received": 700}
    f = {"poses_received": 3, "states_sent": 0}
    w.update({"expert": D(0), "follower": D(1)}, {"expert": e, "follower": f}, 12.0)
    e = {"poses_sent": 1900, "states_received": 1650}
    f = {"poses_received": 990, "states_sent": 950}
    e2, f2 = w.adjusted({"expert": e, "follower": f})
    assert w.since_s == 12.0
    assert (e2["poses_sent"], e2["states_received"]) == (1000, 950)
    assert f2 == f  # the restarted daemon's own counts start at its start
    assert f2["poses_received"] <= e2["poses_sent"] and e2["states_received"] <= f2["states_sent"]


def test_count_window_starts_at_the_restart_not_at_the_new_process_first_stats():
    class D:
        def __init__(self, restarts):
            self.restarts = restarts

    w = CountWindow()
    # The follower has just been restarted: no stats of the new process yet (its old file was
    # moved aside). The expert's count now is the baseline: nothing can have reached the new
    # process before it.
    w.update(
        {"expert": D(0), "follower": D(1)}, {"expert": {"poses_sent": 900}, "follower": {}}, 7.0
    )
    assert w.since_s == 7.0
    # By its first stats the new follower had already received 40 poses; the window counts them.
    e = {"poses_sent": 960, "states_received": 0}
    f = {"poses_received": 40, "states_sent": 0}
    w.update({"expert": D(0), "follower": D(1)}, {"expert": e, "follower": f}, 9.0)
    e2, f2 = w.adjusted({"expert": e, "follower": f})
    assert w.since_s == 7.0
    assert f2["poses_received"] <= e2["poses_sent"] == 60

"""A daemon whose signaling host does not resolve: a clear warning at every retry, with backoff,
its status shows the link 'unreachable', no traceback, and it stops cleanly."""

import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from humantele.runtime.process import PARENT_PID_ENV


def _stats(path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


@pytest.mark.e2e  # starts a daemon (the fast lane leaves it out)
def test_follower_with_an_unresolvable_signaling_host(tmp_path):
    stats, log_path = tmp_path / "follower.json", tmp_path / "follower.log"
    env = dict(os.environ, HUMANTELE_TOKEN="daemon-token", **{PARENT_PID_ENV: str(os.getpid())})
    args = [sys.executable, "-m", "humantele", "follower",
            "--signaling-url", "ws://signaling.invalid:8765/ws",  # RFC 2606: never resolves
            "--state-dir", str(tmp_path / "state"), "--feed-port", "0",
            "--stats-file", str(stats), "--log-level", "INFO"]  # fmt: skip
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(args, stdout=log, stderr=log, env=env)
    try:
        deadline = time.monotonic() + 90
        while _stats(stats).get("link_state") != "unreachable" or (
            log_path.read_text().count("retrying in") < 3
        ):
            assert proc.poll() is None, log_path.read_text()
            assert time.monotonic() < deadline, log_path.read_text()
            time.sleep(0.1)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    text = log_path.read_text()
    assert "Traceback" not in text
    warnings = [line for line in text.splitlines() if "retrying in" in line]
    assert all("cannot reach signaling server ws://signaling.invalid" in w for w in warnings)
    delays = [float(re.search(r"retrying in ([0-9.]+) s", w).group(1)) for w in warnings]
    assert delays[:3] == [0.5, 1.0, 2.0]  # the link's backoff

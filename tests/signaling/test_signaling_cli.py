"""`humantele signal` errors a user sees: one clear line and a non-zero exit, no traceback."""

import os
import socket
import subprocess
import sys

import pytest

pytestmark = pytest.mark.e2e  # each test runs `humantele signal` (not in the fast lane)


def _signal(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "HUMANTELE_TOKEN": "cli-token"}
    return subprocess.run(
        [sys.executable, "-m", "humantele", "signal", *args],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )


@pytest.fixture
def busy_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


def test_port_in_use_is_one_line_and_exit_1(busy_port):
    r = _signal("--port", str(busy_port))
    assert r.returncode == 1
    assert "Traceback" not in r.stderr
    lines = [line for line in r.stderr.splitlines() if "cannot listen" in line]
    assert lines == [f"humantele signal: cannot listen on 127.0.0.1:{busy_port}: the port is in use"
                     " (another server running?)"]  # fmt: skip


def test_unresolvable_host_is_one_line_and_exit_1():
    r = _signal("--host", "signaling.invalid", "--insecure", "--port", "0")
    assert r.returncode == 1
    assert "Traceback" not in r.stderr
    assert "humantele signal: cannot listen on signaling.invalid:0:" in r.stderr


@pytest.mark.parametrize(
    "args, message",
    [
        (["--host", "0.0.0.0"], "--insecure"),
        (["--tls-key", "/nonexistent.key"], "tls_key"),
        (["--tls-cert", "/nonexistent.pem"], "tls_cert"),
    ],
)
def test_unsafe_or_missing_tls_settings_are_configuration_errors(args, message):
    r = _signal(*args)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and message in r.stderr

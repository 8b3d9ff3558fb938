"""Stopping pytest leaves nothing running (issue 20 item 8): a test that started a process
group (as the browser and demo fixtures do: ``start_new_session``) and a grandchild in it,
then pytest stopped by Ctrl-C (SIGINT), SIGTERM or SIGHUP: all of them are gone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from procgroups import descendants, pid_alive

HERE = Path(__file__).resolve().parent

TEST = """
import os, subprocess, sys, time
from pathlib import Path

def test_starts_a_group_and_hangs():
    # A leader in its own session (as a fixture's Chromium or demo) with a grandchild, and
    # shared memory (as a daemon's video or servo) that its resource tracker would unlink.
    p = subprocess.Popen([sys.executable, "-c", LEADER], start_new_session=True)
    Path(os.environ["PIDFILE"]).write_text(str(p.pid))
    time.sleep(600)

LEADER = '''
import os, subprocess, sys, time
from multiprocessing import shared_memory
subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
shm = shared_memory.SharedMemory(create=True, size=4096)
open(os.environ["SHMFILE"], "w").write(shm.name)
time.sleep(600)
'''
"""


def as_a_shell_starts_it() -> None:
    """The stop signals at their defaults and none blocked, as a terminal's pytest has them
    (this worker's may not be: a test ran a daemon in it; the full suite's run hung on it)."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_SETMASK, [])


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_stopping_pytest_kills_what_its_tests_started(tmp_path, sig):
    (tmp_path / "test_hang.py").write_text(TEST)
    pidfile, shmfile = tmp_path / "pid", tmp_path / "shm"
    env = {**os.environ, "PIDFILE": str(pidfile), "SHMFILE": str(shmfile)}
    env["PYTHONPATH"] = os.pathsep.join([str(HERE), env.get("PYTHONPATH", "")])
    pytest_proc = subprocess.Popen(
        [sys.executable, "-m", "pytest", "-q", "-p", "procgroups", "-p", "no:cacheprovider",
         "-n", "0", "-o", "addopts=", str(tmp_path / "test_hang.py")],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        start_new_session=True, preexec_fn=as_a_shell_starts_it,
    )  # fmt: skip
    try:
        t_end = time.monotonic() + 120
        started: set[int] = set()
        while len(started) < 3 or not shmfile.exists():  # leader, grandchild, tracker
            assert pytest_proc.poll() is None, pytest_proc.stdout.read().decode()
            assert time.monotonic() < t_end, "the test's processes never started"
            if pidfile.exists():
                started = descendants(pytest_proc.pid)
            time.sleep(0.1)
        leader = int(pidfile.read_text())
        assert leader in started
        os.kill(pytest_proc.pid, sig)
        try:
            pytest_proc.wait(60)
        except subprocess.TimeoutExpired:  # say why: its signal state, as the kernel has it
            status = Path(f"/proc/{pytest_proc.pid}/status").read_text().splitlines()
            raise AssertionError(
                f"pytest did not stop on {sig.name}: "
                + "; ".join(x for x in status if x.startswith(("State", "Sig", "ShdPnd")))
            ) from None
        t_end = time.monotonic() + 30
        while any(pid_alive(p) for p in started) and time.monotonic() < t_end:
            time.sleep(0.1)
        assert not [p for p in started if pid_alive(p)], "left running after pytest stopped"
        # the leader's resource tracker was left to unlink what the killed leader made
        assert not Path("/dev/shm", shmfile.read_text()).exists()
    finally:
        for p in descendants(pytest_proc.pid) | started:
            try:
                os.kill(p, signal.SIGKILL)
            except OSError:
                pass
        if pytest_proc.poll() is None:
            os.killpg(pytest_proc.pid, signal.SIGKILL)
            pytest_proc.wait()

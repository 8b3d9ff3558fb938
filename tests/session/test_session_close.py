"""The tests' :class:`Session` ends what a test left running and leaves no shared memory: the
daemons and their children are killed, their resource trackers are not (killed with them, they
left an expert's servo blocks in /dev/shm, one set per browser run that killed an expert)."""

import asyncio
import os
import sys
from pathlib import Path

import pytest
from session_helpers import Session, descendants, pid_alive

# A stand-in daemon: shared memory (its resource tracker starts) and a child, as an expert
# with its servo has.
DAEMON = """
import os, subprocess, sys, time
from multiprocessing import shared_memory
subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
shm = shared_memory.SharedMemory(create=True, size=4096)
open(os.environ["SHMFILE"], "w").write(shm.name)
time.sleep(600)
"""


class _Server:  # the session's signaling server
    async def stop(self) -> None:
        pass


@pytest.mark.e2e  # runs a daemon-like process and its child (the fast lane leaves it out)
async def test_closing_kills_the_daemons_and_their_children_but_unlinks_their_memory(tmp_path):
    shmfile = tmp_path / "shm"
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-c", DAEMON, env={**os.environ, "SHMFILE": str(shmfile)}
    )
    session = Session(tmp_path, _Server(), "token")
    session.procs["expert"] = proc
    for _ in range(300):
        if shmfile.exists() and shmfile.read_text():
            break
        await asyncio.sleep(0.05)
    name = shmfile.read_text()
    assert Path("/dev/shm", name).exists()
    family = descendants(proc.pid)
    assert len(family) == 2  # its child and its resource tracker
    await session.close()
    assert proc.returncode is not None
    for _ in range(200):  # SIGKILLed: gone within moments; the tracker once it has unlinked
        if not [p for p in family if pid_alive(p)] and not Path("/dev/shm", name).exists():
            break
        await asyncio.sleep(0.05)
    assert not [p for p in family if pid_alive(p)]
    assert not Path("/dev/shm", name).exists()

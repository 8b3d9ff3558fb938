"""Signalling a child process started with asyncio, without taking its exit code from asyncio.

``asyncio.subprocess.Process.send_signal`` (and ``terminate``, ``kill``) goes through
``subprocess.Popen.send_signal``, which polls the child first (``waitpid(WNOHANG)``, Python
3.9 on): a child that has just exited, whose exit asyncio's child watcher has not yet
delivered, is reaped there, and the watcher's own ``waitpid`` then fails. asyncio says
"Unknown child process pid N, will report returncode 255" and the process's returncode is
255, not its own (CPython issue 86276). The demo's daemons, told to stop by a terminal's
Ctrl-C, exit by themselves just as the demo sends them SIGTERM: a follower that exited 0 was
reported as 255, and the demo exited 1 ("a daemon failed"). :func:`signal_child` looks at the
child with ``waitid(WNOWAIT)``, which leaves an exited child for the watcher to reap, and
sends the signal with ``os.kill`` only to a child that has not exited.
"""

from __future__ import annotations

import asyncio
import contextlib
import os


def signal_child(proc: asyncio.subprocess.Process, sig: int) -> bool:
    """Send ``sig`` to ``proc`` if it is still running, never reaping it; whether it was sent
    (False: it has exited, its exit code on its way to ``proc.returncode``)."""
    if proc.returncode is not None:
        return False
    try:
        exited = os.waitid(os.P_PID, proc.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT)
    except ChildProcessError:  # reaped by the watcher already
        return False
    if exited is not None:  # a zombie: the watcher reaps it
        return False
    with contextlib.suppress(ProcessLookupError):
        os.kill(proc.pid, sig)
    return True

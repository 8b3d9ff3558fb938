"""The first code a :func:`humantele.runtime.child.spawn` child runs. This module imports only
what the interpreter and ``multiprocessing`` have already loaded, so the child ignores the
process group's SIGINT and SIGTERM (a terminal's Ctrl-C, systemd's stop: its daemon stops it)
before it imports anything that takes time; then it imports and runs its target.

Why: a restarted sensing process died of a Ctrl-C while it imported its modules (seconds on a
loaded machine), with a KeyboardInterrupt traceback, before it could ignore the signal; a
first fix still imported asyncio here, and a Ctrl-C at load 20 landed in that import."""

from __future__ import annotations

import os
import signal
import threading
import time

PARENT_POLL_S = 0.5  # how often a child checks that its daemon is still there


GROUP_SIGNALS = (signal.SIGINT, signal.SIGTERM)  # reach the whole process group


def ignore_group_signals() -> None:
    """SIGINT and SIGTERM ignored: they reach the whole process group; the daemon stops us.
    Then unblocked (``spawn`` starts a child with them blocked: one that came meanwhile is
    pending, and now dropped)."""
    for sig in GROUP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, GROUP_SIGNALS)


def watch_parent(
    parent_pid: int, on_gone=None, grace_s: float = 3.0, poll_s: float = PARENT_POLL_S
) -> threading.Thread:
    """A daemon thread that, once ``parent_pid`` is no longer our parent (it died without
    stopping us), calls ``on_gone()`` (a stop flag: it must never wait on anyone) and ends
    the process ``grace_s`` later if it has not ended by itself."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(poll_s)
        if on_gone is not None:
            try:
                on_gone()
            except Exception:  # noqa: BLE001 - the process ends anyway
                pass
        time.sleep(grace_s)
        os._exit(0)

    t = threading.Thread(target=watch, name="humantele-parent-watch", daemon=True)
    t.start()
    return t


def set_process_name(name: str) -> None:
    """The process's name as ``ps``, ``top`` and /proc/PID/comm show it (15 bytes; Linux)."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(15, name.encode()[:15], 0, 0, 0)  # PR_SET_NAME
    except (OSError, AttributeError, ImportError):
        pass


class Pickled:
    """A target and its arguments, pickled by the daemon as it spawned the child (with the
    child's pipes, as multiprocessing passes them); unpickled by :meth:`load`, in the child."""

    def __init__(self, blob: bytes) -> None:
        self.blob = blob

    def load(self) -> tuple:
        import pickle

        return pickle.loads(self.blob)


def child_main(call: Pickled, parent_pid: int, watch: bool, name: str) -> None:
    """Every child's entry: group signals ignored, named, the parent watched, then the
    target's modules imported and ``target(*args)`` run."""
    ignore_group_signals()
    set_process_name(name)
    if watch:
        watch_parent(parent_pid)
    target, args = call.load()
    target(*args)

"""What the tests start never outlives them: the processes a test process started (daemons,
the demo, Chromium, coturn, and their children) are killed with their process groups when
pytest ends, however it ends: normally, on Ctrl-C (after the fixtures' own clean-up), on
SIGTERM or SIGHUP (a CI runner's or ``timeout``'s stop, a closed terminal), and at
interpreter exit. Fixtures still stop their own processes first, cleanly; this is the net
under them (tests/conftest.py installs it)."""

from __future__ import annotations

import atexit
import contextlib
import os
import signal
from pathlib import Path

import pytest


def descendants(pid: int) -> set[int]:
    """Every live descendant of ``pid`` (from /proc)."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(d.name))
    out: set[int] = set()
    todo = [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            if c not in out:
                out.add(c)
                todo.append(c)
    return out


def kill_descendants(pid: int | None = None) -> int:
    """SIGKILL every descendant of ``pid`` (this process) and the process groups they lead or
    belong to, except this process's own group; how many processes were found."""
    me = os.getpid() if pid is None else pid
    found = descendants(me)
    own_group = os.getpgid(me)
    groups = set()
    for p in found:
        with contextlib.suppress(OSError):
            groups.add(os.getpgid(p))
    for g in groups - {own_group}:
        with contextlib.suppress(OSError):
            os.killpg(g, signal.SIGKILL)
    for p in found:
        with contextlib.suppress(OSError):
            os.kill(p, signal.SIGKILL)
    return len(found)


def _on_stop_signal(signum: int, frame: object) -> None:
    kill_descendants()
    signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)  # end as the signal says (exit status 128 + signum)


_installed = False


def install() -> None:
    """Kill what this process started at exit and on SIGTERM/SIGHUP (main thread only)."""
    global _installed
    if _installed:
        return
    _installed = True
    atexit.register(kill_descendants)
    for sig in (signal.SIGTERM, signal.SIGHUP):
        with contextlib.suppress(ValueError):  # not the main thread
            if signal.getsignal(sig) in (signal.SIG_DFL, None):
                signal.signal(sig, _on_stop_signal)


def _sweeps(config: pytest.Config) -> bool:
    """This process starts the tests' processes: an xdist worker, or a run without xdist
    (the xdist controller's children are the workers, which sweep for themselves)."""
    return hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", None)


def pytest_configure(config: pytest.Config) -> None:
    if _sweeps(config):
        install()


def pytest_unconfigure(config: pytest.Config) -> None:
    if _sweeps(config):
        kill_descendants()

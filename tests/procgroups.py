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


def pid_alive(pid: int | None) -> bool:
    """Running (not a zombie) process ``pid``."""
    if not pid:
        return False
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in ("Z", "X")


def children(parent: int) -> dict[int, tuple[str, str]]:
    """Live (not zombie) children of ``parent``: pid -> (comm, command line)."""
    out = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            stat = Path(f"/proc/{d}/stat").read_text()
            comm = Path(f"/proc/{d}/comm").read_text().strip()
            cmd = Path(f"/proc/{d}/cmdline").read_text().replace("\0", " ")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == parent and pid_alive(int(d)):
            out[int(d)] = (comm, cmd)
    return out


def daemon_of(parent: int, role: str) -> int | None:
    """The running ``humantele <role>`` daemon that ``parent`` (a demo) started (None: none
    now)."""
    return next((p for p, (_, cmd) in children(parent).items() if f" {role} " in cmd), None)


def resource_tracker(pid: int) -> bool:
    """Whether ``pid`` is a multiprocessing resource tracker: it ends by itself once the
    process it serves is gone, after unlinking the shared memory that process left."""
    try:
        return b"multiprocessing.resource_tracker" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False


def kill_descendants(pid: int | None = None) -> int:
    """SIGKILL every descendant of ``pid`` (this process) and every member of the process
    groups they lead or belong to (except this process's own group), but the resource
    trackers (killed, they leave the killed processes' shared memory in /dev/shm); how many
    processes were found."""
    me = os.getpid() if pid is None else pid
    own_group = os.getpgid(me)
    first: set[int] | None = None
    for _ in range(3):  # again: one may have forked between the scan and its kill
        found = descendants(me)
        first = found if first is None else first
        groups = set()
        for p in found:
            with contextlib.suppress(OSError):
                groups.add(os.getpgid(p))
        groups.discard(own_group)
        members = set(found)
        for d in Path("/proc").iterdir():
            if d.name.isdigit():
                with contextlib.suppress(OSError):
                    if os.getpgid(int(d.name)) in groups:
                        members.add(int(d.name))
        victims = {p for p in members - {me} if not resource_tracker(p)}
        if not victims:
            break
        for p in victims:
            with contextlib.suppress(OSError):
                os.kill(p, signal.SIGKILL)
    return len(first or ())


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

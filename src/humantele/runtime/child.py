"""The one way a daemon runs work in a child process: spawn, parent watch, priority, stop,
restart with back-off.

The daemons' children (the expert's servo, the follower's sensing and video processes, the
OpenIGTLink sim ultrasound) are ``multiprocessing`` *spawn* children that share these rules:

- :func:`spawn` starts ``target(*args)`` through :func:`_child_main`, which first makes the
  child ignore SIGINT and SIGTERM (a terminal's Ctrl-C and systemd's stop reach the whole
  process group; the daemon stops its children itself, in order) and, unless the child
  watches by itself, starts a thread that ends the child when the daemon is gone
  (:func:`watch_parent`): a child never outlives its daemon.
- :func:`set_priority` is the child's scheduling, by what matters (:data:`PRIORITY`): the
  servo at SCHED_FIFO, the rest at SCHED_OTHER with a nice value; a real-time policy the
  daemon's thread had is never inherited (spawn execs a fresh interpreter, and the daemon's
  loop thread runs with ``SCHED_RESET_ON_FORK``); :func:`set_thread_nice` lowers one thread.
- :func:`stop_process` ends a child: ask (the caller's way: a flag, a message), wait, SIGTERM,
  wait, SIGKILL, reap.
- :class:`Restarter` notices a dead child on the owner's tick and starts its replacement after
  a back-off (first, then doubled, capped), in a task, so the daemon's loop never waits for a
  spawn; one restart at a time; after :meth:`Restarter.close` never again.

Shared memory is created and unlinked by the daemon's side only (a restarted child attaches
to the same blocks by name): the owner unlinks it in its ``close()``, whatever happened.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import logging
import multiprocessing as mp
import os
import signal
import threading
import weakref
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from multiprocessing import resource_tracker
from typing import Any

from humantele.runtime.child_entry import (
    GROUP_SIGNALS,
    Pickled,
    child_main,
    ignore_group_signals,
    set_process_name,
    watch_parent,
)

__all__ = ["Priority", "Restarter", "ignore_group_signals", "set_process_name", "spawn",
           "stop_process", "watch_parent"]  # fmt: skip

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Priority:
    """One child's (or thread's) scheduling: ``fifo`` > 0 asks SCHED_FIFO at that priority,
    else (or where the system refuses it) SCHED_OTHER at ``nice`` (added to the daemon's,
    0-19; higher gives way)."""

    fifo: int = 0
    nice: int = 0


# What matters first, in every mechanism (issue 19 §2): servo > pose stream (the daemons'
# event loops) > tracker and force (the follower's sensing process) > US video > POV video.
# The configurations' defaults come from here; docs/video.md explains the order.
PRIORITY: dict[str, Priority] = {
    "servo": Priority(fifo=80),  # [servo] realtime_priority
    "loop": Priority(fifo=10),  # [*.link] realtime_priority (the pose stream)
    # the tracker, then the force: [follower] sensing_realtime_priority, below the loops and
    # above any normal process (a browser, a build); sensing_nice where FIFO is refused
    "sensing": Priority(fifo=5, nice=2),
    "video_us": Priority(nice=5),  # [follower.video] process_nice: the video process
    "video_pov": Priority(nice=8),  # its POV thread: process_nice + POV_EXTRA_NICE
    "igtl_render": Priority(nice=10),  # the OpenIGTLink sim ultrasound (no video track)
}
POV_EXTRA_NICE = PRIORITY["video_pov"].nice - PRIORITY["video_us"].nice


def set_priority(priority: Priority) -> str:
    """This process's scheduling (call it in the child): ``"fifo N"``, ``"nice N"``, or with
    ``"fifo N refused: ...; nice M"`` when the system said no (no privilege: the child runs at
    the normal policy and its nice, which the daemon logs)."""
    refused = ""
    if priority.fifo > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority.fifo))
        except (OSError, AttributeError) as exc:
            refused = f"fifo {priority.fifo} refused: {exc}; "
        else:
            return f"fifo {priority.fifo}"
    with contextlib.suppress(OSError, AttributeError):  # a batch job: never a real-time policy
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    if priority.nice:
        try:
            os.nice(priority.nice)
        except OSError as exc:
            return f"{refused}nice {priority.nice} refused: {exc}"
    return f"{refused}nice {priority.nice}"


def set_thread_nice(extra: int) -> None:
    """Lower the calling thread alone by ``extra`` nice steps (Linux: nice is per thread)."""
    if extra <= 0:
        return
    with contextlib.suppress(OSError, AttributeError):
        tid = threading.get_native_id()
        now = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, min(19, now + extra))


class _Deferred:
    """``(target, args)`` pickled as the child is spawned (its pipes go with it, as
    multiprocessing passes them) and unpickled in the child only once it ignores the group's
    signals: unpickling imports the target's modules (seconds on a loaded machine: aiortc,
    cv2, pydantic), and a Ctrl-C then killed a restarted child with a KeyboardInterrupt
    traceback before it could ignore it. What remains open is the interpreter's own start
    and the import of :mod:`~humantele.runtime.child_entry` (nothing new)."""

    def __init__(self, target: Callable[..., Any], args: tuple) -> None:
        self.call = (target, args)

    def __reduce__(self) -> tuple:
        from multiprocessing.reduction import ForkingPickler

        return (Pickled, (bytes(ForkingPickler.dumps(self.call)),))


_SPAWNED: weakref.WeakSet[mp.process.BaseProcess] = weakref.WeakSet()  # by this process


def _kill_leftover_children() -> None:
    """At exit, a child its owner did not stop (an error path that left before its close):
    killed. It ignores SIGTERM, so multiprocessing's own exit handler, which terminates a
    daemonic child and then joins it, would wait for it forever (a follower whose feed port
    was taken hung on its sensing child). Registered after multiprocessing's: runs first."""
    for proc in list(_SPAWNED):
        with contextlib.suppress(Exception):
            if proc.is_alive():
                log.info("%s still running at exit: killed", proc.name)
                proc.kill()
                proc.join(5.0)


atexit.register(_kill_leftover_children)


def spawn(
    target: Callable[..., Any], args: tuple = (), *, name: str, watch: bool = True
) -> mp.process.BaseProcess:
    """Start ``target(*args)`` in a spawn child named ``name`` (also its process name, as
    ``ps`` shows it: ``humantele-servo``, ``humantele-video``, ``humantele-sensi(ng)``; see
    the module docstring); ``watch=False`` for a child that checks its parent itself (the
    servo, in its loop)."""
    ctx = mp.get_context("spawn")
    proc = ctx.Process(
        target=child_main,
        args=(_Deferred(target, args), os.getpid(), watch, name),
        name=name,
        daemon=True,
    )
    # The child is born with the group's signals blocked (a thread's signal mask is kept
    # across fork and exec): a terminal's Ctrl-C during the interpreter's own start-up, before
    # any of our code runs, would kill it (the servo restarted as Ctrl-C came: "Fatal Python
    # error: init_import_site", KeyboardInterrupt). child_main ignores them, then unblocks.
    # The resource tracker first: starting it (in the first ``start()`` of a process, or
    # after it died) *unblocks* SIGINT and SIGTERM once it is up (multiprocessing's
    # resource_tracker.ensure_running), which left the first child of a daemon unprotected.
    resource_tracker.ensure_running()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, GROUP_SIGNALS)
    try:
        proc.start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
    _SPAWNED.add(proc)
    return proc


def stop_process(
    proc: mp.process.BaseProcess | None,
    ask: Callable[[], None] | None = None,
    timeout_s: float = 3.0,
    term: bool = True,
) -> int | None:
    """End ``proc``: ``ask()`` (the child's own way to stop), wait ``timeout_s``, SIGTERM
    (``term``: for a child that handles it; the others ignore it), wait, SIGKILL; reaped;
    its exit code (None without a process)."""
    if proc is None:
        return None
    if ask is not None and proc.is_alive():
        with contextlib.suppress(Exception):
            ask()
    proc.join(timeout_s)
    if term and proc.is_alive():
        proc.terminate()
        proc.join(timeout_s)
    if proc.is_alive():
        proc.kill()
        proc.join()
    return proc.exitcode


def child_priority(pid: int | None) -> tuple[str, int] | None:
    """A running process's scheduling as the system has it: (policy name, nice), or None."""
    if not pid:
        return None
    try:
        policy = os.sched_getscheduler(pid)
        nice = os.getpriority(os.PRIO_PROCESS, pid)
    except (OSError, AttributeError):
        return None
    names = {os.SCHED_OTHER: "other", os.SCHED_FIFO: "fifo", os.SCHED_RR: "rr"}
    return names.get(policy, str(policy)), nice


class Restarter:
    """Restart a dead child after a back-off, off the event loop (see the module docstring).

    ``start_new()``: starts the replacement (an awaitable; raise to say it could not: the
    reason is kept and the next try waits longer). ``check(now, alive, exitcode)`` on each
    tick. ``first_s`` is the first wait, doubled per failed or repeated death up to ``max_s``;
    a child that stayed up ``stable_s`` resets it. ``max_restarts`` (None: no limit): then
    :attr:`gave_up`.
    """

    def __init__(
        self,
        name: str,
        start_new: Callable[[], Awaitable[None]],
        first_s: float = 1.0,
        max_s: float = 30.0,
        max_restarts: int | None = None,
        stable_s: float = 30.0,
    ) -> None:
        self.name = name
        self.start_new = start_new
        self.first_s = first_s
        self.max_s = max_s
        self.max_restarts = max_restarts
        self.stable_s = stable_s
        self.restarts = 0  # replacements started successfully
        self.attempts = 0  # tries since the last stable run (the back-off's exponent)
        self.down = ""  # why the child is not running ("" while it runs)
        self.exit_codes: list[int | None] = []
        self.due_at: float | None = None  # the next try (s, the caller's clock)
        self.up_since: float | None = None
        self.closed = False
        self.gave_up = False
        self.failed_start = False  # the last replacement could not start (not just: died)
        self.task: asyncio.Future | None = None

    @property
    def restarting(self) -> bool:
        return self.task is not None and not self.task.done()

    def delay(self) -> float:
        return min(self.max_s, self.first_s * 2.0**self.attempts)

    def check(self, now: float, alive: bool, exitcode: int | None = None) -> None:
        """Notice a death (logged once), start the replacement when due (one at a time)."""
        if self.closed or self.restarting:
            return
        if alive:
            if self.up_since is None:
                self.up_since = now
            elif now - self.up_since >= self.stable_s:
                self.attempts = 0
            self.down, self.due_at = "", None
            return
        self.up_since = None
        if self.gave_up:
            return
        if self.due_at is None:
            if not self.down:
                self.down = f"{self.name} process exited with code {exitcode}"
                self.exit_codes.append(exitcode)
            if self.max_restarts is not None and self.attempts >= self.max_restarts:
                self.gave_up = True
                log.error("%s; not restarted again (%d tries)", self.down, self.attempts)
                return
            self.due_at = now + self.delay()
            log.error("%s; restarting it in %g s", self.down, self.delay())
            return
        if now >= self.due_at:
            self.task = asyncio.ensure_future(self._start())

    async def _start(self) -> None:
        self.attempts += 1
        try:
            await self.start_new()
        except Exception as exc:  # noqa: BLE001 - kept as the reason, tried again later
            self.failed_start = True
            self.down = str(exc) or f"{self.name} did not restart ({type(exc).__name__})"
            self.due_at = None
            log.error("%s", self.down)
            return
        if self.closed:
            return
        self.restarts += 1
        self.failed_start = False
        self.down, self.due_at, self.up_since = "", None, None
        log.warning("%s process restarted (%d)", self.name, self.restarts)

    def state(self, now: float, alive: bool) -> str:
        """``running``, ``restarting (N)``, ``down: <why>, restart in S s``, ``failed: <why>``
        or ``stopped`` (closed)."""
        if self.closed:
            return "stopped"
        if self.restarting:
            return f"restarting ({self.restarts + 1})"
        if alive:
            return "running"
        if self.gave_up:
            return f"failed: {self.down}"
        if self.due_at is not None:
            return f"down: {self.down}, restart in {max(0.0, self.due_at - now):.0f} s"
        return f"down: {self.down or 'not running'}"

    async def close(self) -> None:
        """No more restarts; a restart in flight finishes first (its owner stops what it
        started: it sees :attr:`closed`)."""
        self.closed = True
        task = self.task
        if task is not None:
            with contextlib.suppress(BaseException):
                await task

    def stats(self) -> dict[str, Any]:
        return {"restarts": self.restarts, "down": self.down, "exit_codes": self.exit_codes[-8:]}

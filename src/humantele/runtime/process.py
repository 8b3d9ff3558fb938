"""A daemon process's life: stop signals and the demo that started it."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Callable
from typing import Any

PARENT_PID_ENV = "HUMANTELE_PARENT_PID"  # set by the demo for the daemons it starts


def on_stop_signals(loop: Any, callback: Callable[[], None]) -> None:
    """Call ``callback`` on SIGINT or SIGTERM (asyncio loop)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, callback)


def ignore_stop_signals() -> None:
    """After the asyncio loop closed (its handlers are gone): a late SIGINT/SIGTERM (a
    terminal's Ctrl-C reaching the process group, a supervisor's SIGTERM) must not turn a
    clean stop into a KeyboardInterrupt or a death by signal while the process exits."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)


def parent_gone() -> bool:
    """True when this process was started by a demo (``HUMANTELE_PARENT_PID``) that is gone."""
    want = os.environ.get(PARENT_PID_ENV)
    return bool(want) and str(os.getppid()) != want


def realtime_loop_thread(priority: int) -> str:
    """Run the calling thread (a daemon's event loop, which carries the pose stream) at
    SCHED_FIFO ``priority``; threads and processes it starts later get the normal policy back
    (SCHED_RESET_ON_FORK: aiortc's encoder and decoder threads, the video and sensing
    processes, the servo, which asks for its own higher priority).

    Why: on 2 cores shared with the 1 kHz servo, the video process and the sensing process, a
    pose arriving while both cores run other work waited for a time slice; that wait was the
    pose age's tail under load (docs/benchmarks.md). Returns ``"fifo <priority>"``, ``"off"``
    (priority 0) or ``"refused: <reason>"`` (no privilege: the daemon runs at normal priority;
    systemd's ``LimitRTPRIO`` grants it without root, see examples/systemd/).
    """
    if priority <= 0:
        return "off"
    try:
        policy = os.SCHED_FIFO | os.SCHED_RESET_ON_FORK
        os.sched_setscheduler(0, policy, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        return f"refused: {exc}"
    return f"fifo {priority}"


def thread_priority_for(loop_priority: int) -> int:
    """The SCHED_FIFO priority of a daemon's other threads: 1, the lowest real-time one
    (below the sensing process and the loop), when the loop runs real-time above it; else
    0 (they stay at the normal policy)."""
    return 1 if loop_priority > 1 else 0


def lift_threads(priority: int) -> int:
    """Run this process's other threads at SCHED_FIFO ``priority`` (called now and then: the
    threads aiortc and the daemon start later are found at the next call); returns how many
    were lifted now. Only threads at the normal policy and the process's own nice: one lowered
    on purpose (``runtime.child.set_thread_nice``) stays where it is.

    Why: a daemon's threads (aiortc's VP8 encoders and decoders, the executor's) share the
    interpreter lock with the loop that carries the pose stream. At the normal policy a
    browser or a build preempted a thread while it held the lock, and the real-time loop then
    waited for it to be scheduled again: priority inversion through the GIL. The follower's
    pose age p99 with one core busy and the console open was 2.7-4.0 ms; with its threads at
    FIFO 1, 1.1-1.5 ms (docs/benchmarks.md, "console_busy")."""
    if priority <= 0:
        return 0
    me, lifted = threading.get_native_id(), 0
    with contextlib.suppress(OSError):
        base = os.getpriority(os.PRIO_PROCESS, 0)
        for name in os.listdir("/proc/self/task"):
            tid = int(name)
            if tid in (me, os.getpid()):
                continue
            try:
                if os.sched_getscheduler(tid) != os.SCHED_OTHER:
                    continue
                if os.getpriority(os.PRIO_PROCESS, tid) != base:
                    continue
                policy = os.SCHED_FIFO | os.SCHED_RESET_ON_FORK
                os.sched_setscheduler(tid, policy, os.sched_param(priority))
            except OSError:  # gone meanwhile, or refused (no privilege: stays normal)
                continue
            lifted += 1
    return lifted


class ThreadLifter:
    """:func:`lift_threads` every ``every_s`` on its own thread (``humantele-lift``), not on
    the event loop (a scan of ``/proc/self/task`` and a few system calls a thread, which the
    loop carrying the pose stream need not wait for). ``lifted`` counts the threads lifted so
    far. The lifter itself stays at the normal policy. ``priority`` 0: nothing is started."""

    def __init__(self, priority: int, every_s: float = 0.5) -> None:
        self.priority = priority
        self.every_s = every_s
        self.lifted = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Start lifting (once; no-op at priority 0)."""
        if self.priority <= 0 or self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="humantele-lift", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            self.lifted += lift_threads(self.priority)
            if self._stop.wait(self.every_s):
                return

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

"""The follower's sensing (tracker frames, the tracking pipeline, the force sensor) in its own
process, so its Python time never holds the daemon's GIL.

Why: on the follower's thread pool, each tracker frame (~5 ms of Python and small NumPy
calls, 45 Hz) held the GIL the event loop needs to read the expert's poses. With the CPU
shared (2 cores, the servo spinning, other processes), the sensing thread is often descheduled
*while holding the GIL*, and the loop waits for it: ``humantele bench sensing`` measures the
loop's wake-up latency with sensing beside it in a thread and in a process.

:class:`SensingProcess` is the daemon's handle: a ``spawn`` child that builds the daemon's own
:class:`~humantele.follower.sensing.Sensing` and answers one request at a time over a pipe:
``(job, (t, world))`` in (``world``: what the sim clinic's devices observe; None with
real devices), ``(job, Measurement, seconds)`` out. The daemon's loop reads the
answers with ``add_reader`` (never blocks on the child). One frame at most is in flight: the
caller skips frames while :attr:`busy`, as it did with the thread. A child that dies is
restarted by a :class:`~humantele.runtime.child.Restarter`, as the video and servo processes
are: after ``RESTART_FIRST_S``, doubled per death up to ``RESTART_MAX_S``, reset by a child
that stayed up 30 s; after ``max_restarts`` deaths in a row, :attr:`failed` and the caller
falls back to its thread. (The pipe's end says at once that the child died, so the restart
is timed on the loop, not found on a tick.) A child that cannot build its sensing (a bad
config) reports why and is not restarted. The child is started by
:func:`humantele.runtime.child.spawn` (SIGINT and SIGTERM ignored: the daemon stops it; it
ends when the daemon is gone, and when the pipe closes). Once started it runs at
SCHED_FIFO 5 (``sensing_realtime_priority``, :data:`~humantele.runtime.child.PRIORITY`):
below the servo (80) and the daemons' loops (10), which preempt it, and above every normal
process: the video process (nice 5, its POV thread 8), and a browser or a build on the same
machine, so when CPU is short the video and the rest give way before the tracker (issue 19
§2). Where the system refuses a real-time policy it runs at ``sensing_nice`` (+2).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing as mp
import os
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from humantele.runtime.child import (
    PRIORITY,
    Priority,
    Restarter,
    set_priority,
    spawn,
    stop_process,
)
from humantele.runtime.stats import process_cpu_percent

log = logging.getLogger(__name__)

RESTART_FIRST_S = 0.5  # a dead sensing process's replacement starts this soon (s): the
# tracker's pose is stale until it measures (the video's is 1 s, the servo's 2 s)
RESTART_MAX_S = 8.0  # the back-off's cap (s): 0.5, 1, 2, 4, 8 for the five tries
HUNG_S = 10.0  # a frame in the child this long without an answer: the child is hung, killed
# and restarted (every device read is bounded, by about a second: hl2ss read_timeout_s)

STATS_PERIOD_S = 0.25  # the child sends its devices' counters this often (s)

OnResult = Callable[[int, Any, float], None]  # (job, Measurement, seconds measuring)


def sensing_main(
    config: Any, sensing_config: Any, conn: Connection, priority: Priority = PRIORITY["sensing"]
) -> None:
    """The child: build the sensing, then measure each request until the pipe closes."""
    try:
        from humantele.follower.sensing import Sensing

        sensing = Sensing(config, sensing_config)
    except Exception as exc:  # a config the sensing refuses: say why, once
        with contextlib.suppress(OSError):
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    serve(sensing, conn, priority)


def serve(sensing: Any, conn: Connection, priority: Priority = PRIORITY["sensing"]) -> None:
    """The child's loop on a built :class:`~humantele.follower.sensing.Sensing`: its
    priority, then each request measured and answered until the pipe closes; closed after."""
    # After starting at the daemon's priority: a niced start can starve for long.
    got = set_priority(priority)
    # OpenCV's worker threads, started while the sensing was built (before the priority),
    # run at the normal policy: a frame's filter split over them waited on a worker that a
    # normal process (a browser, a build) had preempted. One thread: the whole frame runs at
    # this process's priority.
    import cv2

    cv2.setNumThreads(1)
    if "refused" in got:
        log.warning("sensing: %s", got)
    try:
        from humantele.follower.clinic import simulator_modules

        conn.send(("ready", os.getpid(), simulator_modules()))
        stats_due = 0.0
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                break
            if msg is None:
                break
            job, (t, world) = msg
            t0 = time.perf_counter()
            m = sensing.measure(t, world)  # catches the pipeline's own faults
            seconds = time.perf_counter() - t0
            stats = None  # the devices' counters, a few times a second
            if time.monotonic() >= stats_due:
                stats, stats_due = sensing.device_stats(), time.monotonic() + STATS_PERIOD_S
            conn.send(("result", job, m, seconds, sensing.errors, stats))
    except (BrokenPipeError, OSError):
        pass
    finally:
        sensing.close()


class SensingProcess:
    """The daemon's handle on the sensing child. ``start(loop)`` spawns it (non-blocking);
    ``submit(job, truth)`` sends one frame (False when busy, not running or failed);
    results arrive through ``on_result`` on the loop; ``on_error(reason)`` once if the child
    cannot build its sensing. ``close()`` stops it."""

    def __init__(
        self,
        config: Any,
        sensing_config: Any,
        on_result: OnResult,
        on_error: Callable[[str], None] | None = None,
        max_restarts: int = 5,
        priority: Priority = PRIORITY["sensing"],
        hung_s: float = HUNG_S,
        target: Callable[..., None] | None = None,
    ) -> None:
        """``target``: the child's main (default :func:`sensing_main`; tests give others)."""
        self.config = config
        self.hung_s = hung_s
        self.target = target or sensing_main
        self.hangs = 0  # children killed for not answering within hung_s
        self._sent_at: float | None = None
        self.sensing_config = sensing_config
        self.on_result = on_result
        self.on_error = on_error
        self.priority = priority
        self.restarter = Restarter("sensing", self._restart, RESTART_FIRST_S, RESTART_MAX_S,
                                   max_restarts=max_restarts)  # fmt: skip
        self._restart_at: asyncio.TimerHandle | None = None
        self._closed = False
        self.child_errors = 0  # sensing faults the child counted (all children so far)
        self._errors_before = 0
        self.ready = False
        self.busy = False
        self.failed = False
        self.error: str | None = None
        self.pid: int | None = None
        self.simulator_modules: list[str] | None = None  # loaded in the child (once ready)
        self.device_stats: dict | None = None  # the child's devices' counters (latest)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._proc: mp.process.BaseProcess | None = None
        self._conn: Connection | None = None

    @property
    def running(self) -> bool:
        """A child is running or being replaced (not failed, not closed)."""
        replacing = bool(self.restarter.down)  # from its death to its replacement's start
        return not self.failed and not self._closed and (self._proc is not None or replacing)

    @property
    def restarts(self) -> int:
        """Replacements started so far."""
        return self.restarter.restarts

    def start(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        self._loop = loop or asyncio.get_running_loop()
        self._spawn()

    async def wait_ready(
        self, timeout_s: float = 120.0, cancel: Callable[[], bool] | None = None
    ) -> bool:
        """Wait until the child has built its sensing (True) or failed, timed out or
        ``cancel()`` said so (False)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while not self.ready and not self.failed and loop.time() < deadline:
            if cancel is not None and cancel():
                break
            await asyncio.sleep(0.02)
        return self.ready

    def _spawn(self) -> None:
        parent, child = mp.get_context("spawn").Pipe(duplex=True)
        from humantele.follower.sensing import SensingSetup  # (the daemon has it loaded)

        # not the whole config: see SensingSetup (None: a test's own target)
        setup = None if self.config is None else SensingSetup.of(self.config)
        self._proc = spawn(self.target, (setup, self.sensing_config, child, self.priority),
                           name="humantele-sensing")  # fmt: skip
        child.close()
        self._errors_before = self.child_errors
        self._conn = parent
        self.ready = self.busy = False
        assert self._loop is not None
        self._loop.add_reader(parent.fileno(), self._readable)

    def cpu_percent(self) -> float | None:
        """The running child's CPU use since it started, % of one core (Linux; else None)."""
        if self._proc is None or self.pid is None:
            return None
        return process_cpu_percent(self.pid)

    def submit(self, job: int, frame: Any) -> bool:
        """Send one frame to measure; False (nothing sent) if one is in flight or no child."""
        if self.busy:
            self.check_hung()
        if self.busy or not self.running or self._conn is None:
            return False
        try:
            self._conn.send((job, frame))
        except (BrokenPipeError, OSError):
            self._died()
            return False
        self.busy = True
        self._sent_at = self._now()
        return True

    def _now(self) -> float:
        return self._loop.time() if self._loop is not None else time.monotonic()

    def check_hung(self) -> bool:
        """A frame in the child for ``hung_s`` without an answer (a device read that does not
        return, a deadlock): the child is killed and, as after any death, restarted by the
        :class:`Restarter`. True if it was."""
        if not self.busy or self._sent_at is None or self._proc is None:
            return False
        waited = self._now() - self._sent_at
        if waited < self.hung_s:
            return False
        self.hangs += 1
        self.restarter.down = f"sensing process hung (no answer in {waited:.1f} s)"
        log.error("follower: the sensing process gave no answer in %.1f s: hung; killed and "
                  "restarted", waited)  # fmt: skip
        with contextlib.suppress(Exception):
            self._proc.kill()
        self._died()
        return True

    def _readable(self) -> None:
        conn = self._conn
        if conn is None:
            return
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            self._died()
            return
        kind = msg[0]
        if kind == "result":
            self.busy = False
            self.restarter.check(self._loop.time(), True)  # up: a long run resets the back-off
            self.child_errors = self._errors_before + msg[4]
            if msg[5] is not None:
                self.device_stats = msg[5]
            self.on_result(msg[1], msg[2], msg[3])
        elif kind == "ready":
            self.ready, self.pid, self.simulator_modules = True, msg[1], msg[2]
        elif kind == "error":
            self.failed, self.error = True, msg[1]
            self._drop_child()
            log.error("follower: the sensing process cannot start: %s", msg[1])
            if self.on_error is not None:
                self.on_error(msg[1])

    def _died(self) -> None:
        proc = self._proc
        self._drop_child()  # reaped: its exit code is known
        code = proc.exitcode if proc is not None else None
        self._schedule(code)

    def _schedule(self, code: int | None = None) -> None:
        """After a death (its exit ``code``) or a replacement that could not start: the
        :class:`Restarter` logs it and sets the next try, timed on the loop; or it gives up."""
        loop = self._loop
        assert loop is not None
        self.restarter.check(loop.time(), False, code)
        if self.restarter.gave_up:
            self.failed = True
            log.error("follower: the sensing process keeps exiting; measuring in a thread")
        elif self.restarter.due_at is not None:
            self._restart_at = loop.call_at(self.restarter.due_at, self._restart_due)

    def _restart_due(self) -> None:
        self._restart_at = None
        if self._loop is None or self._closed:
            return
        # due: starts the replacement (asyncio may run a timer up to its clock's resolution
        # early, which the Restarter would take for "not yet", and nothing would call again)
        due = self.restarter.due_at
        now = self._loop.time() if due is None else max(self._loop.time(), due)
        self.restarter.check(now, False)
        if self.restarter.task is not None:
            self.restarter.task.add_done_callback(self._restart_done)

    def _restart_done(self, _task: asyncio.Future) -> None:
        if not self._closed and not self.failed and self._proc is None:  # it could not start
            self._schedule()

    async def _restart(self) -> None:
        """The :class:`Restarter`'s ``start_new``: spawn the replacement (it says when ready)."""
        if not self._closed:
            self._spawn()

    def _drop_child(self) -> None:
        """Forget the child: stop reading its pipe, close it, reap the process."""
        conn, proc = self._conn, self._proc
        self._conn, self._proc = None, None
        self.busy = self.ready = False
        if conn is not None:
            if self._loop is not None and not self._loop.is_closed():
                with contextlib.suppress(Exception):
                    self._loop.remove_reader(conn.fileno())
            conn.close()
        stop_process(proc, timeout_s=1.0, term=False)

    def close(self, timeout_s: float = 3.0) -> None:
        """Ask the child to stop (the frame being measured ends first), then reap it; no
        replacement after this."""
        self._closed = self.restarter.closed = True
        if self._restart_at is not None:
            self._restart_at.cancel()
            self._restart_at = None
        conn, proc = self._conn, self._proc
        self._conn, self._proc = None, None
        if conn is not None:
            if self._loop is not None and not self._loop.is_closed():
                with contextlib.suppress(Exception):
                    self._loop.remove_reader(conn.fileno())
            with contextlib.suppress(OSError):
                conn.send(None)
            conn.close()
        stop_process(proc, timeout_s=timeout_s, term=False)
        self.busy = self.ready = False

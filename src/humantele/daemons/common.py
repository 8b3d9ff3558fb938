"""What the expert and follower daemons share: set-up, the recording's open and close, the
main loop's ticks, the teardown of :meth:`run`, and the command line common to both."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import math
import os
import sys
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

from humantele.cliargs import EXIT_FAILED, EXIT_OK, EXIT_REFUSED, duration_s, log_level
from humantele.daemons.session import (
    ClockSyncLog,
    add_session_arguments,
    close_daemon_recording,
    open_daemon_recording,
    recorder_stats,
    session_overrides,
)
from humantele.recording import Recorder
from humantele.runtime.pacing import daemon_ticks
from humantele.runtime.process import (
    ThreadLifter,
    ignore_stop_signals,
    on_stop_signals,
    realtime_loop_thread,
    thread_priority_for,
)
from humantele.runtime.stats import CpuMeter, StatsFile
from humantele.transport.link import link_refusal

log = logging.getLogger(__name__)


class Daemon:
    """The runtime of one daemon (``role`` 'expert' or 'follower'). ``config`` has the
    ``session`` (:class:`~humantele.daemons.session.SessionConfig`) and ``recording``
    sections; ``stats_file``: where :meth:`stats` is written every 0.5 s and at the end."""

    role = "daemon"

    def __init__(self, config: Any, stats_file: str | None = None) -> None:
        self.config = config
        self.stats_out = StatsFile(stats_file)
        self.cpu = CpuMeter()
        self.t_start = time.monotonic()
        self.clock: Callable[[], float] = time.monotonic  # the loop's clock (s); tests replace it
        self._stop = asyncio.Event()
        # Recording (opened by run(), or set by a caller).
        self.rec: Recorder | None = None
        self.clock_log = ClockSyncLog(f"/{self.role}/clock_sync")
        self._last_report = -math.inf
        self.loop_priority = "off"  # the event loop thread's scheduling (start_run sets it)
        self.thread_priority = 0  # SCHED_FIFO of the process's other threads (0: normal)
        self.lifter: ThreadLifter | None = None  # lifts the other threads (off the loop)
        self.link_ended_early: asyncio.Task | None = None  # the link's task, if it ended the run
        self.step_errors = 0  # steps run by guarded() that failed

    def stats(self) -> dict:
        raise NotImplementedError

    def common_stats(self, link: Any) -> dict[str, Any]:
        """The stats both daemons give: role, pid, uptime (s), the link's state and counters,
        CPU (% of one core), the event loop's scheduling and the recording."""
        return {
            "role": self.role,
            "pid": os.getpid(),
            "uptime_s": round(time.monotonic() - self.t_start, 3),
            "link_state": link.state,
            "connections": link.counters.connections,
            "dropped": dict(link.counters.dropped),
            "dropped_total": sum(link.counters.dropped.values()),
            "cpu_percent": self.cpu.overall(),
            "loop_priority": self.loop_priority,
            "thread_priority": f"fifo {self.thread_priority}" if self.thread_priority else "off",
            "threads_lifted": self.lifter.lifted if self.lifter is not None else 0,
            "recording": recorder_stats(self.rec),
        }

    def guarded(self, step: Callable[[float], object], t: float) -> None:
        """Run a step that must never end the daemon (scans, recording); failures counted."""
        try:
            step(t)
        except Exception:
            self.step_errors += 1
            if self.step_errors in (1, 10, 100, 1000):
                log.exception("%s: %s failed (%d so far)", self.role, step.__name__,
                              self.step_errors)  # fmt: skip

    def record_any(self, topic: str, t: float, payload: dict) -> None:
        """Record one sample (``t``: this daemon's clock, s) if recording; from any thread
        (the recorder only queues)."""
        rec = self.rec
        if rec is not None:
            rec.write(topic, t, payload)

    def write_stats(self) -> None:
        """Hand the current stats to the stats file's writer thread (every 0.5 s). The first
        call starts the lifter: every 0.5 s, on its own thread, the threads started since go
        to :attr:`thread_priority`."""
        if self.lifter is None:
            self.lifter = ThreadLifter(self.thread_priority)
            self.lifter.start()
        self.stats_out.write(self.stats())

    def stop(self) -> None:
        """End :meth:`run` at its next tick (as SIGINT or SIGTERM do)."""
        self._stop.set()

    def open_recording(self) -> bool:
        """Open the recording of ``[<role>.session]`` (if any); False, with a clear message on
        stderr, if it cannot be recorded to."""
        if self.rec is not None:
            return True
        ok, self.rec = open_daemon_recording(self.role, self.config.session, self.config.recording)
        return ok

    def close_recording(self) -> None:
        close_daemon_recording(self.role, self.rec)

    def start_run(self) -> bool:
        """The start of :meth:`run`: stop signals, then the recording (False: cannot record)."""
        on_stop_signals(asyncio.get_running_loop(), self._stop.set)
        return self.open_recording()

    def loop_ticks(
        self,
        rate_hz: float,
        duration_s: float | None,
        link_task: asyncio.Task,
        on_late: Callable[[], None] | None = None,
    ) -> AsyncIterator[float]:
        """The main loop's ticks (s, :attr:`clock`) until stopped, the link task ends, or
        ``duration_s`` has passed; the stats file is written every 0.5 s."""
        self.link_ended_early = None

        def running() -> bool:
            if self._stop.is_set():
                return False
            if link_task.done():  # nobody asked: the exit code says so (run_result)
                self.link_ended_early = link_task
                return False
            return True

        return daemon_ticks(
            rate_hz,
            duration_s,
            running=running,
            report=self.write_stats,
            clock=self.clock,
            on_late=on_late,
        )

    async def close_link(self, link: Any, link_task: asyncio.Task) -> None:
        """Say bye on the link and wait (at most 5 s) for its task to end."""
        await link.close(f"{self.role} stopping")
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await asyncio.wait_for(link_task, 5.0)

    def run_result(self, link_task: asyncio.Task) -> int:
        """The exit code of :meth:`run` after its teardown: ``EXIT_REFUSED`` (the reason on
        stderr) when the signaling server refused this daemon (wrong token, room full);
        ``EXIT_FAILED`` when the link's task ended before anyone asked the daemon to stop (it
        raised, or returned: the main loop ends with it); else 0 (stopped on request: a
        signal, :meth:`stop`, ``--duration``, or the demo that started it gone).

        Why: a supervisor reads 0 as "stopped on request" (systemd's ``Restart=on-failure``
        does not restart it). A daemon that was not asked to stop never exits 0: under load a
        link whose task raised (an error the retry loop did not expect) once ended the
        expert's main loop in the middle of a run, and it exited 0 (issue 20 §2)."""
        refused = link_refusal(link_task)
        if refused:
            print(f"humantele {self.role}: {refused}", file=sys.stderr)
            return EXIT_REFUSED
        if self.link_ended_early:
            why = link_end(self.link_ended_early)
            print(f"humantele {self.role}: the link ended unexpectedly ({why})", file=sys.stderr)
            return EXIT_FAILED
        return EXIT_OK

    def finish_run(self) -> None:
        """The end of :meth:`run`: the recording closed, the final stats written."""
        self.close_recording()
        if self.lifter is not None:
            self.lifter.stop()
        self.stats_out.close(self.stats())


def link_end(task: asyncio.Task) -> str:
    """How a link's task ended, in a few words (for the exit message)."""
    if task.cancelled():
        return "cancelled"
    exc = task.exception()
    return "returned" if exc is None else f"{type(exc).__name__}: {exc}"


def run_daemon_process(daemon: Daemon, duration_s: float | None) -> int:
    """A daemon's process: its thread becomes the event loop's, at ``[<role>.link]
    realtime_priority`` (:func:`~humantele.runtime.process.realtime_loop_thread`), and runs
    :meth:`Daemon.run` to its exit code. (Tests run daemons on their own loop, unchanged.)"""
    daemon.loop_priority = realtime_loop_thread(daemon.config.link.realtime_priority)
    if daemon.loop_priority.startswith("refused"):
        log.warning("%s: event loop at normal priority (SCHED_FIFO %s)", daemon.role,
                    daemon.loop_priority)  # fmt: skip
    elif daemon.loop_priority.startswith("fifo"):  # its threads just below it (GIL)
        daemon.thread_priority = thread_priority_for(daemon.config.link.realtime_priority)
    try:
        return asyncio.run(daemon.run(duration_s))
    finally:
        ignore_stop_signals()


# --- command line ---------------------------------------------------------------------------


def add_daemon_arguments(parser: argparse.ArgumentParser, config_help: str) -> None:
    """The options both daemons take (then each adds its own)."""
    parser.add_argument("--config", help=config_help)
    parser.add_argument("--signaling-url", help="signaling server, e.g. ws://127.0.0.1:8765/ws")
    parser.add_argument("--room", help="session room name")
    parser.add_argument("--duration", type=duration_s, help="stop after this many seconds")
    parser.add_argument("--stats-file", help="write running figures (JSON) to this file")
    parser.add_argument(
        "--log-level", type=log_level, default="WARNING", help="logging level (default WARNING)"
    )
    add_session_arguments(parser)


def daemon_overrides(args: argparse.Namespace, data: dict[str, Any]) -> None:
    """Put the common options (signaling, room, recording) into a daemon config's ``data``."""
    if args.signaling_url:
        data["link"]["signaling_url"] = args.signaling_url
    if args.room:
        data["link"]["room"] = args.room
    session_overrides(args, data)


def setup_logging(role: str, level: str) -> None:
    """A daemon's log lines, prefixed with its role; aioice's chatter at WARNING."""
    logging.basicConfig(
        level=getattr(logging, str(level).upper(), logging.WARNING),
        format=f"%(asctime)s {role} %(name)s: %(message)s",
    )
    logging.getLogger("aioice").setLevel(logging.WARNING)

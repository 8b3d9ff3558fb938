"""One daemon process under the demo's supervision: started, restarted when it dies unexpectedly
(at most ``max_restarts`` times, after 1, 2, 4 ... s), stopped at the end.

A daemon that exits with a code restarting cannot fix (2: configuration, 3: refused by the
signaling server; :mod:`humantele.cliargs`) is not restarted. Each run of the process writes a
fresh stats file: the dead one's file is kept as ``<role>.<n>.json`` so the running figures and
the summary never mix a dead process's last numbers with the new one's.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from humantele.cliargs import FATAL_EXIT_CODES
from humantele.runtime.signal_child import signal_child


@dataclass
class SupervisedDaemon:
    """``humantele <argv...>``, logging to ``log``; ``env`` for it. ``stats``: the stats
    file the argv names (``--stats-file``), set aside when the process dies."""

    role: str
    argv: list[str]
    stats: Path
    log: Path
    env: dict[str, str]
    max_restarts: int = 3
    backoff_s: float = 1.0  # first restart after this, then doubled
    proc: asyncio.subprocess.Process | None = None
    restarts: int = 0
    exit_codes: list[int] = field(default_factory=list)  # of the processes that died
    restart_at: float | None = None  # when the pending restart is due (monotonic s)
    started_t: float | None = None  # when the current process was started (monotonic s)
    up_t: float | None = None  # when it first wrote its stats (monotonic s)

    async def start(self) -> None:
        with open(self.log, "ab") as log_file:
            if self.restarts:
                log_file.write(f"\n--- restart {self.restarts} ---\n".encode())
                log_file.flush()
            self.proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "humantele", *self.argv,
                stdin=asyncio.subprocess.DEVNULL, stdout=log_file, stderr=log_file, env=self.env,
            )  # fmt: skip
        self.started_t = time.monotonic()
        self.up_t = None
        self.restart_at = None

    @property
    def returncode(self) -> int | None:
        return None if self.proc is None else self.proc.returncode

    async def check(self, now: float) -> str | None:
        """Notice a death and restart when due; the reason when it cannot (gave up or fatal)."""
        code = self.returncode
        if self.restart_at is None and code is not None:
            self.exit_codes.append(code)
            if code in FATAL_EXIT_CODES:
                return f"{self.role} exited with code {code}"
            if self.restarts >= self.max_restarts:
                return (
                    f"{self.role} exited with code {code} after {self.restarts} restart(s); "
                    "giving up"
                )
            self.restart_at = now + self.backoff_s * 2.0**self.restarts
            with contextlib.suppress(OSError):  # its figures end here; keep them for the logs
                os.replace(self.stats, self.stats.with_suffix(f".{len(self.exit_codes)}.json"))
        if self.restart_at is not None and now >= self.restart_at:
            self.restarts += 1
            await self.start()
        return None

    def saw_stats(self, now: float) -> None:
        """The current process wrote its stats: it is up (after a restart: it rejoined)."""
        if self.up_t is None:
            self.up_t = now

    def status(self, now: float) -> str:
        """`` | follower DIED (code -9), restarting in 2 s (2/3)`` while down, ``... restarted,
        starting`` until the new process is up, ``... rejoined`` for 10 s after, else ''."""
        if self.restart_at is not None:
            wait = max(0.0, self.restart_at - now)
            return (
                f" | {self.role} DIED (code {self.exit_codes[-1]}), restarting in {wait:.0f} s "
                f"({self.restarts + 1}/{self.max_restarts})"
            )
        if not self.restarts:
            return ""
        if self.up_t is None:
            return f" | {self.role} restarted ({self.restarts}), starting"
        if now - self.up_t < 10.0:
            return f" | {self.role} rejoined (restart {self.restarts})"
        return ""

    async def stop(self, timeout_s: float = 20.0) -> int | None:
        """SIGTERM (the daemon stops cleanly: recording closed, servo and video processes
        ended), SIGKILL after ``timeout_s`` (a loaded 2-core machine can need 10 s); its exit
        code."""
        self.restart_at = None
        proc = self.proc
        if proc is None:
            return None
        if proc.returncode is None:
            signal_child(proc, signal.SIGTERM)  # (not send_signal: it may take the exit code)
            try:
                await asyncio.wait_for(proc.wait(), timeout_s)
            except TimeoutError:
                signal_child(proc, signal.SIGKILL)
                await proc.wait()
        return proc.returncode

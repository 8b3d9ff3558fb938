"""``humantele study CONDITIONS.toml [--out DIR] [--jobs N|auto] [--charts DIR] [--table-only]``:
the study again, in simulation, one whole recorded session per condition and seed.

Each run (a condition with a seed) is a child process (:mod:`humantele.study.session`): both
daemons, the 1 kHz servo, video on, the link relayed through coturn with the user-space WAN
emulator on the expert's side. Its recordings go to ``OUT/RUN_ID/``; ``summary.json`` there
marks it done, so a second call skips it (resumable): a run whose file settings changed since
is refused (remove its directory or rename the condition), and an unfinished one (a crash,
Ctrl-C) is moved aside to ``RUN_ID.incomplete-<time>`` and run again. Then the table
(:mod:`humantele.study.table`: ``OUT/table.md``, ``OUT/study.json``) and the charts
(:mod:`humantele.study.charts`, into ``--charts`` or OUT).

Runs side by side (``--jobs auto``): as many as the cores free of other work hold, one core
each (``SESSION_CORES``: a session used 0.55 of a core on average here - expert, servo,
follower, its sensing and video processes, coturn, the emulator; more while it scans -
rounded up so the servo keeps its budget), at least 1:
``floor((cores - 1-minute load) / SESSION_CORES)``. On the 2-core project machine that is 1
unless it is idle. A finished run whose servo missed its budget (rate under
990 Hz, or over 0.1 % of ticks late) drops the study to one run at a time.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

from humantele.config import ConfigError
from humantele.runtime.signal_child import signal_child
from humantele.study.conditions import Run, StudyFile, load_conditions

SESSION_CORES = 1.0  # cores one run is given (see the module docstring)
SERVO_RATE_MIN_HZ = 990.0
SERVO_LATE_MAX = 0.001  # share of servo ticks allowed over their deadline
KILL_MARGIN_S = 120.0  # past the run's own time limit, the child is killed


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("conditions", type=Path, help="conditions file (configs/study-*.toml)")
    parser.add_argument("--out", type=Path, help="output directory (default runs/study-NAME)")
    parser.add_argument("--jobs", default="auto", help="runs side by side: N or auto")
    parser.add_argument("--charts", type=Path, help="write the charts here (default: --out)")
    parser.add_argument(
        "--table-only", action="store_true", help="run nothing: the table of what is recorded"
    )
    parser.add_argument("--json", action="store_true", help="print the table as JSON last")


def auto_jobs(cpus: int, load1: float, pending: int) -> int:
    """Runs side by side: the cores free of other work, one per run, at least 1."""
    free = int(max(0.0, cpus - load1) // SESSION_CORES)
    return max(1, min(pending, free))


def parse_jobs(text: str, pending: int) -> int:
    if text == "auto":
        return auto_jobs(os.cpu_count() or 1, os.getloadavg()[0], pending)
    try:
        n = int(text)
    except ValueError:
        raise ConfigError(f"--jobs: {text!r} is not a number of runs nor 'auto'") from None
    if not 1 <= n <= 64:
        raise ConfigError(f"--jobs: {n}: between 1 and 64")
    return n


def servo_ok(summary: dict) -> bool:
    """The run's servo kept its budget (see the module docstring)."""
    demo = summary.get("demo") or {}
    rate, late = demo.get("servo_rate_hz"), demo.get("servo_overruns") or 0
    if rate is None:
        return False
    ticks = rate * max(1.0, float(demo.get("duration_s") or 1.0))
    return rate >= SERVO_RATE_MIN_HZ and late <= SERVO_LATE_MAX * ticks


def _same_spec(a: dict, b: dict) -> bool:
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def plan(study: StudyFile, out: Path) -> tuple[list[Run], list[Run]]:
    """(runs already recorded, runs to do). A recorded run with other settings than the file
    now gives is refused; an unfinished one is moved aside (see the module docstring)."""
    done, todo = [], []
    for run in study.runs():
        d = out / run.run_id
        spec = run.spec(study.study)
        summary = d / "summary.json"
        if summary.exists():
            try:
                old = json.loads(summary.read_text(encoding="utf-8"))["spec"]
            except (OSError, ValueError, KeyError, TypeError):
                old = None
            if old is None or not _same_spec({**old, "setup_timeout_s": 0},
                                             {**spec, "setup_timeout_s": 0}):  # fmt: skip
                raise ConfigError(
                    f"{d}: recorded with other settings than {run.run_id} has now; remove the "
                    "directory to record it again, or give the condition another name"
                )
            done.append(run)
            continue
        if d.exists():
            aside = d.with_name(f"{d.name}.incomplete-{time.strftime('%Y%m%dT%H%M%S')}")
            d.rename(aside)
        todo.append(run)
    return done, todo


class Progress:
    """One status line: a bar, runs done/failed/skipped, what is running, elapsed, ETA."""

    def __init__(self, total: int, skipped: int, jobs: int, stream: Any = sys.stderr) -> None:
        self.total, self.skipped, self.jobs = total, skipped, jobs
        self.done = self.failed = 0
        self.running: dict[str, float] = {}
        self.walls: list[float] = []
        self.t0 = time.monotonic()
        self.stream = stream
        self.tty = stream.isatty()
        self._last = ""
        self._last_t = 0.0

    def line(self, now: float | None = None) -> str:
        now = time.monotonic() if now is None else now
        finished = self.skipped + self.done + self.failed
        width = 24
        fill = int(width * finished / self.total) if self.total else width
        bar = "#" * fill + "-" * (width - fill)
        left = self.total - finished
        eta = "-"
        if self.walls and left:
            per = sum(self.walls) / len(self.walls)
            running_left = sum(max(0.0, per - (now - t)) for t in self.running.values())
            queued = left - len(self.running)
            eta = _clock(running_left / max(1, len(self.running)) + queued * per / self.jobs)
        running = ", ".join(f"{k} {now - t:.0f} s" for k, t in self.running.items()) or "-"
        return (
            f"[{bar}] {finished}/{self.total} runs ({self.skipped} recorded before, "
            f"{self.failed} failed) | running: {running} | {_clock(now - self.t0)} elapsed, "
            f"ETA {eta}"
        )

    def show(self, force: bool = False) -> None:
        text = self.line()
        if self.tty:
            print("\r" + text + "\x1b[K", end="", file=self.stream, flush=True)
        else:  # a log: a line when a run starts or ends, else every 30 s
            key = text.split(" | ")[0] + "|" + ",".join(self.running)
            now = time.monotonic()
            if force or key != self._last or now - self._last_t >= 30.0:
                print(text, file=self.stream, flush=True)
                self._last, self._last_t = key, now

    def note(self, text: str) -> None:
        if self.tty:
            print("\r\x1b[K", end="", file=self.stream)
        print(text, file=self.stream, flush=True)


def _clock(s: float) -> str:
    s = int(s)
    return f"{s // 60}:{s % 60:02d}"


async def _run_child(run: Run, study: StudyFile, out: Path) -> tuple[bool, str, dict | None]:
    """Run one session in a child process; (ok, why not, summary)."""
    d = out / run.run_id
    d.mkdir(parents=True)
    spec = {**run.spec(study.study), "setup_timeout_s": study.study.setup_timeout_s}
    (d / "run.json").write_text(json.dumps(spec, indent=1), encoding="utf-8")
    s = study.study
    limit = s.setup_timeout_s + s.scans * (s.scan_s + s.gap_s) + KILL_MARGIN_S
    with open(d / "session.log", "wb") as log:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "humantele.study.session", str(d),
            stdin=asyncio.subprocess.DEVNULL, stdout=log, stderr=log,
        )  # fmt: skip
        try:
            await asyncio.wait_for(proc.wait(), limit)
        except TimeoutError:
            signal_child(proc, signal.SIGKILL)
            await proc.wait()
            return False, f"killed after {limit:.0f} s", None
        except asyncio.CancelledError:  # the study was stopped: let the child stop cleanly
            signal_child(proc, signal.SIGTERM)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(proc.wait(), 30)
            if proc.returncode is None:
                signal_child(proc, signal.SIGKILL)
                await proc.wait()
            raise
    summary_path = d / "summary.json"
    if proc.returncode == 0 and summary_path.exists():
        return True, "", json.loads(summary_path.read_text(encoding="utf-8"))
    why = f"exit code {proc.returncode}"
    with contextlib.suppress(OSError, ValueError):
        why = json.loads((d / "failed.json").read_text(encoding="utf-8"))["reason"]
    return False, f"{why} (log: {d / 'session.log'})", None


async def run_all(study: StudyFile, out: Path, todo: list[Run], jobs: int, progress: Progress):
    """Run ``todo``, ``jobs`` at a time (one at a time once a servo missed its budget)."""
    pending = list(todo)
    running: dict[asyncio.Task, Run] = {}
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    limit = jobs
    try:
        while (pending or running) and not stop.is_set():
            while pending and len(running) < limit:
                run = pending.pop(0)
                running[asyncio.create_task(_run_child(run, study, out))] = run
                progress.running[run.run_id] = time.monotonic()
            progress.show()
            finished, _ = await asyncio.wait(set(running), timeout=1.0)
            for task in finished:
                run = running.pop(task)
                t = progress.running.pop(run.run_id)
                ok, why, summary = task.result()
                if ok:
                    progress.done += 1
                    progress.walls.append(time.monotonic() - t)
                    if not servo_ok(summary) and limit > 1:
                        limit = 1
                        progress.note(f"{run.run_id}: the servo missed its budget: one at a time")
                else:
                    progress.failed += 1
                    progress.note(f"{run.run_id}: FAILED: {why}")
        if stop.is_set():
            progress.note("stopping: the running sessions stop cleanly; run again to resume")
    finally:
        for task in running:
            task.cancel()
        await asyncio.gather(*running, return_exceptions=True)
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        progress.show(force=True)
        if progress.tty:
            print(file=progress.stream)


def build_table(study: StudyFile, out: Path, charts: Path | None) -> dict[str, Any]:
    """The table and charts of every recorded run of the file; the JSON written."""
    from humantele.study import table

    rows, meta_runs = [], []
    for run in study.runs():
        d = out / run.run_id
        if not (d / "summary.json").exists():
            continue
        summary = json.loads((d / "summary.json").read_text(encoding="utf-8"))
        rows += table.run_scans(d, summary)
        meta_runs.append({"run": run.run_id, "wall_s": summary.get("wall_s"),
                          "load_at_start": summary.get("load_at_start"),
                          "servo_ok": servo_ok(summary)})  # fmt: skip
    conditions = [c.model_dump() for c in study.condition]
    summ = table.summarize(rows, conditions)
    meta = {"runs": meta_runs, "settings": study.study.model_dump(), "cpus": os.cpu_count()}
    table.write_json(out / "study.json", rows, summ, meta)
    header = (
        f"{len(meta_runs)} runs of {len(study.runs())}, {study.study.scans} scans of "
        f"{study.study.scan_s:g} s each, seeds {study.study.seeds}."
    )
    (out / "table.md").write_text(table.markdown(rows, summ, header), encoding="utf-8")
    paths = []
    if rows:
        from humantele.study import charts as ch

        paths = ch.write_charts(summ, charts or out)
    return {"meta": meta, "conditions": summ, "scans": rows, "charts": [str(p) for p in paths]}


def run(args: argparse.Namespace) -> int:
    from humantele.transport.turnserver import TurnServer

    study = load_conditions(args.conditions)
    out = args.out or Path("runs") / f"study-{args.conditions.stem}"
    out.mkdir(parents=True, exist_ok=True)
    if not args.table_only:
        if not TurnServer.available():
            print("humantele study: turnserver (coturn) is not installed", file=sys.stderr)
            return 2
        done, todo = plan(study, out)
        jobs = parse_jobs(args.jobs, len(todo))
        print(
            f"humantele study: {len(done) + len(todo)} runs ({len(done)} recorded before), "
            f"{jobs} at a time ({os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}); "
            f"recordings in {out}",
            file=sys.stderr,
        )
        progress = Progress(len(done) + len(todo), len(done), jobs)
        t0 = time.monotonic()
        asyncio.run(run_all(study, out, todo, jobs, progress))
        load = " ".join(f"{v:.1f}" for v in os.getloadavg())
        print(
            f"humantele study: {progress.done} recorded, {progress.failed} failed in "
            f"{_clock(time.monotonic() - t0)} (load average {load})",
            file=sys.stderr,
        )
    result = build_table(study, out, args.charts)
    text = (out / "table.md").read_text(encoding="utf-8")
    if args.json:
        print(json.dumps(result, default=_json_default))
    else:
        print(text)
        print(f"table: {out / 'table.md'}; charts: {', '.join(result['charts']) or 'none'}")
    missing = [r.run_id for r in study.runs() if not (out / r.run_id / "summary.json").exists()]
    return 1 if missing else 0


def _json_default(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return str(v)

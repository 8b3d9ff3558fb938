"""``humantele demo``: a whole session on simulated devices, over real WebRTC on loopback.

One command, no external service. The demo process runs the signaling server itself and starts
the expert (sim Touch X held by the scripted sonographer, 1 kHz servo process) and the follower
(sim tracker, force sensor and person) as separate OS processes (``humantele expert`` and
``humantele follower``) that talk WebRTC over loopback. The follower has a fresh state
directory, so its simulated person performs the four-landmark calibration first; the expert
then gets the patient model and the session runs.

A status line shows what the session does or waits for (:mod:`humantele.demo_status`:
starting daemons, waiting for the link, starting the tracker, calibrating, following), the pose
rate and age at the follower, the haptic force at the expert and the follower's alignment
error. ``--duration S`` ends the run S seconds after
both daemons have started (their first stats; a daemon not started within ``START_TIMEOUT_S``
fails the demo), so a slow start on a busy machine never cuts the run short; ``--json`` prints
one summary object, on one line, as the last line of output. Ctrl-C or SIGTERM: the daemons
say bye, every process ends, exit code 0.

``--record FILE`` records the session: each daemon writes its own file,
``role_path(FILE, "expert")`` and ``role_path(FILE, "follower")`` (``FILE.expert.mcap``,
``FILE.follower.mcap``) with one session id, and the expert runs one scan, from shortly after
the patient model arrives until the demo stops (``[expert.scans]``). The ids are the simulated
participants' pseudonyms (``[demo]``). At the end the demo prints the ``humantele analyze``
command for the files.

The children report to the demo through JSON stats files (:mod:`humantele.runtime.stats`, the
daemons' runtime). The signaling token is random per run and reaches the children through the
environment; it is never printed.

The demo in three parts: its plan (:mod:`humantele.demo_plan`: the run directory, the
children's commands and environment), :func:`supervise` (here) and its report
(:func:`conclude` here, the summary in :mod:`humantele.demo_report`, the status line in
:mod:`humantele.demo_status`).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import shutil
import sys
import time
from typing import Any

from humantele.cliargs import duration_s, log_level, port
from humantele.demo_plan import DemoPlan, plan_demo
from humantele.demo_report import CountWindow, report, summarize
from humantele.demo_status import status_line
from humantele.runtime.process import ignore_stop_signals, on_stop_signals
from humantele.runtime.stats import read_stats
from humantele.runtime.supervise import SupervisedDaemon
from humantele.web.credential import CONSOLE_KEY_ENV, PAIRING_CODE_ENV, show_code

log = logging.getLogger(__name__)


# --- the demo ---------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--duration",
        type=duration_s,
        default=20.0,
        help="seconds once both daemons run (default 20)",
    )
    parser.add_argument("--json", action="store_true", help="print a JSON summary at the end")
    parser.add_argument("--config", help="TOML file with a [demo] section (configs/demo.toml)")
    parser.add_argument("--room", help="session room name (default demo)")
    parser.add_argument("--keep", action="store_true", help="keep the run directory (logs)")
    parser.add_argument(
        "--log-level", type=log_level, default="WARNING", help="daemons' logging level"
    )
    parser.add_argument(
        "--igtl-port",
        type=port,
        metavar="PORT",
        help="the follower serves OpenIGTLink for 3D Slicer on this port (18944: Slicer's "
        "default; 0 picks one; docs/slicer.md)",
    )
    parser.add_argument(
        "--replay",
        metavar="FILE",
        help="the follower on a recorded clinic (`humantele devices record`'s file) through its "
        "real device backends, looped, instead of the simulated clinic",
    )
    parser.add_argument(
        "--record",
        metavar="FILE",
        help="record the session: FILE.expert.mcap and FILE.follower.mcap (one per daemon); "
        "a directory: session-<date>-<time>.*.mcap in it",
    )


def _page_urls(
    e: dict[str, Any], f: dict[str, Any], env: dict[str, str] | None = None
) -> dict[str, str]:
    """The pages the daemons serve, once they do: the sonographer's console (with the key the
    demo gave the expert), the headset's (with the pairing code it gave the follower)."""
    env = env or {}
    urls = {}
    if (e.get("console") or {}).get("url"):
        key = env.get(CONSOLE_KEY_ENV)
        urls["console (sonographer)"] = e["console"]["url"] + (f"#key={key}" if key else "")
    if (f.get("feed") or {}).get("page_url"):
        code = env.get(PAIRING_CODE_ENV)
        urls["headset page (follower)"] = f["feed"]["page_url"] + (
            f"  (pairing code {show_code(code)})" if code else ""
        )
    igtl = f.get("igtl") or {}
    if igtl.get("port"):
        host = igtl.get("host") or "127.0.0.1"
        urls["OpenIGTLink (follower, 3D Slicer)"] = f"{host}:{igtl['port']}"
    return urls


START_TIMEOUT_S = 120.0  # a daemon that has written no stats by then has failed to start


async def supervise(
    plan: DemoPlan,
    daemons: dict[str, SupervisedDaemon],
    duration_s: float,
    stop: asyncio.Event,
    status_to: Any,
) -> tuple[str, CountWindow, float]:
    """Run the daemons until ``duration_s`` after both started, ``stop``, or a failure (a
    daemon that died is restarted by its :class:`SupervisedDaemon`; one that cannot be, or
    did not start within ``START_TIMEOUT_S``, fails the demo); print the pages' addresses
    and the status line meanwhile. Returns (the failure or '', the count window, the time
    the demo started on ``time.monotonic()``). The caller stops the daemons."""
    tty = status_to.isatty()
    window = CountWindow()
    t0 = time.monotonic()
    failed = ""
    for d in daemons.values():
        await d.start()
    last_print = 0.0
    pages: dict[str, str] = {}
    t_started: float | None = None  # both daemons up: --duration counts from here
    while not stop.is_set():
        now = time.monotonic()
        if t_started is not None and now - t_started >= duration_s:
            break
        for d in daemons.values():  # a daemon that died unexpectedly is restarted
            failed = failed or (await d.check(now) or "")
        if failed:
            break
        e, f = read_stats(plan.stats["expert"]) or {}, read_stats(plan.stats["follower"]) or {}
        for name, url in _page_urls(e, f, plan.env).items():
            if name not in pages:
                pages[name] = url
                print(f"{name}: {url}", file=status_to, flush=True)
        window.update(daemons, {"expert": e, "follower": f}, now - t0)
        for d, st in ((daemons["expert"], e), (daemons["follower"], f)):
            if st:
                d.saw_stats(now)
        if t_started is None and e and f:
            t_started = now
        elif t_started is None and now - t0 > START_TIMEOUT_S:
            late = "expert" if not e else "follower"
            failed = f"{late} did not start within {START_TIMEOUT_S:.0f} s"
            break
        if tty or now - last_print >= 2.0:
            last_print = now
            line = status_line(e, f, now - t0) + "".join(d.status(now) for d in daemons.values())
            print(("\r" + line + "\x1b[K") if tty else line, end="" if tty else "\n",
                  file=status_to, flush=True)  # fmt: skip
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), 0.5)
    return failed, window, t0


async def run_demo(args: argparse.Namespace, out=sys.stdout) -> int:
    """Run the demo: :func:`plan_demo`, the signaling server, :func:`supervise` the daemons,
    stop them, :func:`conclude` (the report); returns the exit code."""
    from humantele.signaling.server import SignalConfig, SignalingServer

    plan = plan_demo(args)
    server = SignalingServer(SignalConfig(port=0), token=plan.token)
    await server.start()
    stop = asyncio.Event()
    on_stop_signals(asyncio.get_running_loop(), stop.set)
    status_to = sys.stderr if args.json else out
    common = ["--signaling-url", server.url, "--room", plan.room, "--log-level", args.log_level]
    daemons = {
        role: SupervisedDaemon(
            role,
            [*cmd, *common, "--stats-file", str(plan.stats[role])],
            plan.stats[role],
            plan.run_dir / f"{role}.log",
            plan.env,
        )
        for role, cmd in plan.cmds.items()
    }
    try:
        failed, window, t0 = await supervise(plan, daemons, args.duration, stop, status_to)
    finally:
        codes = {}
        for role in ("expert", "follower"):  # the expert first: it says bye to the follower
            codes[role] = await daemons[role].stop()
        await server.stop()
        if status_to.isatty():
            print(file=status_to)
    return conclude(plan, daemons, codes, failed, window, t0, args, out)


def conclude(
    plan: DemoPlan,
    daemons: dict[str, SupervisedDaemon],
    codes: dict[str, int],
    failed: str,
    window: CountWindow,
    t0: float,
    args: argparse.Namespace,
    out: Any,
) -> int:
    """The demo's report (the daemons stopped with exit ``codes``; ``failed``: why it
    failed, or ''): the summary from their last stats, printed (and as JSON with
    ``--json``); the run directory removed unless kept or failed. The exit code."""
    e, f = read_stats(plan.stats["expert"]) or {}, read_stats(plan.stats["follower"]) or {}
    e, f = window.adjusted({"expert": e, "follower": f})
    summary = summarize(e, f, time.monotonic() - t0, codes)
    summary["restarts"] = {role: d.restarts for role, d in daemons.items()}
    summary["restart_exit_codes"] = {role: d.exit_codes for role, d in daemons.items()}
    summary["counts_since_s"] = window.since_s
    ok = not failed and all(c == 0 for c in codes.values())
    report(summary, e, f, failed, plan.run_dir, plan.rec_paths, args.json, out)
    if ok and not args.keep:
        shutil.rmtree(plan.run_dir, ignore_errors=True)
    elif args.keep:
        print(f"run directory: {plan.run_dir}", file=sys.stderr)
    if args.json:
        print(json.dumps(summary, separators=(",", ":")), file=out, flush=True)
    return 0 if ok else 1


def run(args: argparse.Namespace) -> int:
    try:
        return asyncio.run(run_demo(args))
    finally:
        ignore_stop_signals()

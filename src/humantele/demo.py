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
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import secrets
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import field_validator

from humantele.cliargs import duration_s, log_level, port
from humantele.demo_report import CountWindow, report, summarize
from humantele.demo_status import status_line
from humantele.recording.schemas import check_participant_id
from humantele.runtime.process import PARENT_PID_ENV, ignore_stop_signals, on_stop_signals
from humantele.runtime.stats import read_stats
from humantele.runtime.supervise import SupervisedDaemon
from humantele.signaling.messages import TOKEN_ENV
from humantele.web.credential import (
    CONSOLE_KEY_ENV,
    PAIRING_CODE_ENV,
    new_code,
    new_key,
    show_code,
)

log = logging.getLogger(__name__)


# --- the demo ---------------------------------------------------------------------------------


def _demo_config_model():
    from pydantic import Field

    from humantele.config import ConfigModel

    class DemoConfig(ConfigModel):
        """``[demo]`` of configs/demo.toml; relative paths are from the file's directory's
        parent (the repository root for configs/demo.toml) or the current directory."""

        room: str = Field("demo", pattern=r"^[A-Za-z0-9_.-]{1,64}$")
        expert_config: str | None = None
        follower_config: str | None = None
        # Pseudonyms recorded with --record: the simulated follower and sonographer.
        follower_id: str = "F0"
        sonographer_id: str = "S0"

        @field_validator("follower_id", "sonographer_id")
        @classmethod
        def _pseudonym(cls, v: str, info: Any) -> str:
            return check_participant_id(v, info.field_name)

    return DemoConfig


def _resolve(path: str | None, base: Path) -> str | None:
    if not path:
        return None
    p = Path(path).expanduser()
    for cand in (p, base / p):
        if cand.exists():
            return str(cand.resolve())
    from humantele.config import ConfigError

    raise ConfigError(f"{path}: no such configuration file (from the [demo] section)")


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


def recording_paths(record: str | Path) -> dict[str, Path]:
    """The files the daemons record to for ``--record FILE``; ConfigError (exit code 2) when
    one exists (never overwritten) or its directory is missing or not writable. ``FILE`` a
    directory (or ending in ``/``): ``session-<date>-<time>`` files in it. The daemons check
    again (and the disk space) when they open them."""
    from humantele.config import ConfigError
    from humantele.recording import role_path

    base = Path(record).expanduser()
    if str(record).endswith(("/", os.sep)) or base.is_dir():  # a directory: a file in it
        if not base.is_dir():
            raise ConfigError(f"--record: no directory {base}")
        base = base / time.strftime("session-%Y%m%d-%H%M%S.mcap")
    paths = {role: role_path(base, role) for role in ("expert", "follower")}
    for path in paths.values():
        parent = path.parent
        if path.exists():
            raise ConfigError(f"--record: {path} exists (a recording is never overwritten)")
        if not parent.is_dir():
            raise ConfigError(f"--record: no directory {parent} for {path}")
        if not os.access(parent, os.W_OK):
            raise ConfigError(f"--record: directory {parent} is not writable")
    return paths


def replay_follower_config(recording: str, run_dir: Path) -> str:
    """A follower configuration (written in ``run_dir``) whose clinic is ``recording``
    replayed through the real backends: tracker, force board and, if recorded, video.
    ConfigError (exit code 2) for a file that is not a device recording."""
    from humantele.config import ConfigError
    from humantele.recording.device_file import DeviceRecordingError, open_recording

    path = Path(recording).resolve()
    try:
        info = open_recording(path).info
    except (OSError, DeviceRecordingError) as exc:
        raise ConfigError(f"--replay: {exc}") from None
    devices = set(info.get("devices", "").split(","))
    if "ahat" not in devices or "force" not in devices:
        raise ConfigError(f"--replay: {path} has no tracker frames and force reports to replay")
    file = json.dumps(str(path))
    text = (
        '[follower.clinic]\nbackend = "devices"\n'
        f'[sensing.camera]\nbackend = "replay"\nfile = {file}\nloop = true\n'
        f'[sensing.force.sensor]\nbackend = "replay"\nfile = {file}\nloop = true\n'
    )
    video = {"us", "pov"} <= devices
    text += f"[follower.video]\nenabled = {str(video).lower()}\n"
    if video:
        for track in ("us", "pov"):
            text += f'[follower.video.{track}]\nbackend = "replay"\nfile = {file}\nloop = true\n'
    out = run_dir / "follower-replay.toml"
    out.write_text(text, encoding="utf-8")
    return str(out)


def us_scale(follower_config: str | None) -> tuple[tuple[float, float], float] | None:
    """(row, col) mm per pixel and the row (px) of depth 0 of the follower's ultrasound when
    it is the sim one (the demo tells the expert's console: its calipers and its depth
    scale); None for a real source."""
    from humantele.config import load_config
    from humantele.follower.daemon import FollowerConfig
    from humantele.video.scan import ScanGeometry
    from humantele.video.sim_ultrasound import SimUltrasoundConfig

    cfg = load_config(FollowerConfig, follower_config, "follower" if follower_config else None)
    c = cfg.video.us
    if not isinstance(c, SimUltrasoundConfig):
        return None
    g = ScanGeometry(c.probe, c.width, c.height, c.depth_m, c.fov_deg, c.radius_m,
                     c.aperture_m, c.beams, c.samples)  # fmt: skip
    return g.pixel_spacing_mm, g.depth_origin_row


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


@dataclass
class DemoPlan:
    """What the demo starts: the run directory (logs, stats, the follower's state), the
    children's environment (the token, the pages' key and code: never printed), each
    daemon's command (after ``python -m humantele``, before the link's arguments) and its
    stats file, and the recordings (role -> path; empty without ``--record``)."""

    room: str
    run_dir: Path
    token: str
    env: dict[str, str]
    cmds: dict[str, list[str]]
    stats: dict[str, Path]
    rec_paths: dict[str, Path]


def plan_demo(args: argparse.Namespace) -> DemoPlan:
    """The demo's plan from its arguments and ``[demo]`` config (refused: ConfigError)."""
    from humantele.config import load_config

    cfg = load_config(_demo_config_model(), args.config, "demo" if args.config else None)
    base = Path(args.config).resolve().parent.parent if args.config else Path.cwd()
    child_configs = {
        "expert": _resolve(cfg.expert_config, base),
        "follower": _resolve(cfg.follower_config, base),
    }
    record = getattr(args, "record", None)
    rec_paths = recording_paths(record) if record else {}
    run_dir = Path(tempfile.mkdtemp(prefix="humantele-demo-"))
    token = secrets.token_urlsafe(24)
    env = dict(os.environ)
    env[TOKEN_ENV] = token
    env[PARENT_PID_ENV] = str(os.getpid())
    env.setdefault(CONSOLE_KEY_ENV, new_key())  # the demo prints the pages' addresses with them
    env.setdefault(PAIRING_CODE_ENV, new_code())
    cmds = {
        "follower": [
            "follower", "--state-dir", str(run_dir / "follower-state"), "--feed-port", "0",
        ],
        "expert": ["expert", "--console-port", "0"],
    }  # fmt: skip
    if getattr(args, "replay", None):
        child_configs["follower"] = replay_follower_config(args.replay, run_dir)
    for role, path in child_configs.items():
        if path:
            cmds[role] += ["--config", path]
    if getattr(args, "igtl_port", None) is not None:
        cmds["follower"] += ["--igtl-port", str(args.igtl_port)]
    scale = us_scale(child_configs["follower"])
    if scale is not None:  # the console's calipers and depth scale on the sim ultrasound
        spacing, depth0 = scale
        cmds["expert"] += ["--us-pixel-spacing-mm", *(f"{v:.9g}" for v in spacing),
                           "--us-depth-origin-row", f"{depth0:.6g}"]  # fmt: skip
    if rec_paths:  # one file per daemon, one session id
        ids = ["--session-id", secrets.token_hex(6), "--follower-id", cfg.follower_id,
               "--sonographer-id", cfg.sonographer_id]  # fmt: skip
        for role in cmds:
            cmds[role] += ["--record", str(rec_paths[role]), *ids]
    stats = {role: run_dir / f"{role}.json" for role in ("expert", "follower")}
    return DemoPlan(args.room or cfg.room, run_dir, token, env, cmds, stats, rec_paths)


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

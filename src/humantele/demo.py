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
from pathlib import Path
from typing import Any

from pydantic import field_validator

from humantele.cliargs import duration_s, log_level, port
from humantele.demo_status import demo_phase
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


def _log_tail(path: Path, lines: int = 5) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").strip().splitlines()[-lines:])
    except OSError:
        return ""


def _status_line(e: dict[str, Any], f: dict[str, Any], elapsed: float) -> str:
    def num(v: Any, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    return (
        f"[{elapsed:5.1f} s] {demo_phase(e, f)} | "
        f"poses {num(f.get('pose_rate_hz'), '.0f')} Hz, "
        f"age {num(f.get('pose_age_last_ms'), '.1f')} ms | "
        f"force {num(e.get('force_n'), '.2f')} N | "
        f"alignment {num(f.get('alignment_mm_rms'), '.1f')} mm "
        f"{num(f.get('alignment_deg_rms'), '.1f')} deg | "
        + _servo_status(e)
        + _children_status(f)
        + _recording_status(e, f)
    )


def _children_status(f: dict[str, Any]) -> str:
    """The follower's children when one is not running: `` | video DOWN (...)``, `` | video
    restarting (1)``, `` | sensing restarting (1), no measurements 4 s`` (else '')."""
    out = ""
    video = (f.get("video") or {}).get("process") or {}
    state = str(video.get("state") or "running")
    if state.startswith(("down", "failed")):
        out += f" | video DOWN ({state.partition(': ')[2][:80]})"
    elif state.startswith("restarting"):
        out += f" | video {state}"
    sensing = str(f.get("sensing_state") or "running")
    if sensing.startswith(("restarting", "failed")):
        out += f" | sensing {sensing[:80]}"
        age = f.get("measurement_age_s")
        if age is not None and age > 0.5:
            out += f", no measurements {age:.0f} s"
    return out


def children_summary(e: dict[str, Any], f: dict[str, Any]) -> dict[str, Any]:
    """Each daemon child's restarts and state at the end; the follower's time without
    measurements after its first (a restarted sensing process takes seconds to measure)."""
    video = (f.get("video") or {}).get("process")
    return {
        "servo": {"restarts": e.get("servo_restarts", 0), "state": e.get("servo_state")},
        "sensing": {
            "restarts": f.get("sensing_restarts", 0),
            "state": f.get("sensing_state"),
            **{
                k: f.get(k)
                for k in ("measurement_gaps", "measurement_gap_s", "measurement_gap_max_s")
            },
        },  # fmt: skip
        "video": None if not video else {k: video.get(k) for k in ("restarts", "state")},
    }


def _servo_status(e: dict[str, Any]) -> str:
    """``servo 1000 Hz``, or the fault / the reason it is down, in capitals (never hidden)."""
    state = str(e.get("servo_state") or "running")
    if state.startswith("down"):
        return f"servo DOWN ({state.partition(': ')[2][:80]})"
    text = f"servo {format(e['servo_rate_hz'], '.0f') if e.get('servo_rate_hz') else '-'} Hz"
    if state.startswith("fault"):
        text += f" FAULT {state.partition(': ')[2]}"
    if e.get("models_refused"):
        text += f", {e['models_refused']} model(s) REFUSED"
    return text


def _recording_status(e: dict[str, Any], f: dict[str, Any]) -> str:
    """`` | scan 1, recording`` (or ``recording FAILED``) when the daemons record."""
    recs = [s["recording"] for s in (e, f) if s.get("recording")]
    scan = e.get("scan")
    text = f" | scan {scan}" if scan else ""
    if recs:
        failed = any(r.get("error") for r in recs)
        text += (", " if text else " | ") + ("recording FAILED" if failed else "recording")
    return text


def replay_follower_config(recording: str, run_dir: Path) -> str:
    """A follower configuration (written in ``run_dir``) whose clinic is ``recording``
    replayed through the real backends: tracker, force board and, if recorded, video.
    ConfigError (exit code 2) for a file that is not a device recording."""
    from humantele.config import ConfigError
    from humantele.devices.replay_file import DeviceRecordingError, open_recording

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


def summarize(
    e: dict[str, Any], f: dict[str, Any], duration: float, codes: dict[str, int | None]
) -> dict[str, Any]:
    """The demo's summary from the two daemons' final stats."""
    recording = {
        r: s["recording"] for r, s in (("expert", e), ("follower", f)) if s.get("recording")
    }
    return {
        "duration_s": round(duration, 2),
        "poses_sent": e.get("poses_sent", 0),
        "poses_received": f.get("poses_received", 0),
        "pose_age_p50_ms": f.get("pose_age_p50_ms"),
        "pose_age_p99_ms": f.get("pose_age_p99_ms"),
        "states_sent": f.get("states_sent", 0),
        "states_received": e.get("states_received", 0),
        "state_age_p50_ms": e.get("state_age_p50_ms"),
        "servo_rate_hz": e.get("servo_rate_hz"),
        "servo_overruns": e.get("servo_overruns"),
        "servo_period_p99_us": e.get("servo_period_p99_us"),
        "servo_state": e.get("servo_state"),
        "servo_restarts": e.get("servo_restarts", 0),
        "models_refused": e.get("models_refused", 0),
        "calibrated": bool(f.get("calibrated", False)),
        "model_installed": bool(e.get("has_model", False)),
        "alignment_mm_rms": f.get("alignment_mm_rms"),
        "alignment_deg_rms": f.get("alignment_deg_rms"),
        "dropped_messages": int(e.get("dropped_total", 0)) + int(f.get("dropped_total", 0)),
        "dropped": {"expert": e.get("dropped", {}), "follower": f.get("dropped", {})},
        "link_connections": e.get("connections", 0),
        "cpu_percent_expert": e.get("cpu_percent"),
        "cpu_percent_servo": e.get("cpu_percent_servo"),
        "cpu_percent_follower": f.get("cpu_percent"),
        "cpu_percent_sensing": f.get("cpu_percent_sensing"),
        "follower_tick_late_p99_ms": f.get("tick_late_p99_ms"),
        "loop_priority": {"expert": e.get("loop_priority"), "follower": f.get("loop_priority")},
        "scans": e.get("scans_started", 0),
        "recording": recording or None,
        "video": video_summary(e.get("video"), f.get("video")),
        "children": children_summary(e, f),
        "exit_codes": codes,
    }


START_TIMEOUT_S = 120.0  # a daemon that has written no stats by then has failed to start


def video_summary(e: dict[str, Any] | None, f: dict[str, Any] | None) -> dict[str, Any] | None:
    """Per track at the expert: frames, rate, age (capture to decoded) p50/p95/max; the
    follower's POV degradation level. None when video is off."""
    if not e:
        return None
    out: dict[str, Any] = {}
    keys = ("frames", "fps", "fps_mean", "gap_max_ms", "age_p50_ms", "age_p95_ms", "age_max_ms",
            "unreadable", "no_info", "stale_dropped", "jitter")  # fmt: skip
    for name in ("us", "pov"):
        t = e.get(name) or {}
        out[name] = {k: t.get(k) for k in (*keys, "size")}
    if f:
        out["pov_level"] = f.get("pov_level")
        out["us_level"] = f.get("us_level")
        out["pov_level_changes"] = f.get("pov_level_changes")
        out["process"] = f.get("process")
        out["follower"] = {n: f.get(n) for n in ("us", "pov")}
    return out


# Counts of one stream at each end: (sender's key, receiver's key) per role.
STREAM_COUNTS = {"expert": ("poses_sent", "states_received"),
                 "follower": ("poses_received", "states_sent")}  # fmt: skip


class CountWindow:
    """After a daemon restarts, the stream counts of the summary cover the same window at both
    ends: from the restart on, the other daemon's counts are taken relative to its last
    figures before the new process could have connected (taken as the restart is seen, not at
    the new process's first stats, which may come after its link is up and messages flow).
    ``since_s``: the window's start (s after the demo started), None without a restart."""

    def __init__(self) -> None:
        self.baseline: dict[str, dict[str, int]] = {"expert": {}, "follower": {}}
        self._restarts_seen = {"expert": 0, "follower": 0}
        self.since_s: float | None = None

    def update(self, daemons: dict, stats: dict[str, dict], t: float) -> None:
        for role, d in daemons.items():
            if d.restarts != self._restarts_seen[role]:  # restarted since the last look
                self._restarts_seen[role] = d.restarts
                other = "follower" if role == "expert" else "expert"
                self.baseline[role] = {}
                self.baseline[other] = {
                    k: int(stats[other].get(k) or 0) for k in STREAM_COUNTS[other]
                }
                self.since_s = round(t, 2)

    def adjusted(self, stats: dict[str, dict]) -> tuple[dict, dict]:
        out = []
        for role in ("expert", "follower"):
            s = dict(stats[role])
            for k, v in self.baseline[role].items():
                s[k] = max(0, int(s.get(k) or 0) - v)
            out.append(s)
        return out[0], out[1]


async def run_demo(args: argparse.Namespace, out=sys.stdout) -> int:
    """Run the demo; returns the exit code."""
    from humantele.config import load_config
    from humantele.signaling.server import SignalConfig, SignalingServer

    cfg = load_config(_demo_config_model(), args.config, "demo" if args.config else None)
    base = Path(args.config).resolve().parent.parent if args.config else Path.cwd()
    child_configs = {
        "expert": _resolve(cfg.expert_config, base),
        "follower": _resolve(cfg.follower_config, base),
    }
    room = args.room or cfg.room
    record = getattr(args, "record", None)
    rec_paths = recording_paths(record) if record else {}
    run_dir = Path(tempfile.mkdtemp(prefix="humantele-demo-"))
    token = secrets.token_urlsafe(24)
    server = SignalingServer(SignalConfig(port=0), token=token)
    await server.start()
    env = dict(os.environ)
    env[TOKEN_ENV] = token
    env[PARENT_PID_ENV] = str(os.getpid())
    env.setdefault(CONSOLE_KEY_ENV, new_key())  # the demo prints the pages' addresses with them
    env.setdefault(PAIRING_CODE_ENV, new_code())
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    on_stop_signals(loop, stop.set)
    status_to = sys.stderr if args.json else out
    tty = status_to.isatty()
    common = ["--signaling-url", server.url, "--room", room, "--log-level", args.log_level]
    stats = {"expert": run_dir / "expert.json", "follower": run_dir / "follower.json"}
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
    daemons = {
        role: SupervisedDaemon(
            role,
            [*cmd, *common, "--stats-file", str(stats[role])],
            stats[role],
            run_dir / f"{role}.log",
            env,
        )
        for role, cmd in cmds.items()
    }
    window = CountWindow()
    t0 = time.monotonic()
    failed = ""
    try:
        for d in daemons.values():
            await d.start()
        last_print = 0.0
        pages: dict[str, str] = {}
        t_started: float | None = None  # both daemons up: --duration counts from here
        while not stop.is_set():
            now = time.monotonic()
            if t_started is not None and now - t_started >= args.duration:
                break
            for d in daemons.values():  # a daemon that died unexpectedly is restarted
                failed = failed or (await d.check(now) or "")
            if failed:
                break
            e, f = read_stats(stats["expert"]) or {}, read_stats(stats["follower"]) or {}
            for name, url in _page_urls(e, f, env).items():
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
                line = _status_line(e, f, now - t0) + "".join(
                    d.status(now) for d in daemons.values()
                )
                print(("\r" + line + "\x1b[K") if tty else line, end="" if tty else "\n",
                      file=status_to, flush=True)  # fmt: skip
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), 0.5)
    finally:
        codes = {}
        for role in ("expert", "follower"):  # the expert first: it says bye to the follower
            codes[role] = await daemons[role].stop()
        await server.stop()
        if tty:
            print(file=status_to)
    elapsed = time.monotonic() - t0
    e, f = read_stats(stats["expert"]) or {}, read_stats(stats["follower"]) or {}
    e, f = window.adjusted({"expert": e, "follower": f})
    summary = summarize(e, f, elapsed, codes)
    summary["restarts"] = {role: d.restarts for role, d in daemons.items()}
    summary["restart_exit_codes"] = {role: d.exit_codes for role, d in daemons.items()}
    summary["counts_since_s"] = window.since_s
    ok = not failed and all(c == 0 for c in codes.values())
    if failed:
        role = failed.split(" ", 1)[0]
        tail = _log_tail(run_dir / f"{role}.log")
        print(f"humantele demo: {failed}; logs in {run_dir}", file=sys.stderr)
        if tail:
            print(f"{role} log ends with:\n{tail}", file=sys.stderr)
    elif not ok:
        print(f"humantele demo: a daemon failed {codes}; logs in {run_dir}", file=sys.stderr)
    if not args.json:
        print(_status_line(e, f, elapsed), file=out)
        print(
            f"poses sent {summary['poses_sent']}, received {summary['poses_received']}, "
            f"age p50 {summary['pose_age_p50_ms']} ms p99 {summary['pose_age_p99_ms']} ms; "
            f"servo {summary['servo_rate_hz'] or 0:.0f} Hz, {summary['servo_overruns']} overruns; "
            f"calibrated {summary['calibrated']}; dropped {summary['dropped_messages']}; "
            f"CPU expert {summary['cpu_percent_expert']} % (servo "
            f"{summary['cpu_percent_servo']} %), follower {summary['cpu_percent_follower']} %",
            file=out,
        )
    for role, st in (summary["recording"] or {}).items():
        if st.get("error") or st.get("dropped"):
            print(
                f"humantele demo: {role} recording: {st.get('error') or 'ok'}, "
                f"{st.get('dropped')} sample(s) dropped",
                file=sys.stderr,
            )
    if rec_paths and all(p.exists() for p in rec_paths.values()):
        files = " ".join(str(p) for p in rec_paths.values())
        print(f"recorded {summary['scans']} scan(s); analyze with:\n  humantele analyze {files}",
              file=sys.stderr if args.json else out)  # fmt: skip
    if ok and not args.keep:
        shutil.rmtree(run_dir, ignore_errors=True)
    elif args.keep:
        print(f"run directory: {run_dir}", file=sys.stderr)
    if args.json:
        print(json.dumps(summary, separators=(",", ":")), file=out, flush=True)
    return 0 if ok else 1


def run(args: argparse.Namespace) -> int:
    try:
        return asyncio.run(run_demo(args))
    finally:
        ignore_stop_signals()

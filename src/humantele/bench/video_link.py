"""``humantele bench video link``: the two video tracks end to end, in the whole session.

Runs the demo (both daemons, the 1 kHz servo, the video process, on this machine) with a
generated configuration for ``--seconds`` and reads the daemons' figures:

- per track, glass to glass: the frame counter drawn at capture is read from the decoded
  frame at the expert and matched to its capture time (clock sync): p50/p95/max (ms, capture
  to decoded, display not included), frames per second at the expert (mean over the run),
  the longest gap between frames (a freeze), the POV's degradation level at the end;
- in the same row: the pose stream's age at the follower (p50/p99), the servo's rate and
  overruns, and CPU of the expert, its servo, the follower and its video process (% of one
  core).

Links: loopback; ``--turn`` (relay through coturn) with ``--delay-ms``/``--jitter-ms``/
``--loss``/``--kbps`` (the user-space WAN emulator on the expert's side, as ``bench session``;
``--kbps`` caps its rate each way, a 0.2 s tail-drop queue: a thin link);
``--busy-core`` adds a process spinning on one core; ``--no-fec`` has the follower send no
parity packet after each US frame (``[follower.video] fec``, on by default; docs/video.md,
"Sixth pass"; its figures in the JSON's ``video.fec`` and ``video.fec_sent``). ``--codec``,
``--us-size``, ``--pov-size`` pick the encoder and sizes. ``--matrix`` runs the standard set of
rows. Each row is merged into the "video-link" section of docs/benchmarks.md (rows of other
settings are kept).
Prints each row and, last, one JSON object.

Recovery: with ``--loss-window A,B`` the loss applies only from A to B s after the video
started to flow (200 kB forwarded to the expert). The expert then records its received frames
(``/expert/video_frame``, every frame's age) and the row is split into three phases: before
(from 2 s after the first frame to A), during, the first 5 s after B, and the rest, each with
its latency, rate and longest freeze; they go in a second table of the same section.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from humantele.report import (
    BENCHMARKS_MD,
    machine_line,
    markdown_table,
    section_rows,
    write_section,
)
from humantele.runtime.stats import percentile_ms

SECTION = "video-link"
TARGETS = {"us_p95_ms": 100.0, "pov_p95_ms": 150.0, "us_fps": 15.0, "pov_fps": 20.0}
MATRIX = [
    [],
    ["--us-kbps", "1000", "--pov-kbps", "800"],
    ["--us-kbps", "2500", "--pov-kbps", "2000"],
    ["--codec", "h264"],
    ["--us-size", "320x240", "--pov-size", "640x360"],
    ["--turn", "--delay-ms", "4", "--jitter-ms", "1.5"],
    ["--turn", "--delay-ms", "4", "--jitter-ms", "1.5", "--loss", "1"],
    ["--turn", "--delay-ms", "4", "--jitter-ms", "1.5", "--loss", "2"],
    ["--turn", "--delay-ms", "4", "--jitter-ms", "1.5", "--loss", "5"],
    ["--busy-core"],
    ["--turn", "--delay-ms", "4", "--jitter-ms", "1.5", "--loss", "5", "--loss-window", "10,25",
     "--seconds", "45"],
]  # fmt: skip
WARMUP_S = 2.0  # the first frames after the link comes up are left out of a phase
VIDEO_FLOWING = 200_000  # bytes to the expert: the video is flowing (--loss-window counts on)


def add_link_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=30.0, help="session length (s)")
    p.add_argument("--codec", choices=["vp8", "h264"], default="vp8")
    p.add_argument("--us-size", default="640x480", help="US image WxH (default 640x480)")
    p.add_argument("--pov-size", default="960x540", help="POV WxH (default 960x540)")
    p.add_argument("--us-kbps", type=int, help="fix the US bit rate (kbit/s; default: REMB)")
    p.add_argument("--pov-kbps", type=int, help="fix the POV bit rate (kbit/s; default: REMB)")
    p.add_argument("--turn", action="store_true", help="relay through a coturn turnserver")
    p.add_argument("--delay-ms", type=float, default=0.0, help="one-way delay (ms; --turn)")
    p.add_argument("--jitter-ms", type=float, default=0.0, help="delay std dev (ms; --turn)")
    p.add_argument("--loss", type=float, default=0.0, help="percent lost each way (--turn)")
    p.add_argument(
        "--kbps", type=float, default=0.0, help="the link's rate each way (kbit/s; --turn)"
    )
    p.add_argument(
        "--no-fec", action="store_true",
        help="the follower sends no parity packet after each US frame ([follower.video] fec)",
    )  # fmt: skip
    p.add_argument("--busy-core", action="store_true", help="a process spins on one core")
    p.add_argument("--no-process", action="store_true", help="video sources in threads")
    p.add_argument(
        "--loss-window", type=_window, default=None, metavar="A,B",
        help="--loss only from A to B s after the video flows (figures before/during/after)",
    )  # fmt: skip
    p.add_argument("--matrix", action="store_true", help="run the standard set of rows")


def _window(text: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("A,B: two numbers of seconds") from None
    if not 0.0 <= a < b:
        raise argparse.ArgumentTypeError("A,B: 0 <= A < B")
    return a, b


def _size(text: str) -> tuple[int, int]:
    w, h = (int(v) for v in text.lower().split("x"))
    return w, h


def label(args: argparse.Namespace) -> str:
    parts = [args.codec, f"US {args.us_size}", f"POV {args.pov_size}"]
    if args.us_kbps or args.pov_kbps:
        parts.append(f"fixed {args.us_kbps or 'REMB'} / {args.pov_kbps or 'REMB'} kbit/s")
    if args.turn or args.delay_ms or args.loss or args.kbps:
        link = "TURN"
        if args.delay_ms:
            link += f" +{args.delay_ms:g}" + (f"±{args.jitter_ms:g}" if args.jitter_ms else "")
            link += " ms"
        if args.kbps:
            link += f", {args.kbps:g} kbit/s"
        if args.loss:
            link += f", {args.loss:g} % loss"
            if args.loss_window:
                link += " from {:g} to {:g} s".format(*args.loss_window)
        parts.append(link)
    else:
        parts.append("loopback")
    if getattr(args, "no_fec", False):
        parts.append("no US parity")
    if args.busy_core:
        parts.append("1 core busy")
    if args.no_process:
        parts.append("threads")
    return ", ".join(parts)


def _toml_str(v: object) -> str:
    return json.dumps(v)  # a JSON string is a TOML basic string


def write_configs(d: Path, args: argparse.Namespace, ice: object | None) -> Path:
    """expert.toml, follower.toml and demo.toml for one run, in ``d`` (0700)."""
    (uw, uh), (pw, ph) = _size(args.us_size), _size(args.pov_size)
    link = {"expert": "", "follower": ""}
    for role, server in (ice or {}).items():
        cred = server.credential.get_secret_value() if server.credential else ""
        url = _toml_str(server.urls[0])
        link[role] = (
            f"relay_only = true\n[[{role}.link.ice_servers]]\nurls = [{url}]\n"
            f"username = {_toml_str(server.username or '')}\ncredential = {_toml_str(cred)}\n"
        )
    (d / "expert.toml").write_text(
        f"[expert.link]\npose_rate_hz = 100.0\n{link['expert']}\n"
        f'[expert.video]\nenabled = true\ncodec = "{args.codec}"\n'
    )
    (d / "follower.toml").write_text(
        f"[follower.link]\n{link['follower']}\n"
        f"[follower.video]\nenabled = true\nprocess = {str(not args.no_process).lower()}\n"
        f"record_us_hz = 0.0\nrecord_pov_hz = 0.0\n"
        + ("fec = false\n" if getattr(args, "no_fec", False) else "")
        + f'[follower.video.us]\nbackend = "sim"\nwidth = {uw}\nheight = {uh}\nfps = 20.0\n'
        f'[follower.video.pov]\nbackend = "sim"\nwidth = {pw}\nheight = {ph}\nfps = 25.0\n'
        + "".join(
            f"[follower.video.{name}_bitrate]\nstart_kbps = {k}\nmin_kbps = {k}\nmax_kbps = {k}\n"
            for name, k in (("us", args.us_kbps), ("pov", args.pov_kbps))
            if k
        )
    )
    (d / "demo.toml").write_text(
        f"[demo]\nexpert_config = {_toml_str(str(d / 'expert.toml'))}\n"
        f"follower_config = {_toml_str(str(d / 'follower.toml'))}\n"
    )
    os.chmod(d, 0o700)
    return d / "demo.toml"


async def measure(args: argparse.Namespace) -> dict:
    """One session with video; the demo's summary with this run's settings."""
    from humantele.demo import run_demo
    from humantele.transport.netem import NetemConfig, UdpRelay
    from humantele.transport.turnserver import TurnServer

    impaired = bool(args.delay_ms or args.jitter_ms or args.loss or args.kbps)
    use_turn = args.turn or impaired
    busy = None
    with tempfile.TemporaryDirectory(prefix="humantele-bench-video-") as tmp:
        async with contextlib.AsyncExitStack() as stack:
            ice = None
            relay = None
            if use_turn:
                turn = await stack.enter_async_context(TurnServer())
                ice = {"expert": turn.ice_server(), "follower": turn.ice_server()}
                if impaired:
                    netem = NetemConfig(
                        delay_s=args.delay_ms * 1e-3,
                        jitter_s=args.jitter_ms * 1e-3,
                        loss=0.0 if args.loss_window else args.loss / 100.0,
                        bandwidth_kbps=args.kbps,
                    )
                    relay = await stack.enter_async_context(UdpRelay((turn.host, turn.port), netem))
                    ice["expert"] = turn.ice_server(*relay.address)
            config = write_configs(Path(tmp), args, ice)
            load = os.getloadavg()[0]  # the machine's load when the run starts
            if args.busy_core:
                busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
            record = Path(tmp) / "run.mcap" if args.loss_window else None
            switches: list[float] = []
            lossy = None
            try:
                out = io.StringIO()
                demo_args = argparse.Namespace(
                    config=str(config), duration=args.seconds, json=True, room=None,
                    keep=False, log_level="WARNING", record=None if record is None else str(record),
                )  # fmt: skip
                t0 = time.monotonic()
                if args.loss_window and relay is not None:
                    lossy = asyncio.ensure_future(loss_window(relay, args, switches))
                code = await run_demo(demo_args, out=out)
                wall = time.monotonic() - t0
            finally:
                if lossy is not None:
                    lossy.cancel()
                if busy is not None:
                    busy.kill()
                    busy.wait()
            summary = json.loads(out.getvalue().strip().splitlines()[-1])
            summary["exit_code"] = code
            summary["load_at_start"] = round(load, 1)
            summary["wall_s"] = wall
            summary["relay"] = None if relay is None else relay.counters.as_dict()
            if record is not None and len(switches) == 2:
                summary["phases"] = phases(record, switches)
    summary["label"] = label(args)
    return summary


async def loss_window(relay: Any, args: argparse.Namespace, out: list) -> None:
    """Turn the relay's loss on at A and off at B s after the video started to flow (the
    relay has forwarded VIDEO_FLOWING bytes to the expert); ``out`` gets the two instants
    (s, monotonic: the daemons' clock on this machine)."""
    while relay.counters.down.bytes_forwarded < VIDEO_FLOWING:
        await asyncio.sleep(0.1)
    t0 = time.monotonic()
    a, b = args.loss_window
    for at, loss in ((a, args.loss / 100.0), (b, 0.0)):
        await asyncio.sleep(max(0.0, t0 + at - time.monotonic()))
        relay.config.loss = loss
        out.append(time.monotonic())


def phase_figures(t: list[float], ages: list[float], start: float, end: float) -> dict:
    """Latency (ms), frames per second and longest gap (ms) of the frames decoded in
    [start, end) (s, expert clock); ``ages`` NaN where unknown."""
    import numpy as np

    ta, aa = np.asarray(t, float), np.asarray(ages, float)
    keep = (ta >= start) & (ta < end)
    ts, a = ta[keep], aa[keep]
    a = a[np.isfinite(a)]
    edges = np.concatenate([[start], ts, [end]])
    return {
        "s": round(end - start, 1),
        "frames": int(ts.size),
        "fps": round(ts.size / (end - start), 1) if end > start else None,
        "gap_max_ms": round(float(np.diff(edges).max()) * 1e3),
        "age_p50_ms": percentile_ms(a, 50, ndigits=1),
        "age_p95_ms": percentile_ms(a, 95, ndigits=1),
        "age_max_ms": round(float(a.max()) * 1e3, 1) if a.size else None,
    }


def phases(record: Path, switches: list[float]) -> dict:
    """Per track, the figures before, during and after the loss window, from the expert's
    recording of every frame it decoded."""
    from humantele.recording import read_recording, role_path

    rec = read_recording(role_path(record, "expert"), ["/expert/video_frame"])
    samples = [s for s in rec.samples("/expert/video_frame") if s.get("event") == "received"]
    on, off = switches
    out: dict = {}
    for name in ("us", "pov"):
        mine = [s for s in samples if s.get("stream") == name]
        if not mine:
            continue
        t = [float(s["t"]) for s in mine]
        ages = [float(s.get("age_s", float("nan"))) for s in mine]
        bounds = {
            "before": (t[0] + WARMUP_S, on),
            "during": (on, off),
            "after, first 5 s": (off, off + 5.0),
            "after, rest": (off + 5.0, t[-1]),
        }
        out[name] = {k: phase_figures(t, ages, a, b) for k, (a, b) in bounds.items() if b > a}
    return out


def _v(x: object, fmt: str = "{:.0f}") -> str:
    return "-" if x is None else fmt.format(x)


def row(s: dict) -> list[str]:
    v = s.get("video") or {}
    us, pov = v.get("us") or {}, v.get("pov") or {}
    dur = s.get("duration_s") or 1.0
    proc = v.get("process") or {}
    vcpu = None if not proc.get("cpu_s") else 100.0 * proc["cpu_s"] / dur

    def track(t: dict) -> list[str]:
        return [
            f"{_v(t.get('age_p50_ms'))} / {_v(t.get('age_p95_ms'))} / {_v(t.get('age_max_ms'))}",
            _v(t.get("fps_mean"), "{:.1f}"),
            _v(t.get("gap_max_ms")),
        ]

    sent = v.get("follower") or {}

    def kbps(name: str) -> str:
        return _v(((sent.get(name) or {}).get("encoder") or {}).get("bitrate_kbps"))

    def unread(t: dict) -> str:
        return f"{_v(t.get('unreadable'))} of {_v(t.get('frames'))}"

    return [
        s["label"],
        *track(us),
        *track(pov),
        f"{unread(us)} / {unread(pov)}",
        f"{kbps('us')} / {kbps('pov')}",
        _v(v.get("pov_level")),
        f"{_v(s.get('pose_age_p50_ms'), '{:.1f}')} / {_v(s.get('pose_age_p99_ms'))}",
        f"{_v(s.get('servo_rate_hz'))} / {_v(s.get('servo_overruns'))}",
        f"{_v(s.get('cpu_percent_expert'))} / {_v(s.get('cpu_percent_servo'))} / "
        f"{_v(s.get('cpu_percent_follower'))} / {_v(vcpu)}",
        _v(s.get("load_at_start"), "{:.1f}"),
        time.strftime("%H:%M", time.gmtime()),
    ]


HEADER = [
    "setting", "US p50/p95/max ms", "US fps", "US gap ms", "POV p50/p95/max ms", "POV fps",
    "POV gap ms", "counter unread US / POV", "kbit/s US / POV", "POV level",
    "pose age p50/p99 ms", "servo Hz / overruns", "CPU % expert/servo/follower/video", "load",
    "UTC",
]  # fmt: skip
PHASE_HEADER = ["setting", "phase", "s", "US p50/p95/max ms", "US fps", "US gap ms",
                "POV p50/p95/max ms", "POV fps", "POV gap ms"]  # fmt: skip


def _phase_track(t: dict) -> list[str]:
    return [
        f"{_v(t.get('age_p50_ms'))} / {_v(t.get('age_p95_ms'))} / {_v(t.get('age_max_ms'))}",
        _v(t.get("fps"), "{:.1f}"),
        _v(t.get("gap_max_ms")),
    ]


def phase_rows(s: dict) -> list[list[str]]:
    """The recovery table's rows of one run: before, during, after the loss window."""
    out = []
    ph = s.get("phases") or {}
    for phase in ("before", "during", "after, first 5 s", "after, rest"):
        us = (ph.get("us") or {}).get(phase) or {}
        pov = (ph.get("pov") or {}).get(phase) or {}
        if us or pov:
            out.append([s["label"], phase, _v((us or pov).get("s")), *_phase_track(us),
                        *_phase_track(pov)])  # fmt: skip
    return out


def markdown(rows: list[list[str]], recovery: list[list[str]]) -> str:
    parts = [
        "## Video over the link: glass to glass (`humantele bench video link`)",
        machine_line() + " `load` is the machine's 1-minute load average when the row started "
        "(2 cores: above 2, every process waits for CPU; a row taken at a load above 1.5 is "
        "provisional). Figures are one run each; a row where a daemon did not start shows `-`.",
        "The whole demo session per row (both daemons, the 1 kHz servo in its own process, "
        "the follower's video process at nice +5, US 20 fps and POV 25 fps sim sources), "
        "`--seconds` long including the follower's calibration. Latency is capture to "
        "decoded at the expert (the counter drawn at capture read back from the decoded "
        "frame and matched to its capture time through the clock sync; display not "
        "included). fps: mean frames per second decoded at the expert; gap: the longest "
        "time between two decoded frames (a freeze). Counter unread: decoded frames whose "
        "counter did not read (of those decoded). kbit/s: each encoder's target at the end "
        "(REMB within `[follower.video] us_bitrate`/`pov_bitrate`). POV level: the "
        "degradation level at the end (0 full; 1 half rate; 2 half size, half rate; 3 half "
        "size, quarter rate). "
        f"Targets: US p95 <= {TARGETS['us_p95_ms']:.0f} ms, POV p95 <= "
        f"{TARGETS['pov_p95_ms']:.0f} ms, US >= {TARGETS['us_fps']:.0f} fps, POV >= "
        f"{TARGETS['pov_fps']:.0f} fps at the default settings on loopback.",
        markdown_table(HEADER, rows),
    ]
    if recovery:
        parts += [
            "Recovery (`--loss-window A,B`): the loss only from A to B s after the video "
            f"started to flow; before: from {WARMUP_S:g} s after the first frame to A; after: "
            "the first 5 s after B (the recovery), then the rest of the run (where other work "
            "on the machine also shows). From the expert's recording of every frame it decoded.",
            markdown_table(PHASE_HEADER, recovery),
        ]
    return "\n\n".join(parts)


def run_link(args: argparse.Namespace) -> int:
    from humantele.transport.turnserver import TurnServer

    runs = MATRIX if args.matrix else [None]
    summaries = []
    rows = {r[0]: r for r in section_rows(SECTION, len(HEADER), BENCHMARKS_MD)}
    recovery = {(r[0], r[1]): r for r in section_rows(SECTION, len(PHASE_HEADER), BENCHMARKS_MD)}
    for extra in runs:
        a = args
        if extra is not None:
            p = argparse.ArgumentParser()
            add_link_arguments(p)
            a = p.parse_args(["--seconds", str(args.seconds), *extra])
        if (a.turn or a.loss or a.delay_ms) and not TurnServer.available():
            print("bench video link: turnserver (coturn) is not installed", file=sys.stderr)
            return 2
        s = asyncio.run(measure(a))
        summaries.append(s)
        r = row(s)
        rows[r[0]] = r
        new_phases = phase_rows(s)
        if new_phases:  # this setting's phases replace all of its earlier ones
            recovery = {k: v for k, v in recovery.items() if k[0] != r[0]}
        for pr in new_phases:
            recovery[(pr[0], pr[1])] = pr
        if not args.json:
            print(" | ".join(r), flush=True)
            for pr in new_phases:
                print("  " + " | ".join(pr[1:]), flush=True)
        if not args.no_write:
            md = markdown(list(rows.values()), list(recovery.values()))
            write_section(SECTION, md, BENCHMARKS_MD)
    print(json.dumps({"part": "link", "runs": summaries}))
    return 0

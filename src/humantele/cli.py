"""The ``humantele`` command. Each subcommand lives in its own module exposing
``add_arguments(parser)`` and ``run(args) -> int``; this file only maps names to modules.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from humantele.config import ConfigError

# name -> (module, one-line help). Modules are imported only when their command runs.
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("humantele.demo", "run a whole session on simulated devices over loopback WebRTC"),
    "expert": ("humantele.expert.cli", "run the expert daemon (haptic device, servo loop)"),
    "follower": ("humantele.follower.cli", "run the follower daemon (tracking, force, video)"),
    "signal": ("humantele.signaling.server", "run the signaling server"),
    "analyze": ("humantele.analysis.cli", "the study's analysis of recorded sessions"),
    "study": (
        "humantele.study.cli",
        "the study in simulation: whole recorded sessions per network condition, the table and "
        "charts (alignment against delay, video freezes against loss)",
    ),
    "export": (
        "humantele.export.cli",
        "recorded video per scan: MP4 (H.264) for raters, MCAP for Foxglove",
    ),
    "devices": (
        "humantele.devices.check",
        "list devices and read a few samples from each; save the hl2ss calibration; record "
        "the follower's devices to replay them",
    ),
}

# name -> (module, one-line help) for `humantele bench NAME`.
BENCHES: dict[str, tuple[str, str]] = {
    "haptics": ("humantele.bench.haptics", "penetration methods: cost against accuracy"),
    "loop": ("humantele.bench.loop", "servo loop rate and jitter on the sim device"),
    "session": ("humantele.bench.session", "pose stream over loopback WebRTC"),
    "tracking": ("humantele.bench.tracking", "IR marker tracking: time against pose error"),
    "hl2ss": (
        "humantele.bench.hl2ss",
        "hl2ss AHAT settings over a Wi-Fi link: rate, frame age, accuracy, CPU",
    ),
    "sensing": ("humantele.bench.sensing", "follower loop latency with sensing: thread/process"),
    "keepup": ("humantele.bench.keepup", "hl2ss frames the follower's sensing measures, loaded"),
    "analysis": ("humantele.bench.analysis", "analyze a 10-min session; recording CPU cost"),
    "video": ("humantele.bench.video", "video: sources (render cost) and link (glass to glass)"),
    "igtl": ("humantele.bench.igtl", "OpenIGTLink: added follower CPU, pose/image latency"),
    "archive": ("humantele.bench.archive", "DICOM to Orthanc: capture to archived, a scan, outage"),
    "registration": (
        "humantele.bench.registration",
        "headset registration: time (targets) against accuracy",
    ),
}


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="humantele", description="humantele: remote ultrasound by human teleoperation."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    # Only the chosen command's module is imported (and adds its own arguments).
    chosen = argv[0] if argv else None
    bench_chosen = argv[1] if len(argv) > 1 and chosen == "bench" else None
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module_name)
        if name == chosen:
            importlib.import_module(module_name).add_arguments(p)
    bench = sub.add_parser("bench", help="benchmarks; write docs/benchmarks.md")
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCH")
    for name, (module_name, help_text) in BENCHES.items():
        p = bench_sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module_name)
        if name == bench_chosen:
            importlib.import_module(module_name).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    module_name = getattr(args, "_module", None)
    if module_name is None:
        parser.print_help()
        return 2
    try:
        return int(importlib.import_module(module_name).run(args) or 0)
    except ConfigError as exc:
        print(f"humantele: configuration error:\n{exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130

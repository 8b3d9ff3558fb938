"""``humantele expert``: the expert daemon's command line (the daemon itself is
:mod:`humantele.expert.daemon`)."""

from __future__ import annotations

import argparse

from humantele.cliargs import port
from humantele.config import load_config, validate_config
from humantele.daemons.common import (
    add_daemon_arguments,
    daemon_overrides,
    run_daemon_process,
    setup_logging,
)
from humantele.expert.config import ExpertConfig, servo_config_for
from humantele.expert.daemon import ExpertDaemon
from humantele.haptics.servo_config import ServoConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_daemon_arguments(parser, "TOML file; [expert] and [servo] sections are used")
    parser.add_argument("--console-port", type=port, help="console page port (0 picks one)")
    parser.add_argument("--no-console", action="store_true", help="do not serve the console page")
    parser.add_argument(
        "--us-pixel-spacing-mm", type=float, nargs=2, metavar=("ROW", "COL"),
        help="mm per pixel of the received ultrasound image, for the console's calipers",
    )  # fmt: skip
    parser.add_argument(
        "--us-depth-origin-row", type=float, metavar="ROW",
        help="row (px) of depth 0 of the received ultrasound image, for the console's depth scale",
    )  # fmt: skip
    parser.add_argument(
        "--igtl-port",
        type=port,
        help="serve OpenIGTLink on this port (0 picks one; 18944 Slicer's)",
    )


def configs_from_args(args: argparse.Namespace) -> tuple[ExpertConfig, ServoConfig]:
    config = load_config(ExpertConfig, args.config, "expert" if args.config else None)
    servo = load_config(ServoConfig, args.config, "servo" if args.config else None)
    data = config.model_dump()
    if getattr(args, "console_port", None) is not None:
        data["console"]["port"] = args.console_port
    if getattr(args, "no_console", False):
        data["console"]["enabled"] = False
    if getattr(args, "us_pixel_spacing_mm", None):
        data["console"]["us_pixel_spacing_mm"] = tuple(args.us_pixel_spacing_mm)
    if getattr(args, "us_depth_origin_row", None) is not None:
        data["console"]["us_depth_origin_row"] = args.us_depth_origin_row
    if getattr(args, "igtl_port", None) is not None:
        data["igtl"].update(enabled=True, port=args.igtl_port)
    daemon_overrides(args, data)
    config = validate_config(ExpertConfig, data, "command line")
    return config, servo_config_for(config.mapping, servo)


def run(args: argparse.Namespace) -> int:
    setup_logging("expert", args.log_level)
    config, servo = configs_from_args(args)
    return run_daemon_process(ExpertDaemon(config, servo, args.stats_file), args.duration)

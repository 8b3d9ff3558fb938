"""``humantele follower``: the follower daemon's command line (the daemon itself is
:mod:`humantele.follower.daemon`)."""

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
from humantele.follower.config import FollowerConfig
from humantele.follower.daemon import FollowerDaemon
from humantele.follower.sensing import SensingConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_daemon_arguments(parser, "TOML file; the [follower] section is used")
    parser.add_argument("--state-dir", help="where the calibration is saved")
    parser.add_argument("--feed-port", type=port, help="renderer feed port (0 picks one)")
    parser.add_argument(
        "--igtl-port",
        type=port,
        help="serve OpenIGTLink on this port (0 picks one; 18944 Slicer's)",
    )
    parser.add_argument("--recalibrate", action="store_true", help="ignore a saved calibration")


def config_from_args(args: argparse.Namespace) -> FollowerConfig:
    config = load_config(FollowerConfig, args.config, "follower" if args.config else None)
    data = config.model_dump()
    daemon_overrides(args, data)
    if args.state_dir:
        data["state_dir"] = args.state_dir
    if args.feed_port is not None:
        data["feed"]["port"] = args.feed_port
    if getattr(args, "igtl_port", None) is not None:
        data["igtl"].update(enabled=True, port=args.igtl_port)
    return validate_config(FollowerConfig, data, "command line")


def sensing_config_from_args(args: argparse.Namespace) -> SensingConfig:
    """The ``[sensing]`` section of the follower's file (the sensing pipeline's own)."""
    return load_config(SensingConfig, args.config, "sensing" if args.config else None)


def run(args: argparse.Namespace) -> int:
    setup_logging("follower", args.log_level)
    config = config_from_args(args)
    daemon = FollowerDaemon(config, args.stats_file, sensing_config_from_args(args))
    if args.recalibrate:
        daemon.cal.forget()
    return run_daemon_process(daemon, args.duration)

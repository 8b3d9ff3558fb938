"""The systemd units in examples/ match the commands and the servo's configuration."""

from __future__ import annotations

import configparser
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

from humantele.cli import build_parser
from humantele.cliargs import FATAL_EXIT_CODES
from humantele.haptics.servo_config import ServoConfig
from humantele.tracking.sphere import CACHE_DIR_ENV
from humantele.transport.config import LinkConfig

UNITS = Path(__file__).resolve().parents[1] / "examples" / "systemd"
NAMES = ("humantele-signal", "humantele-expert", "humantele-follower")


def _unit(name: str) -> configparser.ConfigParser:
    cp = configparser.ConfigParser(interpolation=None, strict=True)
    cp.optionxform = str  # keys are case-sensitive
    cp.read(UNITS / f"{name}.service")
    return cp


@pytest.mark.parametrize("name", NAMES)
def test_unit_restarts_on_failure_but_not_on_fatal_codes(name):
    svc = _unit(name)["Service"]
    assert svc["Restart"] == "on-failure"
    assert {int(c) for c in svc["RestartPreventExitStatus"].split()} == set(FATAL_EXIT_CODES)
    assert "HUMANTELE_TOKEN" not in svc["ExecStart"]  # the token is never on a command line
    argv = shlex.split(svc["ExecStart"])[1:]
    assert argv[0] == name.removeprefix("humantele-")
    args = build_parser(argv).parse_args(argv)  # the options exist and their values parse
    assert args.config.startswith("/etc/humantele/")


def test_follower_unit_keeps_the_tracker_s_tables_where_it_may_write():
    svc = _unit("humantele-follower")["Service"]
    assert svc["ProtectSystem"] == "strict"  # so nothing outside the unit's own directories
    cache = dict(shlex.split(e)[0].split("=", 1) for e in [svc["Environment"]])
    assert cache[CACHE_DIR_ENV] == f"/var/cache/{svc['CacheDirectory']}"


def test_expert_unit_allows_the_servo_s_realtime_priority():
    svc = _unit("humantele-expert")["Service"]
    assert int(svc["LimitRTPRIO"]) >= ServoConfig().realtime_priority
    assert svc["KillMode"] == "mixed"  # SIGTERM to the daemon; it stops the servo itself
    assert svc["LimitRTTIME"]


@pytest.mark.parametrize("name", ["humantele-expert", "humantele-follower"])
def test_daemon_units_allow_the_event_loop_s_realtime_priority(name):
    svc = _unit(name)["Service"]
    assert int(svc["LimitRTPRIO"]) >= LinkConfig().realtime_priority > 0
    assert LinkConfig().realtime_priority < ServoConfig().realtime_priority  # the servo first
    assert svc["LimitRTTIME"]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze")
def test_units_verify():
    r = subprocess.run(
        ["systemd-analyze", "verify", "--man=no", *[str(UNITS / f"{n}.service") for n in NAMES]],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    problems = [ln for ln in r.stderr.splitlines() if "is not executable" not in ln and ln]
    assert problems == [], r.stderr


@pytest.mark.parametrize("name", NAMES)
def test_units_raise_the_descriptor_limit_for_the_connection_caps(name):
    """The pages' and the signaling server's caps are sized from RLIMIT_NOFILE: systemd's
    default soft limit (1024) is what let a flood exhaust the expert (issue 20)."""
    from humantele.expert.console import ConsoleConfig
    from humantele.follower.feed import FeedConfig
    from humantele.signaling.server import SignalConfig
    from humantele.web.connguard import FD_RESERVE

    limit = int(_unit(name)["Service"]["LimitNOFILE"])
    assert limit >= 8192
    wanted = {
        "humantele-signal": SignalConfig().max_connections,
        "humantele-expert": ConsoleConfig().max_connections + ConsoleConfig().max_clients,
        "humantele-follower": FeedConfig().max_connections + FeedConfig().max_clients,
    }[name]
    assert 2 * (wanted + FD_RESERVE) < limit  # the caps as configured, with room to spare

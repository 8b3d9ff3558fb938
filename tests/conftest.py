"""Shared by every test folder: this folder is on ``sys.path`` (pytest's prepend import mode
puts a conftest's folder there), so tests import the daemons' doubles from
``daemon_doubles``.

The suite runs on two pytest-xdist workers (``-n auto --dist loadgroup``, pyproject.toml, and
:func:`pytest_xdist_auto_num_workers`; the fast lane on three). Tests
that run real processes for seconds (the daemons, the servo, the demo, coturn, a browser) must
not all run at once on a 2-core machine, or they starve each other's real-time loops: the
ones on the host's network go to one worker, one after the other (the xdist group
``processes``); the browser scenarios, each in a network namespace of its own (so no port of
theirs meets the host's), to another (``processes-netns``); the other tests run beside them.
Such a test is marked ``slow`` or uses a fixture that starts those processes; it is also
marked ``e2e``, so ``python -m pytest -q -m "not e2e"`` is the fast lane for everyday work
(the README's command runs everything).

Whatever a test process started is killed with its process group when pytest ends, also on
Ctrl-C, SIGTERM or SIGHUP (``procgroups``): stopping pytest leaves no daemon or Chromium.
In the xdist controller (whose children are the workers) each worker does it for itself.
"""

import os
import sys
from pathlib import Path

import pytest
from hypothesis import settings

from procgroups import pytest_configure, pytest_unconfigure  # noqa: F401 - the hooks

# Where PYTHONDONTWRITEBYTECODE is set (this machine's images set it), pytest rewrote every
# test module's asserts again on each run, in each worker (2.1 of the 3.6 s a worker spends
# collecting), and each daemon and child the tests start compiled every module it imported
# again (0.1-0.2 CPU-s a process, some 300 processes in a whole run). Their bytecode is cached
# in pytest's cache folder instead, never beside the sources (the variable's intent): here
# through sys.pycache_prefix, in the processes the tests start (xdist's workers included)
# through the environment they inherit.
if sys.dont_write_bytecode:
    sys.pycache_prefix = str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "pycache")
    sys.dont_write_bytecode = False
    os.environ["PYTHONPYCACHEPREFIX"] = sys.pycache_prefix
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

FAST_LANE_WORKERS = 3  # -m "not e2e": its tests wait on timers and sockets a third of the time
SUITE_WORKERS = 2  # with the e2e tests: their real-time loops need the two cores

PROCESS_FIXTURES = {"session", "demo_run", "browser_scenario"}

# Property tests check behaviour, not speed: no per-example deadline (hypothesis's 200 ms
# default failed a wire round trip once on a busy machine).
settings.register_profile("suite", deadline=None)
settings.load_profile("suite")


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(items):
    for item in items:
        if item.get_closest_marker("slow") or PROCESS_FIXTURES & set(item.fixturenames):
            netns = "browser_scenario" in item.fixturenames
            item.add_marker(pytest.mark.xdist_group("processes-netns" if netns else "processes"))
            item.add_marker(pytest.mark.e2e)  # the fast lane, -m "not e2e", leaves them out


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto`` (pyproject.toml's addopts): three workers for the fast lane, two for a run
    with the e2e tests (their slow ones run one at a time in two xdist groups, beside the
    rest). An explicit ``-n N`` wins."""
    fast = "not e2e" in (config.getoption("markexpr") or "")
    return FAST_LANE_WORKERS if fast else SUITE_WORKERS

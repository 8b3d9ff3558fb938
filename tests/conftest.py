"""Shared by every test folder: this folder is on ``sys.path`` (pytest's prepend import mode
puts a conftest's folder there), so tests import the daemons' doubles from
``daemon_doubles``.

The suite runs on two pytest-xdist workers (``-n auto --dist loadgroup``, pyproject.toml, and
:func:`pytest_xdist_auto_num_workers`; the fast lane on three). Tests
that run real processes for seconds (the daemons, the servo, the demo, coturn, a browser) must
not all run at once on a 2-core machine, or they starve each other's real-time loops. They run
in two xdist groups (lanes), each on one worker, one test after the other: ``sessions``, every
module with a test that runs a whole session (both daemons or a demo, on the host or beside a
Chromium in a browser scenario), and ``processes``, the other tests that run processes for
seconds; the rest of the tests run beside them, and after. Two whole sessions never run at once
(a Chromium beside a demo and another demo put the load at 19 on 2 cores), nor two Chromiums:
the processes lane runs its browser scenarios first, while the sessions lane runs the host's
sessions, whose browser scenarios come last (``tests/session_slot.py``, whose slot also holds
sessions one at a time under other scheduling: ``-n 3``, ``--dist load``). A browser scenario
runs in a network namespace of its own, so no port of its meets the host's.
Such a test is marked ``slow`` or uses a fixture that starts those processes; it is also
marked ``e2e``, so ``python -m pytest -q -m "not e2e"`` is the fast lane for everyday work
(the README's command runs everything). A shorter test that starts any process (a child, the
CLI, a Python interpreter, a compiler) is marked ``e2e`` itself, saying which. The fast lane
draws fewer property-test examples (``fuzz_examples``), and a module whose tests share a
module-scoped fixture runs on one worker (its own xdist group), which builds it once.

Tests that need a Debian package beyond Python (Chromium, coturn, OpenIGTLink's library, ...)
skip without it, their reason naming it (``system_packages``); the run's last line counts them
by package and gives the one command that installs them all (:func:`pytest_sessionfinish`).

Whatever a test process started is killed with its process group when pytest ends, also on
Ctrl-C, SIGTERM or SIGHUP (``procgroups``): stopping pytest leaves no daemon or Chromium.
In the xdist controller (whose children are the workers) each worker does it for itself.
"""

import contextlib
import functools
import json
import os
import signal
import sys
from pathlib import Path

# Where PYTHONDONTWRITEBYTECODE is set (this machine's images set it), pytest rewrote every
# test module's asserts again on each run, in each worker (2.1 of the 3.6 s a worker spends
# collecting), and each daemon and child the tests start compiled every module it imported
# again (0.1-0.2 CPU-s a process, some 300 processes in a whole run). Their bytecode is cached
# in pytest's cache folder instead, never beside the sources (the variable's intent): here
# through sys.pycache_prefix, in the processes the tests start (xdist's workers included)
# through the environment they inherit. Set before anything else is imported: pytest rewrites
# the asserts of every module of a plugin's distribution (hypothesis's ~90), which were
# rewritten again in each process when imported before this (1-1.5 CPU-s a worker).
if sys.dont_write_bytecode:
    sys.pycache_prefix = str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "pycache")
    sys.dont_write_bytecode = False
    os.environ["PYTHONPYCACHEPREFIX"] = sys.pycache_prefix
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

# OpenBLAS (numpy's and scipy's, each its own copy) starts a thread per core and, after each
# call it splits over them, keeps those threads spinning for a while: on 2 cores with two
# xdist workers that was a third to a half of a numerical test's CPU (the PSF calibration test
# 7.5 -> 4.7 CPU-s) and it took the other worker's core. The tests' matrices are small: one
# thread, read by each copy when it loads (so before numpy is imported; the processes the tests
# start inherit it). OpenCV's own pool likewise (its default a thread per core): 10-20 % more
# CPU for the same wall time on the tracker's frames, which the sensing and video processes
# already run on one thread (cv2.setNumThreads(1)); the tests that run the tracker in the
# worker now do too. An explicit setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OPENCV_FOR_THREADS_NUM", "1")
# Tables the processes compute once and keep (the tracker's sphere tables: half a sensing
# process's start) in pytest's cache folder, not the user's (an explicit setting wins).
os.environ.setdefault(
    "HUMANTELE_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "humantele")
)

import pytest  # noqa: E402 - after the bytecode cache is set
from hypothesis import settings  # noqa: E402

from cpu_durations import (  # noqa: F401 - the hooks of --cpu-durations=N
    pytest_addoption,
    pytest_runtest_call,
    pytest_runtest_logreport,
    pytest_runtest_makereport,
    pytest_runtest_setup,
    pytest_runtest_teardown,
    pytest_terminal_summary,
)
from fuzz_examples import set_fast_lane
from procgroups import pytest_configure as procgroups_configure
from procgroups import pytest_unconfigure  # noqa: F401 - the hook
from session_slot import order_the_lanes, scaled, whole_session_slot, why_xdist_cannot_group
from system_packages import system_packages_line

sys.path.append(str(Path(__file__).resolve().parent / "browser"))  # netns, for browser_scenario
from netns import SCENARIOS, ScenarioError, run_scenario, skip_reason  # noqa: E402

# -m "not e2e": its tests wait on timers and sockets half of the time (one after the other: 141
# s, 64 CPU-s). Three workers, four and five, alternated on one host (2026-11-29, c14e073):
# 60.7, 61.5, 62.0 s; 57.9, 56.8, 56.8, 56.8 s; 57.6, 57.6 s.
FAST_LANE_WORKERS = 4
SUITE_WORKERS = 2  # with the e2e tests: their real-time loops need the two cores

PROCESS_FIXTURES = {"session", "demo_run", "browser_scenario"}
SESSION_FIXTURES = {"session", "demo_run", "installed_demo"}  # each runs a whole session
SESSION_MODULES: set[str] = set()  # this run's, before -m or -k leave tests out: the lane's

# Property tests check behaviour, not speed: no per-example deadline (hypothesis's 200 ms
# default failed a wire round trip once on a busy machine). The whole suite draws each test's
# full count of examples; the fast lane a tenth (``fast``, and tests/fuzz_examples.py for the
# tests that set their own count): its budget is 60 s on 2 cores (issue 33).
settings.register_profile("suite", deadline=None)
settings.register_profile("fast", deadline=None, max_examples=10)
settings.load_profile("suite")


def pytest_configure(config: pytest.Config) -> None:
    """The fast lane (``-m "not e2e"``) draws fewer examples (tests/fuzz_examples.py; an
    explicit ``--hypothesis-profile`` wins), then procgroups' hook. xdist's workers with
    ``--dist loadgroup`` (the lanes) and a pytest it cannot group: a clear stop."""
    grouped = getattr(config.option, "dist", None) == "loadgroup"
    if (
        grouped
        and getattr(config.option, "numprocesses", None)
        and (why := why_xdist_cannot_group())
    ):
        raise pytest.UsageError(why)
    fast = _fast_lane(config)
    share = set_fast_lane(fast)
    if not config.getoption("hypothesis_profile", None):
        settings.load_profile("fast" if share < 1.0 else "suite")
    procgroups_configure(config)


def _fast_lane(config: pytest.Config) -> bool:
    return "not e2e" in (config.getoption("markexpr") or "")


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(items):
    SESSION_MODULES.clear()
    SESSION_MODULES.update(_module(item) for item in items if _holds_the_slot(item))
    browser = {_module(item) for item in items if "browser_scenario" in item.fixturenames}
    for item in items:
        in_sessions = _module(item) in SESSION_MODULES
        if in_sessions:
            item.add_marker(pytest.mark.xdist_group("sessions"))  # the module whole: its fixtures
        if item.get_closest_marker("slow") or PROCESS_FIXTURES & set(item.fixturenames):
            if not in_sessions:
                item.add_marker(pytest.mark.xdist_group("processes"))
            item.add_marker(pytest.mark.e2e)  # the fast lane, -m "not e2e", leaves them out
        elif (
            not in_sessions and not item.get_closest_marker("e2e") and _uses_a_module_fixture(item)
        ):
            item.add_marker(pytest.mark.xdist_group(f"module {_module(item)}"))
    # One Chromium at a time: the processes lane runs its browser scenarios first, while the
    # sessions lane runs the host's sessions; the sessions lane its browser sessions last.
    order_the_lanes(items, lambda item: _module(item) in browser)


def _module(item: pytest.Item) -> str:
    return item.nodeid.split("::")[0]


def _holds_the_slot(item: pytest.Item) -> bool:
    """Whether ``item`` runs a whole session (it takes the slot, tests/session_slot.py): marked
    ``whole_session``, using a fixture that runs one (SESSION_FIXTURES), or a browser scenario
    that starts the daemons or a demo (:func:`starts_a_session`; its module names the
    scenario)."""
    if item.get_closest_marker("whole_session"):
        return True
    fixtures = set(item.fixturenames)
    if SESSION_FIXTURES & fixtures:
        return True
    return "browser_scenario" in fixtures and _scenarios_start_a_session(str(item.fspath))


@functools.cache
def _scenarios_start_a_session(module: str) -> bool:
    """Whether a scenario the test module names (``browser_scenario("<name>"``) starts one."""
    text = Path(module).read_text()
    names = {part.split('"')[0] for part in text.split('browser_scenario("')[1:]}
    return any((SCENARIOS / f"{n}.py").exists() and starts_a_session(n) for n in names)


def _uses_a_module_fixture(item: pytest.Item) -> bool:
    """Whether ``item`` shares a module-scoped fixture (a recording, encoded video, a fitted
    calibration) with its module's other tests. Those tests go to one xdist worker (one group
    each module), which builds the fixture once: spread over the workers, each built it again
    (the device recording's three times, 9 CPU-s a time on a loaded machine)."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return False
    defs = info.name2fixturedefs
    return any(d.scope == "module" for name in item.fixturenames for d in defs.get(name, ()))


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@pytest.fixture(autouse=True)
def _stop_signals_as_they_were():
    """A daemon or demo run in the test's process ignores SIGINT and SIGTERM once it has
    stopped (``runtime.process.ignore_stop_signals``, right for a process that then exits):
    the worker would then ignore a CI runner's SIGTERM, procgroups' net with it, and pass the
    ignoring on to every process it starts. Each test leaves them as it found them."""
    before = {s: signal.getsignal(s) for s in STOP_SIGNALS}
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    yield
    for s, handler in before.items():
        if handler is not None and signal.getsignal(s) != handler:
            signal.signal(s, handler)
    signal.pthread_sigmask(signal.SIG_SETMASK, mask)


@pytest.fixture(autouse=True)
def _whole_session_slot(request: pytest.FixtureRequest):
    """Tests marked ``whole_session`` (a demo or both daemons, started by the test itself) hold
    the suite's one slot for a whole session (tests/session_slot.py); the ``session`` and
    ``demo_run`` fixtures and the browser scenarios that start daemons take it themselves."""
    if request.node.get_closest_marker("whole_session") is None:
        yield
        return
    with whole_session_slot():
        yield


def starts_a_session(name: str) -> bool:
    """Whether ``browser/scenarios/<name>.py`` starts the daemons or a demo (its
    ``ctx.daemons()`` or ``ctx.demo(...)``): a whole session beside its Chromium, one at a time
    across the lanes."""
    text = (SCENARIOS / f"{name}.py").read_text()
    return "ctx.daemons(" in text or "ctx.demo(" in text


@pytest.fixture(scope="session")
def browser_scenario(tmp_path_factory):
    """``browser_scenario(name, **args) -> ScenarioResult``: run ``browser/scenarios/<name>.py``
    (tests/browser/netns.py), once per session and arguments: the tests of every module that
    checks the same scenario share its run (a whole session shared, issue 33), and its failure
    (each test that asks for it fails with it). Its tests are in one xdist group
    (``sessions`` or ``processes``, :func:`pytest_collection_modifyitems`), so one worker runs
    it."""
    reason = skip_reason()
    if reason:
        pytest.skip(f"browser tests: {reason}")
    runs: dict[str, object] = {}

    def run(name: str, timeout_s: float = 300.0, **args):
        key = json.dumps([name, args], sort_keys=True)
        if key not in runs:
            slot = whole_session_slot() if starts_a_session(name) else contextlib.nullcontext()
            with slot:  # its deadline from when it starts, scaled to the machine's load then
                try:
                    out = tmp_path_factory.mktemp(name)
                    runs[key] = run_scenario(name, out, args, scaled(timeout_s))
                except ScenarioError as exc:
                    runs[key] = exc
        got = runs[key]
        if isinstance(got, ScenarioError):
            raise ScenarioError(str(got))
        return got

    return run


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto`` (pyproject.toml's addopts): four workers for the fast lane, two for a run
    with the e2e tests (their slow ones run one at a time in two xdist groups, beside
    the rest). An explicit ``-n N`` wins."""
    return FAST_LANE_WORKERS if _fast_lane(config) else SUITE_WORKERS


@pytest.hookimpl(wrapper=True, tryfirst=True)  # around the terminal's, so after its last line
def pytest_sessionfinish(session: pytest.Session):
    result = yield
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None and not hasattr(session.config, "workerinput"):
        line = system_packages_line(reporter.stats.get("skipped", []))
        if line:
            reporter.write_line(line, yellow=True, bold=True)
    return result

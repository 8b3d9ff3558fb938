"""The suite's one slot for a whole session (tests/session_slot.py): held across processes,
reentrant in one, the deadlines' scale, and xdist taking the lanes' groups."""

import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import pytest

import session_slot
from session_slot import (
    order_the_lanes,
    scaled,
    time_scale,
    whole_session_slot,
    why_xdist_cannot_group,
)

HOLDER = (
    "import sys; sys.path.insert(0, sys.argv[1]); from pathlib import Path;"
    " from session_slot import whole_session_slot\n"
    "with whole_session_slot(Path(sys.argv[2])):\n"
    "    print('held', flush=True); sys.stdin.readline()\n"
)


@pytest.mark.e2e  # runs a Python process holding the slot (the fast lane leaves it out)
def test_another_process_waits_for_the_slot_until_its_holder_lets_it_go(
    tmp_path: Path, monkeypatch
):
    monkeypatch.setenv("HUMANTELE_TEST_ONE_SESSION", "1")  # crowded, whatever the load
    lock = tmp_path / "slot.lock"
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(Path(__file__).parent), str(lock)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        got = threading.Event()

        def take():
            with whole_session_slot(lock):
                got.set()

        t = threading.Thread(target=take, daemon=True)
        t.start()
        t.join(0.5)
        assert not got.is_set()  # held by the other process: never taken meanwhile
        holder.stdin.write("go\n")
        holder.stdin.flush()
        assert got.wait(60)
    finally:
        holder.kill()
        holder.wait()


def test_the_slot_is_reentrant_in_a_process_and_freed_at_the_outermost_exit(
    tmp_path: Path, monkeypatch
):
    monkeypatch.setenv("HUMANTELE_TEST_ONE_SESSION", "1")
    lock = tmp_path / "slot.lock"
    with whole_session_slot(lock), whole_session_slot(lock):  # would block if not reentrant
        assert session_slot._held["depth"] == 2
    assert session_slot._held["depth"] == 0 and session_slot._held["fd"] == -1


def test_deadlines_scale_with_the_environment_or_the_load(monkeypatch):
    monkeypatch.setenv("HUMANTELE_TEST_TIME_SCALE", "2.5")
    assert time_scale() == 2.5 and scaled(30) == 75
    monkeypatch.delenv("HUMANTELE_TEST_TIME_SCALE")
    monkeypatch.setattr(session_slot.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(session_slot.os, "getloadavg", lambda: (19.0, 10.0, 5.0))
    assert time_scale() == session_slot.MAX_SCALE  # load 9.5 a core: the cap
    monkeypatch.setattr(session_slot.os, "getloadavg", lambda: (3.0, 1.0, 1.0))
    assert time_scale() == 1.5
    monkeypatch.setattr(session_slot.os, "getloadavg", lambda: (0.2, 1.0, 1.0))
    assert time_scale() == 1.0


def test_the_slot_is_taken_whatever_the_load_unless_turned_off(tmp_path: Path, monkeypatch):
    lock = tmp_path / "slot.lock"
    monkeypatch.delenv("HUMANTELE_TEST_ONE_SESSION", raising=False)
    for load in (0.1, 2.0, 6.0):  # quiet or crowded: one session at a time
        monkeypatch.setattr(session_slot.os, "getloadavg", lambda load=load: (load, 1.0, 1.0))
        with whole_session_slot(lock):
            assert session_slot._held["fd"] >= 0, load
        assert session_slot._held["fd"] == -1
    monkeypatch.setenv("HUMANTELE_TEST_ONE_SESSION", "0")  # side by side, asked for
    with whole_session_slot(lock):
        assert session_slot._held["fd"] == -1


GROUPED = """import os, pytest
@pytest.mark.xdist_group("lane")
@pytest.mark.parametrize("i", range(4))
def test_where(i):
    print("worker", os.environ["PYTEST_XDIST_WORKER"])
"""


def test_xdist_runs_a_group_on_one_worker_with_the_installed_pytest(tmp_path: Path):
    """The lanes are xdist groups: with the pytest and pytest-xdist installed, two modules'
    tests of one group run on one worker (with pytest 9.2 and xdist 3.8 they do not)."""
    for name in ("test_a.py", "test_b.py"):
        (tmp_path / name).write_text(GROUPED)
    (tmp_path / "pytest.ini").write_text("[pytest]\n")
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-v", "-p",
         "no:cacheprovider"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
        env={k: v for k, v in os.environ.items() if k != "PYTEST_ADDOPTS"},
    )  # fmt: skip
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    workers = re.findall(
        r"^\[(gw\d)\] .* PASSED test_[ab]\.py::test_where\[\d\]@lane", run.stdout, re.M
    )
    assert len(workers) == 8 and len(set(workers)) == 1, run.stdout[-2000:]


def test_a_pytest_xdist_cannot_group_is_named_before_the_suite_runs(monkeypatch):
    import xdist

    monkeypatch.setattr(pytest, "__version__", "9.2.0")
    monkeypatch.setattr(xdist, "__version__", "3.8.0")
    assert "pytest-dev/pytest-xdist#1386" in why_xdist_cannot_group()
    monkeypatch.setattr(xdist, "__version__", "3.9.0")  # a fixed xdist
    assert why_xdist_cannot_group() is None
    monkeypatch.setattr(pytest, "__version__", "9.1.1")
    monkeypatch.setattr(xdist, "__version__", "3.8.0")
    assert why_xdist_cannot_group() is None


def test_every_module_with_a_whole_session_runs_in_the_sessions_lane(request):
    """The lanes of this run's tests (tests/conftest.py): a module with a test that runs a
    whole session is in ``sessions`` whole (its fixtures are built once, by one worker); no
    test is in two lanes; a browser scenario with no session in ``processes``; each lane's
    browser scenarios first (processes) or last (sessions)."""
    conftest = request.config.pluginmanager.get_plugin(str(Path(__file__).with_name("conftest.py")))
    items = request.session.items
    lanes = {}
    for item in items:
        groups = [m.args[0] for m in item.iter_markers("xdist_group")]
        assert len(groups) <= 1, (item.nodeid, groups)
        lanes[item.nodeid] = groups[0] if groups else None
    module = conftest._module
    with_sessions = conftest.SESSION_MODULES  # from every test collected, before -m or -k
    assert {module(i) for i in items if conftest._holds_the_slot(i)} <= with_sessions
    for item in items:
        assert (lanes[item.nodeid] == "sessions") == (module(item) in with_sessions), item.nodeid
    expected = {  # (those in this run)
        "tests/test_wheel_install.py::test_installed_wheel_runs_the_demo_outside_the_checkout":
            "sessions",  # its installed demo holds the slot
        "tests/session/test_demo_command.py::test_demo_json_and_ctrl_c_leave_no_process":
            "sessions",  # demo_run: console_video's demo
        "tests/browser/test_console_load.py::test_console_tells_the_truth_when_the_daemon_is_slow":
            "processes",  # no daemons: a console alone
    }  # fmt: skip
    for nodeid, lane in expected.items():
        got = [lanes[n] for n in lanes if n.split("@")[0] == nodeid]
        assert got in ([], [lane]), nodeid
    browser = {module(i) for i in items if "browser_scenario" in i.fixturenames}
    for lane, first in session_slot.BROWSER_FIRST.items():
        kinds = [module(i) in browser for i in items if lanes[i.nodeid] == lane]
        assert kinds == sorted(kinds, reverse=first), lane  # the browser's in one run, at its end


def test_a_lane_s_browser_scenarios_first_or_last_each_kind_in_order():
    net = lambda name: name.startswith("b")  # noqa: E731 - "b...": a browser scenario's
    items = [
        _Item("x1"), _Item("b1", "processes"), _Item("p1", "processes"), _Item("s1", "sessions"),
        _Item("bs1", "sessions"), _Item("x2"), _Item("p2", "processes"), _Item("b2", "processes"),
        _Item("s2", "sessions"), _Item("bs2", "sessions"),
    ]  # fmt: skip
    order_the_lanes(items, lambda item: net(item.nodeid))
    assert [i.nodeid for i in items] == [
        "x1", "b1", "b2", "s1", "s2", "x2", "p1", "p2", "bs1", "bs2",
    ]  # fmt: skip


class _Item:
    """What order_the_lanes reads of a pytest item: its node id and its xdist group."""

    def __init__(self, nodeid: str, lane: str | None = None) -> None:
        self.nodeid, self.lane = nodeid, lane

    def get_closest_marker(self, name: str):
        return (
            pytest.mark.xdist_group(self.lane).mark if self.lane and name == "xdist_group" else None
        )

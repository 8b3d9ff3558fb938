"""The suite's one slot for a whole session (tests/session_slot.py): held across processes,
reentrant in one, the deadlines' scale, the lanes' order, and xdist taking the lanes' groups."""

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


class _Item:
    """What order_the_lanes reads of a pytest item: its node id and its xdist group."""

    def __init__(self, nodeid: str, lane: str | None = None, session: bool = False) -> None:
        self.nodeid, self.lane, self.session = nodeid, lane, session

    def get_closest_marker(self, name: str):
        return (
            pytest.mark.xdist_group(self.lane).mark if self.lane and name == "xdist_group" else None
        )


def test_each_lane_meets_the_other_s_sessions_with_its_lighter_tests():
    """The browser lane's session modules first, the host's last; a module's tests together
    and in order (a module counts as a session one if any of its tests is); every test of no
    lane stays where it was."""
    net, host = "processes-netns", "processes"
    items = [
        _Item("a.py::x"), _Item("b.py::1", host, True), _Item("b.py::2", host),
        _Item("c.py::1", net), _Item("d.py::1", host), _Item("e.py::x"),
        _Item("f.py::1", net, True), _Item("f.py::2", net), _Item("g.py::1", host),
        _Item("h.py::x"),
    ]  # fmt: skip
    order_the_lanes(items, lambda item: item.session)
    assert [i.nodeid for i in items] == [
        "a.py::x", "d.py::1", "g.py::1", "f.py::1", "b.py::1", "e.py::x",
        "f.py::2", "c.py::1", "b.py::2", "h.py::x",
    ]  # fmt: skip
    lane = lambda name: [i.nodeid for i in items if i.lane == name]  # noqa: E731
    assert lane(net) == ["f.py::1", "f.py::2", "c.py::1"]
    assert lane(host) == ["d.py::1", "g.py::1", "b.py::1", "b.py::2"]


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

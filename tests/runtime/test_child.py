"""The one child-process helper (humantele.runtime.child): the restart back-off on a fake
clock, and a spawned child's name, signals and priority as the system has them."""

import contextlib
import os
import signal
import time
from pathlib import Path

import pytest

from humantele.demo_status import children_status, children_summary
from humantele.runtime.child import Priority, Restarter, child_priority, spawn, stop_process


async def test_restarts_back_off_one_at_a_time_and_say_why():
    started, fail = [], [True]

    async def start_new():
        started.append(1)
        if fail[0]:
            raise RuntimeError("device busy")

    r = Restarter("thing", start_new, first_s=1.0, max_s=4.0)
    r.check(0.0, False, -9)  # noticed: due in 1 s
    assert r.state(0.0, False) == "down: thing process exited with code -9, restart in 1 s"
    r.check(0.5, False, -9)
    assert not started and not r.restarting
    r.check(1.0, False, -9)
    assert r.restarting and r.state(1.0, False) == "restarting (1)"
    r.check(1.1, False, -9)  # one at a time
    await r.task
    assert started == [1] and r.down == "device busy" and r.restarts == 0
    r.check(2.0, False, None)  # the next try waits twice as long, then 4 s (the cap), ...
    assert r.due_at == 4.0
    r.check(4.0, False, None)
    await r.task
    r.check(5.0, False, None)
    assert r.due_at == 9.0
    fail[0] = False
    r.check(9.0, False, None)
    await r.task
    assert r.restarts == 1 and r.down == "" and r.exit_codes == [-9]
    assert r.state(9.5, True) == "running"
    await r.close()
    r.check(20.0, False, -9)  # closed: never again
    assert not r.restarting and r.state(20.0, False) == "stopped"


async def test_a_bounded_restarter_gives_up_and_says_so():
    async def start_new():
        raise RuntimeError("no")

    r = Restarter("x", start_new, first_s=0.1, max_restarts=1)
    r.check(0.0, False, 1)
    r.check(1.0, False, 1)
    await r.task
    r.check(2.0, False, 1)
    assert r.gave_up and r.state(2.0, False) == "failed: no"


def _sleeper(path: str, nice: int) -> None:
    from humantele.runtime.child import set_priority

    set_priority(Priority(nice=nice))
    Path(path).write_text("up")
    while True:
        time.sleep(0.05)


@pytest.mark.e2e
@pytest.mark.slow
def test_a_spawned_child_is_named_ignores_group_signals_and_runs_at_its_priority(tmp_path):
    flag = tmp_path / "up"
    base = os.getpriority(os.PRIO_PROCESS, 0)
    proc = spawn(_sleeper, (str(flag), 3), name="humantele-test")
    try:
        end = time.monotonic() + 120
        while not flag.exists():
            assert time.monotonic() < end and proc.is_alive()
            time.sleep(0.05)
        assert Path(f"/proc/{proc.pid}/comm").read_text().strip() == "humantele-test"
        assert child_priority(proc.pid) == ("other", base + 3)
        for sig in (signal.SIGINT, signal.SIGTERM):  # Ctrl-C, systemd: the daemon stops it
            os.kill(proc.pid, sig)
        proc.join(0.5)
        assert proc.is_alive()
    finally:
        code = stop_process(proc, timeout_s=0.5)
    assert code == -signal.SIGKILL and not proc.is_alive()


def test_the_demo_shows_a_child_that_is_not_running_and_sums_the_gaps():
    f = {
        "video": {"process": {"state": "down: video process exited with code -9, restart in 1 s",
                              "restarts": 0}},
        "sensing_state": "restarting (1)", "measurement_age_s": 4.2, "sensing_restarts": 1,
        "measurement_gaps": 1, "measurement_gap_s": 4.2, "measurement_gap_max_s": 4.2,
    }  # fmt: skip
    line = children_status(f)
    assert "video DOWN (video process exited with code -9" in line
    assert "sensing restarting (1), no measurements 4 s" in line
    assert children_status({"video": {"process": {"state": "running"}},
                             "sensing_state": "running"}) == ""  # fmt: skip
    s = children_summary({"servo_restarts": 2, "servo_state": "running"}, f)
    assert s["servo"] == {"restarts": 2, "state": "running"}
    assert s["sensing"]["restarts"] == 1 and s["sensing"]["measurement_gap_s"] == 4.2
    assert s["video"]["state"].startswith("down")
    assert children_summary({}, {})["video"] is None


def test_measurement_gaps_are_counted_after_the_first_measurement():
    from humantele.follower.sensing_worker import MeasurementGaps

    now = [0.0]
    g = MeasurementGaps(clock=lambda: now[0])
    for i in range(10):
        g.measured(1.0 + i / 45)
    g.measured(13.0)  # a restarted sensing process measures again 12 s later
    now[0] = 13.1
    s = g.stats()
    assert s["measurement_gaps"] == 1 and 11.7 < s["measurement_gap_s"] < 11.9
    now[0] = 16.0  # down again, still going on: counted as it goes
    s = g.stats()
    assert s["measurement_gaps"] == 2 and abs(s["measurement_gap_max_s"] - 11.8) < 0.1
    assert abs(s["measurement_gap_s"] - (11.8 + 3.0)) < 0.1 and s["measurement_age_s"] == 3.0


@pytest.mark.e2e
@pytest.mark.slow
def test_a_ctrl_c_while_the_child_imports_its_target_does_not_kill_it(tmp_path, monkeypatch):
    """The child imports its target's modules only once it ignores the group's signals (a
    restarted sensing process died of a Ctrl-C in its imports, with a traceback)."""
    flags = tmp_path / "flags"
    flags.mkdir()
    monkeypatch.setenv("HUMANTELE_TEST_FLAGS", str(flags))
    (flags / "go").write_text("1")  # the test's own import passes straight through
    import slow_import_child

    run = slow_import_child.run
    (flags / "go").unlink()
    (flags / "importing").unlink()
    proc = spawn(run, (), name="humantele-test")
    try:
        end = time.monotonic() + 120
        while not (flags / "importing").exists():
            assert time.monotonic() < end and proc.is_alive(), proc.exitcode
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGINT)  # mid-import
        time.sleep(0.2)
        (flags / "go").write_text("1")
        proc.join(60)
        assert proc.exitcode == 0 and (flags / "ran").exists()
    finally:
        stop_process(proc, timeout_s=0.5)


@pytest.mark.e2e  # spawns a child process (the fast lane leaves it out)
def test_a_ctrl_c_during_the_interpreters_start_up_does_not_kill_the_child(tmp_path):
    """A terminal's Ctrl-C reaches the whole group, also a child the daemon is (re)starting
    while its interpreter starts, before any of our code could ignore it: the servo restarted
    as Ctrl-C came died in Python's site import ("Fatal Python error: init_import_site").
    spawn starts the child with the group's signals blocked; it ignores them, then unblocks."""
    flag = tmp_path / "up"
    proc = spawn(_sleeper, (str(flag), 0), name="humantele-test")
    try:
        end = time.monotonic() + 120
        while not flag.exists():  # SIGINT and SIGTERM, from fork to the target's first line
            assert time.monotonic() < end and proc.is_alive(), proc.exitcode
            for sig in (signal.SIGINT, signal.SIGTERM):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, sig)
            time.sleep(0.002)
        assert proc.is_alive()
    finally:
        code = stop_process(proc, timeout_s=0.5)
    assert code == -signal.SIGKILL  # it ran on until stopped


REFUSED_FIFO = """
import os
from humantele.runtime.child import Priority, set_priority

def refuse(*a):
    raise PermissionError(1, "Operation not permitted")

os.sched_setscheduler = refuse
base = os.getpriority(os.PRIO_PROCESS, 0)
print(set_priority(Priority(fifo=5, nice=2)))
print(os.sched_getscheduler(0) == os.SCHED_OTHER, os.getpriority(os.PRIO_PROCESS, 0) - base)
"""


@pytest.mark.e2e  # spawns a child process (the fast lane leaves it out)
def test_a_refused_real_time_policy_falls_back_to_the_nice_and_says_so():
    """Without the privilege for SCHED_FIFO (no root, no rtprio limit) a child that asked for
    it still runs below the daemon at its nice, and the answer says what was refused."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", REFUSED_FIFO], capture_output=True, text=True,
                         check=True).stdout.splitlines()  # fmt: skip
    assert out[0].startswith("fifo 5 refused: ") and out[0].endswith("; nice 2")
    assert out[1] == "True 2"


LEFT_RUNNING = """
import sys, time
from humantele.runtime.child import spawn

def forever():
    while True:
        time.sleep(1)

if __name__ == "__main__":
    proc = spawn(forever, (), name="humantele-test")
    time.sleep(2.0)  # started; the owner exits without stopping it (an error path)
    print(proc.pid, flush=True)
"""


@pytest.mark.e2e  # spawns a child process (the fast lane leaves it out)
def test_a_child_its_owner_did_not_stop_is_killed_at_exit(tmp_path):
    """A daemon that leaves by an error path without stopping its child still exits: the
    child ignores SIGTERM, and multiprocessing's exit handler (terminate, then join) would
    wait for it forever."""
    import subprocess
    import sys

    script = tmp_path / "owner.py"
    script.write_text(LEFT_RUNNING)
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                       timeout=120)  # fmt: skip
    assert r.returncode == 0, r.stderr
    child = int(r.stdout.split()[0])
    assert not Path(f"/proc/{child}").exists() or "Z" in Path(f"/proc/{child}/stat").read_text()

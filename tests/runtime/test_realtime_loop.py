"""The daemons' event-loop thread at SCHED_FIFO: what it asks for, what its children get, and
a refusal that leaves the daemon running at normal priority."""

import json
import os
import subprocess
import sys
import threading

import pytest

from humantele.runtime import process
from humantele.runtime.process import realtime_loop_thread
from sched_privilege import fifo_allowed


def _in_a_thread(fn):
    out = {}

    def run():
        try:
            out["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            out["error"] = exc

    t = threading.Thread(target=run)
    t.start()
    t.join()
    if "error" in out:
        raise out["error"]
    return out["value"]


def test_the_loop_thread_runs_fifo_and_the_threads_it_starts_do_not():
    def body():
        said = realtime_loop_thread(7)
        if said.startswith("refused"):
            return said, None, None
        mine = (os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK, os.sched_getparam(0))
        child = _in_a_thread(lambda: os.sched_getscheduler(0))
        return said, mine, child

    said, mine, child = _in_a_thread(body)  # a thread of its own: pytest's is left alone
    if said.startswith("refused"):
        pytest.skip(f"no privilege for SCHED_FIFO here ({said})")
    assert said == "fifo 7"
    assert mine[0] == os.SCHED_FIFO and mine[1].sched_priority == 7
    assert child == os.SCHED_OTHER  # born normal (the daemon lifts them: lift_threads)


def test_priority_0_is_off_and_a_refusal_is_reported(monkeypatch):
    assert realtime_loop_thread(0) == "off"

    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(process.os, "sched_setscheduler", refuse)
    assert realtime_loop_thread(10).startswith("refused: ")


LIFT = """
import json, os, threading
from humantele.runtime.child import set_thread_nice
from humantele.runtime.process import lift_threads

go, tids = threading.Event(), {}

def worker(name, lower):
    tids[name] = threading.get_native_id()
    set_thread_nice(lower)
    go.wait()

threads = [threading.Thread(target=worker, args=a) for a in (("plain", 0), ("lowered", 3))]
for t in threads:
    t.start()
while len(tids) < 2:
    pass
first, again = lift_threads(1), lift_threads(1)
RESET = os.SCHED_RESET_ON_FORK
state = {n: [os.sched_getscheduler(t) & ~RESET, os.sched_getparam(t).sched_priority,
             bool(os.sched_getscheduler(t) & RESET)] for n, t in tids.items()}
state["main"] = [os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, False]
go.set()
for t in threads:
    t.join()
print(json.dumps({"first": first, "again": again, "state": state, "off": lift_threads(0)}))
"""


@pytest.mark.e2e  # runs a Python process (the fast lane leaves it out)
def test_the_daemon_s_other_threads_are_lifted_just_above_normal_processes():
    """``lift_threads``: the threads at the normal policy go to SCHED_FIFO 1 (once each);
    the calling thread and a thread lowered on purpose stay where they are."""
    if not fifo_allowed():
        pytest.skip("no privilege for SCHED_FIFO here")
    out = subprocess.run([sys.executable, "-c", LIFT], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)
    assert r["state"]["plain"] == [os.SCHED_FIFO, 1, True]  # its own threads born normal
    assert r["state"]["lowered"] == [os.SCHED_OTHER, 0, False]  # the IGTL render pool's kind
    assert r["state"]["main"] == [os.SCHED_OTHER, 0, False]  # the caller (the loop) untouched
    assert (r["first"], r["again"], r["off"]) == (1, 0, 0)


LIFTER = """
import json, os, threading, time
from humantele.runtime.process import ThreadLifter

go, tids = threading.Event(), {}

def worker():
    tids["worker"] = threading.get_native_id()
    go.wait()

t = threading.Thread(target=worker)
t.start()
while not tids:
    time.sleep(0.001)
lifter = ThreadLifter(1, every_s=0.05)
lifter.start()
deadline = time.monotonic() + 30
while lifter.lifted < 1 and time.monotonic() < deadline:
    time.sleep(0.01)
tids["lifter"] = lifter._thread.native_id
state = {n: os.sched_getscheduler(x) & ~os.SCHED_RESET_ON_FORK for n, x in tids.items()}
state["main"] = os.sched_getscheduler(0)
lifter.stop()
go.set()
t.join()
print(json.dumps({"lifted": lifter.lifted, "state": state, "alive": lifter._thread.is_alive()}))
"""


@pytest.mark.e2e  # runs a Python process (the fast lane leaves it out)
def test_the_lifter_lifts_new_threads_off_the_loop():
    """:class:`ThreadLifter` lifts, on its own thread, a thread started before it; the loop's
    thread (here the main one) and the lifter stay normal; ``stop`` ends it."""
    from humantele.runtime.process import ThreadLifter

    idle = ThreadLifter(0)  # no priority: no thread
    idle.start()
    assert idle._thread is None
    if not fifo_allowed():
        pytest.skip("no privilege for SCHED_FIFO here")
    out = subprocess.run([sys.executable, "-c", LIFTER], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)
    assert r["lifted"] == 1 and not r["alive"]
    assert r["state"] == {"worker": os.SCHED_FIFO, "lifter": os.SCHED_OTHER,
                          "main": os.SCHED_OTHER}  # fmt: skip


def test_the_threads_sit_below_the_sensing_and_none_without_a_realtime_loop():
    from humantele.follower.config import FollowerConfig
    from humantele.runtime.process import thread_priority_for
    from humantele.transport import LinkConfig

    loop = LinkConfig().realtime_priority
    assert 0 < thread_priority_for(loop) < FollowerConfig().sensing_priority.fifo < loop
    assert thread_priority_for(0) == thread_priority_for(1) == 0

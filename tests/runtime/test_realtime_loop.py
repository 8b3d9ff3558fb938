"""The daemons' event-loop thread at SCHED_FIFO: what it asks for, what its children get, and
a refusal that leaves the daemon running at normal priority."""

import os
import threading

import pytest

from humantele.runtime import process
from humantele.runtime.process import realtime_loop_thread


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
    assert child == os.SCHED_OTHER  # aiortc's encoder/decoder threads stay normal


def test_priority_0_is_off_and_a_refusal_is_reported(monkeypatch):
    assert realtime_loop_thread(0) == "off"

    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(process.os, "sched_setscheduler", refuse)
    assert realtime_loop_thread(10).startswith("refused: ")

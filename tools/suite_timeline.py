"""Where the suite's time goes, lane by lane: every test's start and end on its xdist worker,
and every wait for the whole-session slot (tests/session_slot.py), one JSON line each.

    PYTHONPATH=tools python -m pytest -q -p suite_timeline        # writes $TIMELINE_LOG
    python tools/suite_timeline.py timeline.jsonl [--over S]       # the lanes, tests over S s

As a pytest plugin (``-p suite_timeline``, with ``tools`` on ``PYTHONPATH``) it appends to
``$TIMELINE_LOG`` (default ``timeline.jsonl`` in the working directory); run as a script it
prints each worker's busy time, each lane's span (the ``sessions`` and ``processes`` xdist
groups), the tests over ``--over`` seconds, and the waits for the slot over 0.3 s.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import types
from pathlib import Path

import pytest

WORKER = os.environ.get("PYTEST_XDIST_WORKER", "main")


def _write(**row: object) -> None:
    with open(os.environ.get("TIMELINE_LOG", "timeline.jsonl"), "a") as f:
        f.write(json.dumps({"w": WORKER, **row}) + "\n")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    t0 = time.time()
    yield
    _write(kind="test", id=item.nodeid, t0=t0, t1=time.time())


def pytest_configure(config: pytest.Config) -> None:
    """Time each take of the slot: session_slot's ``flock`` wrapped (tests/ is on sys.path
    once the suite's conftest has loaded)."""
    try:
        import session_slot
    except ImportError:
        return
    real = session_slot.fcntl

    def flock(fd: int, op: int) -> None:
        t0 = time.time()
        real.flock(fd, op)
        if op == real.LOCK_EX:
            _write(kind="slot", t0=t0, t1=time.time())

    session_slot.fcntl = types.SimpleNamespace(
        flock=flock, LOCK_EX=real.LOCK_EX, LOCK_UN=real.LOCK_UN
    )


def report(path: Path, over_s: float) -> None:
    rows = [json.loads(line) for line in path.read_text().splitlines() if line]
    tests = [r for r in rows if r["kind"] == "test"]
    t0 = min(r["t0"] for r in rows)
    print(f"span {max(r['t1'] for r in tests) - t0:.1f} s")
    for w in sorted({r["w"] for r in tests}):
        mine = sorted((r for r in tests if r["w"] == w), key=lambda r: r["t0"])
        busy = sum(r["t1"] - r["t0"] for r in mine)
        print(f"{w}: {len(mine)} tests, busy {busy:.0f} s, last end {mine[-1]['t1'] - t0:.1f} s")
        for r in mine:
            if r["t1"] - r["t0"] > over_s:
                print(f"  {r['t0'] - t0:7.1f} {r['t1'] - r['t0']:6.1f}  {r['id'][:110]}")
    for lane in ("sessions", "processes"):
        mine = [r for r in tests if r["id"].endswith(f"@{lane}")]
        if mine:
            start, end = min(r["t0"] for r in mine) - t0, max(r["t1"] for r in mine) - t0
            print(f"lane {lane}: {start:.1f} to {end:.1f} s")
    waits = [r for r in rows if r["kind"] == "slot" and r["t1"] - r["t0"] > 0.3]
    print("slot waits over 0.3 s:", [(r["w"], round(r["t0"] - t0), round(r["t1"] - r["t0"], 1))
                                     for r in waits] or "none")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("--over", type=float, default=4.0, help="list tests over S s (4)")
    args = parser.parse_args()
    report(args.log, args.over)


if __name__ == "__main__":
    main()

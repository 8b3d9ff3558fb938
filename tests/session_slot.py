"""One whole session at a time across the suite's xdist workers, and deadlines that scale with
the machine.

The suite runs every test that runs a whole session in one lane, one after the other
(tests/conftest.py, the xdist group ``sessions``). Two whole sessions at once (a browser
scenario's Chromium beside a demo, and another demo) put the load at 19 on 2 cores and the
pages' first loads past 30 s (issue 34). :func:`whole_session_slot` holds them one at a time
however the tests are scheduled (``-n 3``, ``--dist load``): a lock on a file (``flock``, so it
holds across the workers' processes and is freed when a process dies) taken by every test
that runs a whole session. It is reentrant in a process (a test using two such fixtures takes
it once).

:func:`time_scale` is the factor a scenario's deadlines are multiplied by: the environment's
``HUMANTELE_TEST_TIME_SCALE`` if set, else the machine's load per core (the 1-minute load
average over the cores), between 1 and 4. Deadlines only bound a failure: a passing test
waits for its event, not for the deadline.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

LOCK_FILE = Path(__file__).resolve().parents[1] / ".pytest_cache" / "whole_session.lock"
MAX_SCALE = 4.0
# One whole session at a time, whatever the load ($HUMANTELE_TEST_ONE_SESSION=0: side by side).
# The two lanes' sessions side by side cost more than they saved: on a quiet 2-core machine
# (2026-11-28, fresh clones) the whole suite took 521 s and 833 CPU-s with them side by side
# until the load reached 2.5 a core, 465-494 s and 646-686 CPU-s one at a time (the spinning
# servos, the sensing and Chromium of two sessions took each other's cores), and side by side
# failed two timing-bound scenarios on a host that steals CPU.

_guard = threading.Lock()
_held = {"depth": 0, "fd": -1}


@contextlib.contextmanager
def whole_session_slot(lock_file: Path = LOCK_FILE) -> Iterator[None]:
    """Hold the suite's one slot for a whole session (blocks until the other lane's ends)."""
    with _guard:
        if _held["depth"] == 0 and _crowded():
            lock_file.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(lock_file, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX)
            except BaseException:
                os.close(fd)
                raise
            _held["fd"] = fd
        _held["depth"] += 1
    try:
        yield
    finally:
        with _guard:
            _held["depth"] -= 1
            if _held["depth"] == 0 and _held["fd"] >= 0:
                os.close(_held["fd"])  # closing the last descriptor frees the flock
                _held["fd"] = -1


def _crowded() -> bool:
    """Whether a whole session waits for the other lane's: yes unless
    ``$HUMANTELE_TEST_ONE_SESSION`` is ``0`` (see LOCK_FILE's comment)."""
    return os.environ.get("HUMANTELE_TEST_ONE_SESSION", "1") != "0"


def time_scale() -> float:
    """The factor for a scenario's deadlines now: ``$HUMANTELE_TEST_TIME_SCALE``, or the
    1-minute load per core, within [1, 4]."""
    given = os.environ.get("HUMANTELE_TEST_TIME_SCALE")
    if given:
        return max(1.0, float(given))
    try:
        load = os.getloadavg()[0] / (os.cpu_count() or 1)
    except OSError:
        return 1.0
    return max(1.0, min(MAX_SCALE, load))


def scaled(seconds: float) -> float:
    """``seconds`` times :func:`time_scale`."""
    return seconds * time_scale()


# The lanes' browser scenarios: first in the processes lane, last in the sessions lane, so that
# one lane's Chromium runs beside the other lane's host tests, never beside another Chromium.
# Two at once (three lanes, 2026-11-29 02:58 UTC: the replayed clinic's session beside
# headset_feed's and headset_registration's pages) took the replayed clinic from 49 s to 121 s
# and Chromium's GPU processes from 66 to 117 CPU-s.
BROWSER_FIRST = {"processes": True, "sessions": False}


def order_the_lanes(items: list, in_a_browser: Callable[[Any], bool]) -> None:
    """Reorder each lane's tests in ``items`` (pytest items, in place): those ``in_a_browser``
    first or last (BROWSER_FIRST), each kind in its order; every test of no lane where it was."""
    for lane, first in BROWSER_FIRST.items():
        at = [i for i, item in enumerate(items) if _lane(item) == lane]
        late = [in_a_browser(items[i]) != first for i in at]
        order = sorted(range(len(at)), key=late.__getitem__)  # stable: each kind in order
        for i, item in zip(at, [items[at[k]] for k in order], strict=True):
            items[i] = item


def _lane(item: Any) -> str | None:
    """The item's xdist group (tests/conftest.py: ``sessions``, ``processes``, ...)."""
    marker = item.get_closest_marker("xdist_group")
    return marker.args[0] if marker is not None and marker.args else None


def why_xdist_cannot_group() -> str | None:
    """Why pytest-xdist's ``--dist loadgroup`` would run the lanes' tests on any worker with
    the installed pytest, or None. pytest-xdist 3.8 and before mark a grouped test by
    rewriting ``item._nodeid``, which pytest 9.2 no longer reads (pytest-dev/pytest-xdist#1386):
    no group is then taken, nothing says so, and the real-time process tests run on both
    workers beside each other (in a fresh venv the whole suite took 620 s against 433 s)."""
    import xdist
    from packaging.version import Version

    if Version(pytest.__version__) >= Version("9.2.0.dev0") and Version(
        xdist.__version__
    ) <= Version("3.8.0"):
        return (
            f"pytest {pytest.__version__} with pytest-xdist {xdist.__version__} ignores the"
            " suite's xdist groups (pytest-dev/pytest-xdist#1386): pip install -e '.[test]'"
            " installs a pytest it can group"
        )
    return None

"""The stats file a daemon shares with the demo: written off the event loop, newest wins,
the last stats on disk when the daemon ends."""

import json
import threading

import pytest

from humantele.runtime import stats as stats_module
from humantele.runtime.stats import StatsFile


def test_close_leaves_the_last_stats_on_disk(tmp_path):
    path = tmp_path / "s.json"
    out = StatsFile(path)
    for i in range(50):
        out.write({"i": i})
    out.close({"i": "final"})
    assert json.loads(path.read_text()) == {"i": "final"}
    out.write({"i": "after close"})  # ignored: the daemon has ended
    assert json.loads(path.read_text()) == {"i": "final"}


def test_pending_stats_are_written_by_close_without_final(tmp_path):
    path = tmp_path / "s.json"
    out = StatsFile(path)
    out.write({"i": 1})
    out.write({"i": 2})
    out.close()
    assert json.loads(path.read_text()) == {"i": 2}


def test_write_never_waits_for_the_disk_and_newest_wins(tmp_path, monkeypatch):
    entered, release = threading.Event(), threading.Event()
    real_replace = stats_module._replace

    def slow_replace(path, text):
        entered.set()
        assert release.wait(10.0)
        real_replace(path, text)

    monkeypatch.setattr(stats_module, "_replace", slow_replace)
    path = tmp_path / "s.json"
    out = StatsFile(path)
    out.write({"i": 1})
    assert entered.wait(10.0)  # the writer thread is stuck on the disk...
    out.write({"i": 2})  # ...and these return at once
    out.write({"i": 3})
    assert out.superseded == 1 and not path.exists()
    release.set()
    out.close()
    assert json.loads(path.read_text()) == {"i": 3}


def test_an_unwritable_path_is_counted_not_raised(tmp_path):
    out = StatsFile(tmp_path / "missing-dir" / "s.json")
    out.write({"i": 1})
    out.close()
    assert out.errors == 1


def test_no_path_writes_nothing():
    out = StatsFile(None)
    out.write({"i": 1})
    out.close({"i": 2})
    assert out._thread is None


@pytest.mark.e2e  # runs a busy Python process (the fast lane leaves it out)
def test_cpu_percent_is_over_the_process_s_own_life():
    """A process that has burnt CPU before it was noticed is not a 13968 % process."""
    import subprocess
    import sys

    from humantele.runtime.stats import process_cpu_percent

    busy = subprocess.Popen(
        [sys.executable, "-c", "import time\nt = time.process_time()\n"
         "while time.process_time() - t < 0.3: pass\nimport sys; sys.stdin.read()"],
        stdin=subprocess.PIPE,
    )  # fmt: skip
    try:
        while (process_cpu_percent(busy.pid) or 0.0) == 0.0:
            pass
        pct = process_cpu_percent(busy.pid)
        assert 0.0 < pct <= 120.0  # one thread: at most a core (plus clock-tick rounding)
    finally:
        busy.stdin.close()
        busy.wait()
    assert process_cpu_percent(busy.pid) is None  # gone
    assert process_cpu_percent(None) is None

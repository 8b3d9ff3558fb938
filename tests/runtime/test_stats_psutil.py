"""Other processes' CPU use is read with psutil, not by parsing /proc by hand (issue 22
item 5), and agrees with what the process itself measures."""

from __future__ import annotations

import inspect
import os
import time

import humantele.runtime.stats as stats


def test_no_proc_parsing_left_in_the_stats_module():
    assert "/proc" not in inspect.getsource(stats)


def test_cpu_seconds_of_this_process_agree_with_its_own_clock():
    t = time.process_time()
    while time.process_time() - t < 0.2:  # burn a little
        pass
    mine, theirs = time.process_time(), stats.process_cpu_seconds(os.getpid())
    assert theirs is not None and abs(theirs - mine) < 0.1  # clock ticks of 10 ms
    assert stats.process_cpu_seconds(None) is None
    assert stats.process_cpu_seconds(2**22 + 12345) is None  # no such process

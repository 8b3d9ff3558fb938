"""What the loop counts say about its long periods (:mod:`humantele.haptics.loop_counts`), and
the servo's statistics written without a long tick of their own."""

import gc
import mmap
import resource

import numpy as np
import pytest

from humantele.haptics.loop_counts import LongPeriods, ThreadCounts
from humantele.haptics.renderer import ForceRenderer
from humantele.haptics.servo_child import PeriodTiming, SpinBudget, _stats_row
from humantele.haptics.servo_config import ServoConfig
from humantele.haptics.servo_layout import STAT_FIELDS


def test_each_long_period_is_put_down_to_the_work_the_wake_or_neither():
    c = LongPeriods(0.001)
    c.add(0.0010, 0.0002, 0.00003)  # on time: not counted
    c.add(0.0016, 0.0007, 0.0)  # the tick before worked 0.7 ms
    c.add(0.0030, 0.0001, 0.0020)  # the sleep woke 2 ms late
    c.add(0.0017, 0.0003, 0.0003)  # neither alone: lost the CPU, or both added up
    c.add(0.0014, 0.0009, 0.0)  # long work but no overrun
    assert (c.work, c.wake, c.other) == (1, 1, 1)
    assert c.work_max_s == pytest.approx(0.0009)


def test_thread_counts_count_page_faults_and_collections():
    counts = ThreadCounts()
    size = 4 << 20
    m = mmap.mmap(-1, size)
    if hasattr(mmap, "MADV_NOHUGEPAGE"):
        m.madvise(mmap.MADV_NOHUGEPAGE)  # one fault a 4 kB page, not one a 2 MB page
    for i in range(0, size, mmap.PAGESIZE):
        m[i] = 1  # first touch of each page
    gc.collect()
    c = counts.counts()
    counts.close()
    m.close()
    assert c["minor_faults"] + c["major_faults"] >= size // mmap.PAGESIZE // 2
    assert c["gc_collections"] >= 1
    assert set(c) >= {"involuntary_switches", "voluntary_switches"}
    gc.collect()
    assert counts.counts()["gc_collections"] == c["gc_collections"]  # closed: no longer counted


def _reference(periods_s, q):
    """The percentile as the full 1 us histogram gives it (the statistics before issue 34)."""
    us = np.minimum((np.asarray(periods_s) * 1e6).astype(int), PeriodTiming.BINS - 1)
    h = np.bincount(us, minlength=PeriodTiming.BINS)
    return int(np.searchsorted(np.cumsum(h), q * len(us))), h


def test_period_statistics_from_two_level_bins_equal_the_full_histogram():
    rng = np.random.default_rng(7)
    for _ in range(30):
        periods = rng.gamma(2.0, 0.0005, size=int(rng.integers(1, 3000)))
        timing = PeriodTiming(0.001)
        t = 0.0
        timing.add(t)
        for p in periods:
            t += p
            timing.add(t)
        for q in (0.0, 0.01, 0.5, 0.99, 1.0):
            idx, h = _reference(periods, q)
            want = min(max(idx + 0.5, timing.min_us), timing.max_us)
            assert timing.percentile(q) == pytest.approx(want)
        for s in (0.0015, 0.002, 0.00201, 0.0199, 0.02, 1.0):
            assert timing.count_over(s) == int(h[min(int(s * 1e6), PeriodTiming.BINS) :].sum())


def test_writing_the_statistics_touches_no_new_memory():
    """The statistics row, written 4 times a second from the loop's own tick, allocates nothing
    large: it used to sum a fresh 160 kB array twice (~90 page faults and up to ms a write)."""
    timing = PeriodTiming(0.001)
    t = 0.0
    for i in range(5000):
        timing.add(t)
        t += 0.001 + 1e-6 * (i % 50)
    r = ForceRenderer(ServoConfig())
    counts = ThreadCounts()
    spin = SpinBudget(200e-6)
    _stats_row(timing, r, True, None, None, counts, spin)  # warm up
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(50):
        row = _stats_row(timing, r, True, None, None, counts, spin)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    counts.close()
    assert len(row) == len(STAT_FIELDS)
    assert faults < 50, faults  # was ~4,600

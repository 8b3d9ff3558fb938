"""SortedWindow: the same percentiles as sorting the window, without sorting at report time."""

import math
import random

from hypothesis import given, settings
from hypothesis import strategies as st

from fuzz_examples import examples
from humantele.runtime.stats import SortedWindow, percentile_ms


@settings(max_examples=examples(60), deadline=None)
@given(
    values=st.lists(st.floats(0.0, 1.0, allow_nan=False), max_size=300),
    maxlen=st.integers(1, 50),
    q=st.sampled_from([0, 1, 50, 90, 99, 100]),
)
def test_percentiles_match_a_sort_of_the_last_maxlen_values(values, maxlen, q):
    w = SortedWindow(maxlen)
    for v in values:
        w.append(v)
    kept = values[-maxlen:]
    assert list(w) == kept and len(w) == len(kept)
    assert percentile_ms(w, q) == percentile_ms(kept, q)
    assert w.last(3) == kept[-3:]
    assert w.last(0) == []


def test_non_finite_values_are_ignored_and_long_windows_stay_exact():
    w = SortedWindow(20000)
    rng = random.Random(4)
    vals = [rng.random() for _ in range(25000)]
    for i, v in enumerate(vals):
        w.append(v)
        if i % 1000 == 0:
            w.append(math.nan)
            w.append(math.inf)
    assert len(w) == 20000
    assert percentile_ms(w, 99) == percentile_ms(vals[-20000:], 99)
    assert SortedWindow(5).percentile_ms(50) is None

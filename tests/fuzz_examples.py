"""How many examples a property test draws: its full count in the whole suite (the README's
``python -m pytest -q``), a tenth of it (at least 10) in the fast lane (``-m "not e2e"``).

``tests/conftest.py`` chooses the share in ``pytest_configure``, before any test module is
collected (in each xdist worker too), so a count written ``@settings(max_examples=examples(300))``
reads it when the module is imported; a test without its own count takes the hypothesis
profile's (``suite``: hypothesis's 100; ``fast``: 10). ``HUMANTELE_FUZZ_SHARE=1`` draws the full
counts in the fast lane too (or any other share, e.g. 0.5).
"""

from __future__ import annotations

import os

FAST_LANE_SHARE = 0.1
MIN_EXAMPLES = 10
_share = {"now": 1.0}


def set_fast_lane(fast: bool) -> float:
    """Choose the share for this run (``$HUMANTELE_FUZZ_SHARE`` wins); returns it."""
    given = os.environ.get("HUMANTELE_FUZZ_SHARE")
    share = float(given) if given else (FAST_LANE_SHARE if fast else 1.0)
    _share["now"] = min(1.0, max(0.0, share))
    return _share["now"]


def share() -> float:
    """The share of each test's full count drawn in this run (1.0 in the whole suite)."""
    return _share["now"]


def examples(full: int) -> int:
    """``full`` in the whole suite; in the fast lane its share, at least ``MIN_EXAMPLES``."""
    if _share["now"] >= 1.0:
        return full
    return min(full, max(MIN_EXAMPLES, round(full * _share["now"])))

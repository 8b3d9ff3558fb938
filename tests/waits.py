"""Waiting in a test for something to become true: polled, with a generous deadline, never a
fixed sleep (a test passes on a busy machine as on a quiet one). One helper for every test
folder (this folder is on ``sys.path``, tests/conftest.py), where nine modules had a copy.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

DEADLINE_S = 30.0  # generous: a loaded 2-core machine, never a figure a test relies on
POLL_S = 0.01


class NotInTime(AssertionError, TimeoutError):
    """Still not true at the deadline: a failed assertion, and a TimeoutError for the few tests
    that let a wait run out (``contextlib.suppress(TimeoutError)``)."""


async def until(
    cond: Callable[[], object],
    timeout: float = DEADLINE_S,
    *,
    what: str = "the condition",
    poll: float = POLL_S,
) -> None:
    """Wait on the event loop until ``cond()`` is true, polled every ``poll`` s; NotInTime naming
    ``what`` after ``timeout`` s (monotonic clock)."""
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise NotInTime(f"{what}: still not true after {timeout} s")
        await asyncio.sleep(poll)


def wait_for(
    cond: Callable[[], T],
    timeout: float = DEADLINE_S,
    *,
    what: str = "the condition",
    poll: float = POLL_S,
) -> T:
    """:func:`until` outside an event loop (blocking): ``cond()``'s first true value."""
    end = time.monotonic() + timeout
    while not (value := cond()):
        if time.monotonic() > end:
            raise NotInTime(f"{what}: still not true after {timeout} s")
        time.sleep(poll)
    return value

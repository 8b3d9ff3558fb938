"""tests/waits.py, the tests' one polling helper: it returns as soon as the condition holds, and
fails at the deadline with an error that is both a failed assertion and a TimeoutError."""

import asyncio
import contextlib
import time

import pytest

from waits import NotInTime, until, wait_for


async def test_until_returns_once_the_condition_holds_and_fails_at_the_deadline():
    flag = []
    asyncio.get_running_loop().call_later(0.05, flag.append, 1)
    await until(lambda: flag, 30.0)
    assert flag == [1]
    t0 = time.monotonic()
    with pytest.raises(AssertionError, match="the flag: still not true after 0.05 s"):
        await until(lambda: False, 0.05, what="the flag")
    assert time.monotonic() - t0 >= 0.05
    with contextlib.suppress(TimeoutError):  # a wait allowed to run out (test_turn_relay)
        await until(lambda: False, 0.01)


def test_wait_for_gives_the_first_true_value_or_not_in_time():
    values = iter([0, None, "found", "later"])
    assert wait_for(lambda: next(values), 30.0, poll=0.001) == "found"
    with pytest.raises(NotInTime) as err:
        wait_for(lambda: 0, 0.02)
    assert isinstance(err.value, TimeoutError) and isinstance(err.value, AssertionError)

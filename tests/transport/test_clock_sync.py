import random

import pytest

from humantele.transport.clocksync import ClockSync


class FakeTime:
    def __init__(self):
        self.t = 100.0


def _exchange(
    local: ClockSync,
    remote: ClockSync,
    now: FakeTime,
    d_out: float,
    d_back: float,
    offset: float,
    hold: float = 1e-4,
):
    """One ping/pong with one-way delays d_out/d_back; remote clock = local clock + offset."""
    ping = local.make_ping()
    now.t += d_out
    t1 = remote.clock()
    now.t += hold
    pong = remote.answer(ping, t1)
    now.t += d_back
    return local.on_pong(pong)


@pytest.mark.parametrize("offset", [0.0, 5.0, -1234.5678])
def test_recovers_a_known_offset_despite_jitter(offset):
    now = FakeTime()
    local = ClockSync(lambda: now.t)
    remote = ClockSync(lambda: now.t + offset)
    rng = random.Random(1)
    for _ in range(40):
        base = 0.002
        # queueing delays: mostly small, sometimes large and one-sided
        d_out = base + (rng.expovariate(1 / 0.003) if rng.random() < 0.3 else 0.0)
        d_back = base + (rng.expovariate(1 / 0.003) if rng.random() < 0.3 else 0.0)
        _exchange(local, remote, now, d_out, d_back, offset)
        now.t += 0.1
    assert local.offset == pytest.approx(offset, abs=2e-4)
    assert local.rtt == pytest.approx(0.004, abs=1e-3)
    # a message the remote stamped 3 ms ago (its clock) has age 3 ms here
    sent_remote = now.t + offset - 0.003
    assert local.age_of(sent_remote) == pytest.approx(0.003, abs=3e-4)


def test_asymmetric_delay_bias_is_half_the_asymmetry():
    now = FakeTime()
    local = ClockSync(lambda: now.t)
    remote = ClockSync(lambda: now.t + 2.0)
    _exchange(local, remote, now, d_out=0.010, d_back=0.002, offset=2.0)
    assert local.offset == pytest.approx(2.0 + 0.004, abs=1e-9)


def test_unknown_or_inconsistent_pongs_are_rejected_and_reset_forgets():
    now = FakeTime()
    local = ClockSync(lambda: now.t)
    remote = ClockSync(lambda: now.t)
    assert local.age_of(1.0) is None and not local.synced
    ping = local.make_ping()
    pong = remote.answer(ping, now.t)
    assert local.on_pong(pong) is not None
    assert local.on_pong(pong) is None  # duplicate
    forged = remote.answer(local.make_ping(), now.t).model_copy(update={"t0": 1.0})
    assert local.on_pong(forged) is None
    assert local.rejected == 2
    local.reset()
    assert local.offset is None

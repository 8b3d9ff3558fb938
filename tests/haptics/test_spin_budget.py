"""The servo's spin before each deadline follows what the sleep's overshoot needs
(:class:`humantele.haptics.servo_child.SpinBudget`)."""

import time

import numpy as np

from humantele.haptics.servo_child import SpinBudget


def test_spin_settles_at_the_overshoot_quantile_plus_the_margin():
    rng = np.random.default_rng(3)
    late = rng.gamma(4.0, 7e-6, size=60_000)  # ~28 us typical, a tail past 60 us
    b = SpinBudget(200e-6)
    assert b.spin_s == 200e-6  # starts as the fixed spin did
    for x in late:
        b.overshoot(float(x))
    q = float(np.quantile(late, 0.995))
    assert abs(b.quantile_s - q) < 8e-6, (b.quantile_s, q)
    assert abs(b.spin_s - (q + 30e-6)) < 8e-6
    # the ticks it would have kept on time: about as many as the quantile says
    assert np.mean(late[-20_000:] > b.spin_s) < 0.005


def test_spin_climbs_within_tens_of_ms_when_wakeups_get_later_and_stays_within_its_bounds():
    b = SpinBudget(200e-6)
    for _ in range(20_000):
        b.overshoot(10e-6)
    assert b.spin_s == b.quantile_s + 30e-6 < 60e-6
    for _ in range(25):  # 25 ticks: 25 ms at 1 kHz
        b.overshoot(150e-6)
    assert b.spin_s > 120e-6
    for _ in range(1000):
        b.overshoot(5e-3)  # a stalled machine: never more than spin_s
    assert b.spin_s == 200e-6
    fast = SpinBudget(200e-6, min_s=20e-6, margin_s=0.0)
    for _ in range(50_000):
        fast.overshoot(0.0)
    assert fast.spin_s == 20e-6  # never under min_s
    assert SpinBudget(0.0).spin_s == 0.0  # spin_s = 0: no spin at all
    none = SpinBudget(0.0)
    none.overshoot(1e-3)
    assert none.spin_s == 0.0


def test_wait_until_returns_at_the_deadline_and_learns_from_its_sleep():
    b = SpinBudget(200e-6)
    deadline = time.monotonic() + 0.005
    b.wait_until(deadline)
    assert time.monotonic() >= deadline
    assert b.quantile_s != 200e-6  # the sleep's lateness was taken in, up or down
    late = SpinBudget(200e-6)
    late.wait_until(time.monotonic() - 1.0)  # past: no sleep, nothing learnt
    assert late.quantile_s == 200e-6

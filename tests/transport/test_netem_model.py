"""The WAN emulator's link model (LinkModel) on a hand-driven clock: the jitter is a process in
time (mean hold near the delay, SD near the jitter, correlated over ``jitter_corr_s``), FIFO
order never reorders, and a rate-limited link drops what its queue cannot hold."""

import math
import random
import socket
import statistics
import time

import pytest

from humantele.transport.netem import LinkModel, NetemConfig, receive, timestamp_arrivals

RURAL = {"delay_s": 0.060, "jitter_s": 0.020}  # issue 31's rural link, one way


def _holds(cfg: NetemConfig, n: int, gap_s: float, seed: int = 3) -> list[tuple[float, float]]:
    """(arrival, due) of ``n`` datagrams of 1000 B arriving at random gaps of mean ``gap_s``."""
    model, arrivals = LinkModel(cfg, "up"), random.Random(seed)
    t, out = 0.0, []
    for _ in range(n):
        t += arrivals.expovariate(1.0 / gap_s)
        due = model.due(t, 1000)
        assert due is not None
        out.append((t, due))
    return out


def test_correlated_jitter_keeps_the_mean_hold_near_the_delay_in_fifo_order():
    # 30 s of a dense stream (1000 datagrams a second, as the two video tracks at 1.5 Mbit/s)
    got = _holds(NetemConfig(**RURAL), n=30_000, gap_s=0.001)
    dues = [d for _t, d in got]
    assert dues == sorted(dues)  # FIFO: no datagram leaves before one that arrived before it
    held = [d - t for t, d in got]
    # the queue's own FIFO adds about jitter^2 / corr = 8 ms; the independent draws added 30+
    assert 0.058 <= statistics.fmean(held) <= 0.072
    assert 0.016 <= statistics.pstdev(held) <= 0.023
    assert min(held) >= 0.0


def test_independent_draws_in_fifo_order_wait_for_the_running_maximum():
    # the old model (jitter_corr_s = 0): each datagram waits for the largest draw before it
    got = _holds(NetemConfig(**RURAL, jitter_corr_s=0.0), n=20_000, gap_s=0.001)
    held = [d - t for t, d in got]
    assert statistics.fmean(held) > 0.085
    correlated = _holds(NetemConfig(**RURAL), n=20_000, gap_s=0.001)
    assert statistics.fmean(d - t for t, d in correlated) < statistics.fmean(held) - 0.015


def _autocorrelation(xs: list[float], lag: int) -> float:
    m, v = statistics.fmean(xs), statistics.pvariance(xs)
    return sum((a - m) * (b - m) for a, b in zip(xs, xs[lag:], strict=False)) / (len(xs) - lag) / v


def test_the_jitter_is_correlated_over_its_correlation_time():
    # sampled every 10 ms without FIFO clipping (reorder): the process itself
    cfg = NetemConfig(**RURAL, jitter_corr_s=0.05, reorder=True)
    model = LinkModel(cfg, "down")
    x = [model.delay(0.01 * i) - cfg.delay_s for i in range(20_000)]
    assert statistics.pstdev(x) == pytest.approx(cfg.jitter_s, rel=0.1)
    assert abs(statistics.fmean(x)) < 0.003
    for lag in (1, 5, 20):  # 10, 50 and 200 ms: exp(-lag * 10 ms / 50 ms)
        assert _autocorrelation(x, lag) == pytest.approx(math.exp(-lag * 0.2), abs=0.06)


def test_independent_jitter_has_no_correlation():
    model = LinkModel(NetemConfig(**RURAL, jitter_corr_s=0.0), "down")
    x = [model.delay(0.001 * i) for i in range(20_000)]
    assert abs(_autocorrelation(x, 1)) < 0.05
    assert statistics.pstdev(x) == pytest.approx(0.020, rel=0.1)


def test_a_delay_never_goes_below_zero_and_no_jitter_is_the_fixed_delay():
    model = LinkModel(NetemConfig(delay_s=0.001, jitter_s=0.010), "up")
    assert min(model.delay(0.001 * i) for i in range(5000)) == 0.0
    fixed = LinkModel(NetemConfig(delay_s=0.004), "up")
    assert {fixed.delay(0.001 * i) for i in range(100)} == {0.004}


def test_the_same_seed_and_arrivals_give_the_same_fates():
    cfg = NetemConfig(**RURAL, loss=0.1, seed=11)
    runs = []
    for _ in range(2):
        model = LinkModel(cfg, "up")
        runs.append([None if model.lost() else model.due(0.002 * i, 500) for i in range(2000)])
    assert runs[0] == runs[1]
    assert 150 <= sum(d is None for d in runs[0]) <= 250  # ~10 % lost


def test_the_rate_limited_link_queues_then_tail_drops():
    # 800 kbit/s: 1000 B take 10 ms on the link; the queue holds at most 25 ms of waiting
    model = LinkModel(NetemConfig(bandwidth_kbps=800.0, queue_s=0.025), "up")
    dues = [model.due(1.0, 1000) for _ in range(5)]  # a burst of five at t = 1 s
    assert dues[:3] == pytest.approx([1.01, 1.02, 1.03])  # they wait 0, 10 and 20 ms
    assert dues[3:] == [None, None]  # they would wait 30 ms > 25 ms: dropped, not queued
    assert model.due(1.05, 1000) == pytest.approx(1.06)  # the link is free again


def test_a_datagram_read_late_keeps_its_arrival_time():
    # the relay's loop may be held up (the daemons' real-time threads preempt it): the
    # kernel's receive timestamp, not the read, is when the datagram reached the link
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        timestamp_arrivals(rx)
        rx.bind(("127.0.0.1", 0))
        # The kernel turns receive timestamps on for the whole machine a moment after the first
        # socket asks (a deferred static key; until then it stamps a datagram when it is read):
        # wait until it stamps on arrival, as it does once the relay has run a moment.
        deadline = time.monotonic() + 30.0
        while True:
            tx.sendto(b"w", rx.getsockname())
            time.sleep(0.05)
            _, _, early, read_at = receive(rx)
            if read_at - early >= 0.03 or time.monotonic() > deadline:
                break
        sent = time.monotonic()
        tx.sendto(b"x" * 100, rx.getsockname())
        time.sleep(0.25)  # not read meanwhile
        data, addr, arrival, now = receive(rx)
    finally:
        rx.close()
        tx.close()
    assert data == b"x" * 100 and addr[0] == "127.0.0.1"
    assert now - arrival >= 0.2  # read late, but stamped on arrival
    assert arrival >= sent - 0.05  # (the wall clock mapped to the monotonic one)

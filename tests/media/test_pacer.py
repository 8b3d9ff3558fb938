"""The follower's RTP pacer on a hand-driven clock: new media packets leave spread at the
rate, retransmissions and RTCP at once (their size counted), no packet waits without bound;
and its hook on a real aiortc sender's transport."""

from __future__ import annotations

import asyncio
import struct

import pytest
from media_helpers import two_senders_sending

from humantele.media.aiortc_hooks import pace_sender
from humantele.media.pacer import (
    BURST_S,
    DUP_AFTER_S,
    DUP_HOLD_S,
    DUP_LOSS,
    MIN_RATE_BPS,
    Pacer,
)


class Clock:
    """A clock that moves only when a sleep is awaited."""

    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.now

    async def sleep(self, s: float) -> None:
        self.sleeps.append(s)
        self.now += s


def rtp(seq: int, ssrc: int = 0x1234, size: int = 1200) -> bytes:
    header = struct.pack("!BBHII", 0x80, 96, seq & 0xFFFF, 0, ssrc)
    return header + bytes(size - len(header))


def rtcp_rr(size: int = 60) -> bytes:
    return struct.pack("!BBH", 0x81, 201, size // 4 - 1) + bytes(size - 4)


async def _send(pacer: Pacer, clock: Clock, packets: list[bytes]) -> list[float]:
    out = []
    for p in packets:
        await pacer.before_send(p)
        out.append(clock.now)
    return out


async def test_a_burst_leaves_at_the_rate():
    clock = Clock()
    pacer = Pacer(lambda: 1_000_000.0, clock=clock, sleep=clock.sleep)
    times = await _send(pacer, clock, [rtp(i) for i in range(40)])  # a 48 kB frame at once
    per = 1200 * 8 / 1e6  # 9.6 ms a packet at 1 Mbit/s
    assert times[0] == 100.0  # the first leaves at once
    assert times[-1] - times[0] == pytest.approx(39 * per, abs=BURST_S)
    gaps = [b - a for a, b in zip(times, times[1:], strict=False)]
    assert min(gaps) >= 0.0 and max(gaps) <= per + BURST_S
    assert pacer.paced >= 38 and pacer.waited_s > 0


async def test_retransmissions_and_rtcp_leave_at_once_but_count():
    clock = Clock()
    pacer = Pacer(lambda: 1_000_000.0, clock=clock, sleep=clock.sleep)
    await _send(pacer, clock, [rtp(i) for i in range(10)])
    t = clock.now
    await pacer.before_send(rtp(3))  # asked for again: older than the last sent
    await pacer.before_send(rtcp_rr())
    assert clock.now == t and pacer.immediate == 2
    # the next new packet waits for them too
    before = pacer.free_at
    await pacer.before_send(rtp(10))
    assert clock.now == pytest.approx(before, abs=1e-9)


async def test_a_retransmission_is_not_repeated_within_a_round_trip():
    # aiortc's receiver lists every packet still missing in each NACK: at each new gap the
    # same lost packet is asked for again before the first retransmission could arrive
    clock = Clock()
    pacer = Pacer(lambda: 10_000_000.0, clock=clock, sleep=clock.sleep, rtt_s=lambda: 0.12)
    await _send(pacer, clock, [rtp(i) for i in range(10)])
    assert await pacer.before_send(rtp(4)) is True
    clock.now += 0.05
    assert await pacer.before_send(rtp(4)) is False  # asked again within the round trip
    assert await pacer.before_send(rtp(5)) is True  # another packet is another matter
    clock.now += 0.05  # 100 ms after the first: over 3/4 of the round trip, it may be lost
    assert await pacer.before_send(rtp(4)) is True
    assert pacer.resends_skipped == 1 and pacer.immediate == 3
    assert await pacer.before_send(rtcp_rr()) is True  # RTCP is never held back


class Wire:
    """The transport's own send: what left, and when (on the hand clock)."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.sent: list[tuple[float, bytes]] = []

    async def __call__(self, data: bytes) -> None:
        self.sent.append((self.clock.now, data))


async def _through(pacer: Pacer, wire: Wire, data: bytes) -> None:
    """As the hook does: ask the pacer, send, let it repeat; then run its copies."""
    if await pacer.before_send(data):
        await wire(data)
        pacer.after_send(data, wire)
    if pacer._dup_tasks:
        await asyncio.gather(*list(pacer._dup_tasks))


async def _new(pacer: Pacer, wire: Wire, first: int, n: int) -> int:
    for seq in range(first, first + n):
        await _through(pacer, wire, rtp(seq))
    return first + n


async def test_on_a_reported_lossy_link_each_retransmission_leaves_twice_spaced_and_counted():
    clock = Clock()
    wire = Wire(clock)
    loss: list[float | None] = [None]
    pacer = Pacer(lambda: 1e9, clock=clock, sleep=clock.sleep, rtt_s=lambda: 0.12,
                  loss=lambda: loss[0])  # fmt: skip
    nxt = await _new(pacer, wire, 0, 300)  # few repairs asked for: the share stays low
    await _through(pacer, wire, rtp(3))  # no report yet: one copy
    assert [d for _, d in wire.sent].count(rtp(3)) == 2 and pacer.dups == 0
    nxt = await _new(pacer, wire, nxt, 300)
    loss[0] = 0.01  # below the threshold: one copy
    await _through(pacer, wire, rtp(4))
    assert [d for _, d in wire.sent].count(rtp(4)) == 2 and pacer.dups == 0
    nxt = await _new(pacer, wire, nxt, 300)
    assert pacer.asked_share < DUP_LOSS
    loss[0] = 0.03  # a lossy link: a retransmission leaves twice, DUP_AFTER_S apart
    wire.sent.clear()
    await _through(pacer, wire, rtp(5))
    assert [d for _, d in wire.sent] == [rtp(5), rtp(5)]
    assert wire.sent[1][0] - wire.sent[0][0] == pytest.approx(DUP_AFTER_S)
    assert pacer.dups == 1 and pacer.dup_bytes == 1200
    assert pacer.resent_bytes == 3 * 1200  # the first copies: the repair's cost is counted
    # new media packets and RTCP are never repeated, however lossy the link
    wire.sent.clear()
    await _through(pacer, wire, rtp(nxt))
    await _through(pacer, wire, rtcp_rr())
    assert [d for _, d in wire.sent] == [rtp(nxt), rtcp_rr()] and pacer.dups == 1
    nxt += 1
    # the copy counts against the rate: the next new packet waits for it too
    assert pacer.free_at >= wire.sent[-1][0]
    # a retransmission the pacer holds back (asked again within the round trip): no copy
    wire.sent.clear()
    await _through(pacer, wire, rtp(5))
    assert wire.sent == [] and pacer.dups == 1
    # a report without loss: still lossy for DUP_HOLD_S, then one copy again
    loss[0] = 0.0
    await _through(pacer, wire, rtp(6))
    assert pacer.dups == 2
    clock.now += DUP_HOLD_S
    wire.sent.clear()
    await _through(pacer, wire, rtp(7))
    assert [d for _, d in wire.sent] == [rtp(7)] and pacer.dups == 2


async def test_a_link_whose_repairs_are_asked_for_often_is_lossy_without_a_report():
    # the expert's RTCP reports count a repaired packet as received: on a link whose repairs
    # arrive they report little loss; the share of packets asked for again is the measure
    clock = Clock()
    wire = Wire(clock)
    pacer = Pacer(lambda: 1e9, clock=clock, sleep=clock.sleep, rtt_s=lambda: 0.12)
    nxt = await _new(pacer, wire, 0, 200)
    asks = 0
    while pacer.dups == 0:  # a repair every few packets: 4 % of them
        asks += 1
        await _through(pacer, wire, rtp(nxt - 10))
        nxt = await _new(pacer, wire, nxt, 24)
    assert 3 <= asks <= 10  # lossy within a few repairs of 4 % loss, not at the first
    assert pacer.asked_share >= DUP_LOSS
    # the loss ends: the share decays, and after DUP_HOLD_S a repair leaves once
    nxt = await _new(pacer, wire, nxt, 600)
    clock.now += DUP_HOLD_S
    dups = pacer.dups
    await _through(pacer, wire, rtp(nxt - 10))
    assert pacer.dups == dups and pacer.asked_share < DUP_LOSS


async def test_interleaved_sends_repeat_only_the_retransmissions():
    # the hook awaits the send between before_send and after_send: another packet may pass
    clock = Clock()
    wire = Wire(clock)
    pacer = Pacer(lambda: 1e9, clock=clock, sleep=clock.sleep, loss=lambda: 0.05)
    await _new(pacer, wire, 0, 20)
    wire.sent.clear()
    for data in (rtp(3), rtp(20), rtp(4)):  # a resend, a new packet, a resend: all asked
        assert await pacer.before_send(data)
    for data in (rtp(20), rtp(4), rtp(3)):  # sent in another order
        await wire(data)
        pacer.after_send(data, wire)
    await asyncio.gather(*list(pacer._dup_tasks))
    sent = [d for _, d in wire.sent]
    assert sent.count(rtp(3)) == 2 and sent.count(rtp(4)) == 2 and sent.count(rtp(20)) == 1
    assert pacer.dups == 2 and not pacer._dup_due


async def test_duplicates_can_be_turned_off():
    clock = Clock()
    wire = Wire(clock)
    pacer = Pacer(lambda: 10_000_000.0, clock=clock, sleep=clock.sleep, loss=lambda: 0.2,
                  duplicate=False)  # fmt: skip
    for seq in (0, 1, 2, 0):
        await _through(pacer, wire, rtp(seq))
    assert len(wire.sent) == 4 and pacer.dups == 0 and pacer.figures()["dups"] == 0


async def test_streams_are_told_apart_and_sequence_numbers_wrap():
    clock = Clock()
    pacer = Pacer(lambda: 10_000_000.0, clock=clock, sleep=clock.sleep)
    await _send(pacer, clock, [rtp(65534, ssrc=1), rtp(65535, ssrc=1), rtp(0, ssrc=1)])
    await _send(pacer, clock, [rtp(5, ssrc=2)])  # another stream's first packet is new
    assert pacer.immediate == 0
    await pacer.before_send(rtp(65535, ssrc=1))
    assert pacer.immediate == 1


async def test_no_packet_waits_longer_than_the_bound_and_a_low_rate_is_floored():
    clock = Clock()
    pacer = Pacer(lambda: 0.0, clock=clock, sleep=clock.sleep, max_delay_s=0.2)
    await _send(pacer, clock, [rtp(i) for i in range(20)])
    # floored at MIN_RATE_BPS: 1200 B take 32 ms, not forever
    assert clock.sleeps[0] == pytest.approx(1200 * 8 / MIN_RATE_BPS)
    t = clock.now
    await _send(pacer, clock, [rtp(i) for i in range(20)])  # 20 retransmissions: 0.64 s
    await pacer.before_send(rtp(20))  # new, but would wait 0.64 s: sent at once
    assert clock.now == t and pacer.overdue == 1
    await _send(pacer, clock, [rtp(i) for i in range(21, 60)])
    assert max(clock.sleeps) <= 0.2


async def test_a_rate_that_fails_to_read_paces_at_the_floor():
    clock = Clock()

    def broken() -> float:
        raise RuntimeError("no encoder")

    pacer = Pacer(broken, clock=clock, sleep=clock.sleep)
    await _send(pacer, clock, [rtp(0), rtp(1)])
    assert clock.now - 100.0 == pytest.approx(1200 * 8 / MIN_RATE_BPS)


async def test_the_hook_paces_what_a_real_sender_transport_sends():
    async with two_senders_sending() as (a, b, sent):
        seen: list[bytes] = []

        class Recorder:
            async def before_send(self, data: bytes) -> bool:
                seen.append(data)
                return data != rtp(2)  # the pacer says not to send this one

        pace_sender(a, Recorder())
        pace_sender(b, Recorder())  # one transport (BUNDLE): wrapped once, pacer replaced
        await b.transport._send_rtp(rtp(1))
        await b.transport._send_rtp(rtp(2))
        assert seen == [rtp(1), rtp(2)] and sent == [rtp(1)]
        clock = Clock()
        pacer = Pacer(lambda: 1e7, clock=clock, sleep=clock.sleep, loss=lambda: 0.05)
        pace_sender(a, pacer)
        sent.clear()
        for seq in (5, 6, 5):  # 5 again: a retransmission, on a lossy link
            await b.transport._send_rtp(rtp(seq))
        await asyncio.gather(*list(pacer._dup_tasks))
        assert sent == [rtp(5), rtp(6), rtp(5), rtp(5)] and pacer.dups == 1

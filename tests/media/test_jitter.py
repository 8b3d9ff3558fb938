"""The expert's video jitter buffer (humantele.media.jitter): frames leave on their last packet,
a lost packet is waited for a bounded time, then the buffer skips to a keyframe and asks for
one; nothing old is ever queued for long. Packets are aiortc's RtpPacket; time is a fake clock.

A frame here is a list of payload chunks; its first chunk starts with b"K" for a keyframe."""

from __future__ import annotations

import pytest
from aiortc.rtp import RtpPacket
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon_doubles import Clock
from fuzz_examples import examples
from humantele.media.jitter import (
    BEHIND_RELEASES,
    MIN_REPAIRS,
    REPAIRS_KEPT,
    RTX_MARGIN_S,
    BoundedJitterBuffer,
)

WAIT = 0.1  # s, max_wait_s of the buffers below


def is_key(data: bytes) -> bool:
    return data.startswith(b"K")


class Stream:
    """A sender: frames of n packets, sequence numbers and 90 kHz timestamps going up."""

    def __init__(self, seq: int = 1000) -> None:
        self.seq = seq
        self.ts = 90_000

    def frame(self, chunks: list[bytes]) -> list[RtpPacket]:
        out = []
        for i, chunk in enumerate(chunks):
            p = RtpPacket(sequence_number=self.seq % 65536, timestamp=self.ts,
                          marker=int(i == len(chunks) - 1))  # fmt: skip
            p._data = chunk
            out.append(p)
            self.seq += 1
        self.ts += 4500
        return out


def make(clock: Clock, **kw) -> BoundedJitterBuffer:
    return BoundedJitterBuffer(is_key, max_wait_s=WAIT, clock=clock, **kw)


def feed(buf: BoundedJitterBuffer, packets: list[RtpPacket]) -> list[tuple[bool, bytes | None]]:
    out = []
    for p in packets:
        pli, frame = buf.add(p)
        out.append((pli, None if frame is None else frame.data))
    return out


def test_a_frame_leaves_on_its_last_packet_not_with_the_next_frame():
    clock, s = Clock(), Stream()
    buf = make(clock)
    assert feed(buf, s.frame([b"K1", b"a", b"b"])) == [(False, None), (False, None),
                                                       (False, b"K1ab")]  # fmt: skip
    assert feed(buf, s.frame([b"d2"])) == [(False, b"d2")]
    assert len(buf) == 0 and buf.counters.frames == 2


def test_a_retransmitted_packet_within_the_wait_releases_the_frames_in_order():
    clock, s = Clock(), Stream()
    buf = make(clock)
    feed(buf, s.frame([b"K0"]))
    f1, f2, f3 = s.frame([b"d1", b"x"]), s.frame([b"d2", b"y"]), s.frame([b"d3", b"z"])
    lost = f1[0]
    assert feed(buf, [f1[1], *f2]) == [(False, None)] * 3  # d1 waits for its first packet
    clock.t += 0.9 * WAIT
    assert feed(buf, [lost]) == [(False, b"d1x")]  # the retransmission arrives in time
    # d2 was complete already: it leaves with the next packet, then d3 on its own
    assert feed(buf, f3) == [(False, b"d2y"), (False, b"d3z")]
    assert buf.counters.gaps_given_up == 0 and buf.counters.plis == 0


def test_a_packet_never_retransmitted_costs_a_bounded_freeze_then_a_keyframe():
    clock, s = Clock(), Stream()
    buf = make(clock)
    feed(buf, s.frame([b"K0"]))
    f1 = s.frame([b"d1", b"x"])
    feed(buf, [f1[1]])  # f1[0] is lost for good
    released = []
    for _ in range(2):  # delta frames arrive meanwhile: none may leave (they need d1)
        clock.t += 0.04
        released += [f for _, f in feed(buf, s.frame([b"dn", b"y"])) if f]
    assert released == []
    clock.t += 0.04  # now WAIT has passed since the gap was known
    out = feed(buf, s.frame([b"dn", b"y"]))
    assert any(pli for pli, _ in out)  # a keyframe is asked for, at once
    assert all(f is None for _, f in out) and buf.waiting_for_keyframe
    assert len(buf) == 0  # nothing kept while waiting for the keyframe
    # more delta frames are dropped (their reference is gone), the keyframe leaves at once
    assert all(f is None for _, f in feed(buf, s.frame([b"dn", b"y"])))
    assert feed(buf, s.frame([b"K9", b"q"]))[-1] == (False, b"K9q")
    assert feed(buf, s.frame([b"d10"])) == [(False, b"d10")]  # and the stream goes on
    assert buf.counters.gaps_given_up == 1 and buf.counters.plis == 1
    assert buf.counters.dropped_frames == 4


def test_while_waiting_for_a_keyframe_it_is_asked_for_again_every_interval():
    clock, s = Clock(), Stream()
    buf = make(clock, pli_interval_s=0.5)
    feed(buf, s.frame([b"K0"]))
    feed(buf, s.frame([b"d1", b"x"])[1:])
    clock.t += 2 * WAIT
    plis = 0
    for _ in range(30):  # 1.5 s of delta frames, no keyframe
        plis += sum(p for p, _ in feed(buf, s.frame([b"dn", b"y"])))
        clock.t += 0.05
    assert plis == 3  # at once, then at 0.5 s and 1.0 s


def test_latency_is_bounded_under_steady_loss_and_recovers_when_it_ends():
    """Every 7th packet lost, none retransmitted: the buffer never holds a frame longer than
    the wait plus a frame, and once loss ends every frame leaves on its last packet."""
    clock, s = Clock(), Stream()
    buf = make(clock)
    sent_at: dict[bytes, float] = {}
    ages = []
    n = 0
    for i in range(400):
        key = i % 40 == 0  # the sender answers keyframe requests only every 2 s here
        name = (b"K" if key else b"d") + str(i).encode()
        sent_at[name + b"x"] = clock.t
        for p in s.frame([name, b"x"]):
            n += 1
            if i < 300 and n % 7 == 0:
                continue
            _, frame = buf.add(p)
            if frame is not None:
                ages.append((i, clock.t - sent_at[frame.data]))
        clock.t += 0.05
    assert max(a for _, a in ages) <= WAIT + 0.05 + 1e-9
    assert len(buf) <= 4
    after = [a for i, a in ages if i >= 310]  # loss over, the next keyframe (320) in
    assert len(after) >= 80 and max(after) == 0.0


def test_sequence_numbers_wrap():
    clock, s = Clock(), Stream(seq=65534)
    buf = make(clock)
    assert feed(buf, s.frame([b"K0", b"a", b"b", b"c"]))[-1] == (False, b"K0abc")
    assert feed(buf, s.frame([b"d1", b"e"]))[-1] == (False, b"d1e")


def test_duplicates_and_late_packets_are_ignored_and_counted():
    clock, s = Clock(), Stream()
    buf = make(clock)
    f0 = s.frame([b"K0", b"a"])
    feed(buf, f0)
    f1 = s.frame([b"d1", b"b"])
    feed(buf, f1[:1])
    assert feed(buf, f1[:1]) == [(False, None)]  # a duplicate
    assert feed(buf, f0[:1]) == [(False, None)]  # a packet of a frame already released
    assert feed(buf, f1[1:]) == [(False, b"d1b")]
    assert buf.counters.duplicates == 1 and buf.counters.late_packets == 1


def test_the_start_waits_for_a_keyframe_and_asks_if_it_is_late():
    clock, s = Clock(), Stream()
    buf = make(clock)
    s.frame([b"K0", b"a"])  # the first keyframe is lost whole
    assert feed(buf, s.frame([b"d1", b"b"])) == [(False, None)] * 2  # not asked yet
    clock.t += 2 * WAIT
    assert feed(buf, s.frame([b"d2", b"c"]))[0][0] is True
    assert feed(buf, s.frame([b"K3", b"d"]))[-1] == (False, b"K3d")


def test_a_backlog_of_one_packet_frames_asks_for_a_keyframe():
    """Released one frame per packet, one-packet frames queued behind a late packet never
    catch up: the buffer asks for a keyframe, whose packets drain the queue."""
    clock, s = Clock(), Stream()
    buf = make(clock)
    feed(buf, s.frame([b"K0"]))
    f1, f2, f3 = s.frame([b"d1"]), s.frame([b"d2"]), s.frame([b"d3"])
    feed(buf, [f2[0], f3[0]])
    assert feed(buf, f1) == [(False, b"d1")]  # d1 retransmitted: d2, d3 now wait
    plis = []
    for _ in range(BEHIND_RELEASES + 1):
        plis += [p for p, _ in feed(buf, s.frame([b"dn"]))]
    assert any(plis)
    out = feed(buf, s.frame([b"K", b"1", b"2", b"3", b"4"]))
    assert out[-1] == (False, b"K1234") and len(buf) == 0


def test_overflow_gives_up_like_a_timeout():
    clock, s = Clock(), Stream()
    buf = make(clock, capacity=8)
    feed(buf, s.frame([b"K0"]))
    feed(buf, s.frame([b"d1", b"x"])[1:])
    out = feed(buf, s.frame([b"d", b"2", b"3", b"4", b"5", b"6", b"7", b"8"]))
    assert any(p for p, _ in out) and buf.counters.gaps_given_up == 1 and len(buf) <= 8


@settings(max_examples=examples(200), deadline=None)
@given(
    st.lists(
        st.tuples(
            st.integers(0, 65535),
            st.integers(0, 2**32 - 1),
            st.booleans(),
            st.binary(max_size=12),
            st.floats(0.0, 0.3),
        ),  # fmt: skip
        max_size=300,
    )
)
def test_any_packets_never_raise_and_the_buffer_stays_bounded(packets):
    """Whatever arrives (jumps, wraps, repeats, no markers, keyframe-looking bytes), the
    buffer neither raises nor grows beyond its capacity (and one packet)."""
    clock = Clock()
    buf = make(clock, capacity=64)
    for seq, ts, marker, data, dt in packets:
        clock.t += dt
        p = RtpPacket(sequence_number=seq, timestamp=ts, marker=int(marker))
        p._data = data
        pli, frame = buf.add(p)
        assert isinstance(pli, bool) and len(buf) <= 65
        assert frame is None or isinstance(frame.data, bytes)


def test_on_a_long_round_trip_a_retransmission_is_waited_for_a_round_trip():
    """At 60 ms each way a NACK's retransmission comes ~130 ms after the gap is seen: a fixed
    100 ms wait gave up on every one (a freeze and a keyframe each); with the link's round
    trip the wait is that round trip and a margin, and still bounded."""
    clock, s = Clock(), Stream()
    rtt = {"s": 0.13}
    buf = make(clock, rtt=lambda: rtt["s"])
    assert buf.wait_s() > 0.13 and buf.pli_every_s() == buf.pli_interval_s
    feed(buf, s.frame([b"K0"]))
    f1, f2 = s.frame([b"d1", b"x"]), s.frame([b"d2", b"y"])
    assert feed(buf, [f1[1], *f2]) == [(False, None)] * 3
    clock.t += 0.13  # past the 100 ms of max_wait_s, within the round trip's wait
    assert feed(buf, [f1[0]]) == [(False, b"d1x")]
    assert buf.counters.gaps_given_up == 0
    # a gap never repaired is still given up, after the round trip's wait
    f3, f4 = s.frame([b"d3", b"z"]), s.frame([b"d4", b"w"])
    feed(buf, [f3[1], *f4])
    clock.t += buf.wait_s() + 0.01
    assert feed(buf, s.frame([b"K5"]))[-1][1] == b"K5"  # d3, d4 dropped: the keyframe next
    assert buf.counters.gaps_given_up == 1
    rtt["s"] = 30.0  # a silly round trip: the wait stays bounded, so do keyframe requests
    assert buf.wait_s() <= 1.0 and buf.pli_every_s() <= 1.0
    rtt["s"] = None
    assert buf.wait_s() == WAIT


def test_a_nack_held_for_the_parity_lengthens_the_round_trips_wait():
    """With the parity on, the receiver holds a NACK up to 30 ms for the frame's parity: a
    repair then takes the round trip and the hold, which the wait the round trip sets must
    cover (before repairs are measured: with the parity few are); a repair that takes them
    both is not given up."""
    clock, s = Clock(), Stream()
    buf = make(clock, rtt=lambda: 0.13)
    bare = buf.wait_s()
    buf.nack_hold = lambda: 0.03
    assert buf.wait_s() == pytest.approx(bare + 0.03)
    feed(buf, s.frame([b"K0"]))
    f1, f2 = s.frame([b"d1", b"x"]), s.frame([b"d2", b"y"])
    feed(buf, [f1[1], *f2])
    clock.t += bare + 0.01  # the hold and the round trip: past the bare wait, within this
    assert feed(buf, [f1[0]]) == [(False, b"d1x")]
    assert buf.counters.gaps_given_up == 0


def test_a_packet_still_missing_is_asked_for_again_each_round_trip_until_it_comes():
    """aiortc NACKs a gap once (and again only when a later gap shows): on a lossy link the
    NACK or its retransmission is lost about one time in four at 15 %; the buffer asks again
    every round trip and a little while it still waits, and not for what came or was given
    up."""
    clock, s = Clock(), Stream()
    buf = make(clock, rtt=lambda: 0.03)
    every = buf.renack_every_s()
    assert every == 0.045
    feed(buf, s.frame([b"K0"]))
    f1, f2 = s.frame([b"d1", b"x"]), s.frame([b"d2", b"y"])
    feed(buf, [f1[1]])  # the gap shows: aiortc's own NACK goes out now
    assert buf.take_nacks() == []
    clock.t += every
    feed(buf, [f2[0]])
    assert buf.take_nacks() == [f1[0].sequence_number]  # asked again
    clock.t += 0.5 * every
    feed(buf, [f2[1]])
    assert buf.take_nacks() == []  # not yet again
    clock.t += 0.5 * every
    assert feed(buf, [f1[0]]) == [(False, b"d1x")]  # the retransmission came
    assert buf.take_nacks() == [] and buf.counters.renacks == 1
    f3, f4 = s.frame([b"d3", b"z"]), s.frame([b"d4", b"w"])
    feed(buf, [f3[1], *f4])
    clock.t += buf.wait_s() + 0.01  # never repaired: given up, and no longer asked for
    feed(buf, s.frame([b"K5"]))
    buf.take_nacks()
    clock.t += 1.0
    feed(buf, s.frame([b"d6"]))
    assert buf.take_nacks() == [] and buf.counters.gaps_given_up == 1


def test_the_waits_follow_the_repairs_measured_not_only_the_given_round_trip():
    """Retransmissions take 90 ms, then 125 ms (a queue on the link) where the given round
    trip says 30 ms: the wait grows with the repairs measured (so the picture does not freeze
    on each lost packet) and re-asking follows them too (no duplicate NACKs every 45 ms). A
    retransmission 2 s after its frame was given up is counted, not timed (over
    LATE_REPAIR_MAX_S: the freeze budget)."""
    clock, s = Clock(), Stream()
    buf = make(clock, rtt=lambda: 0.03)
    assert buf.wait_s() == WAIT and buf.renack_every_s() == pytest.approx(0.045)
    feed(buf, s.frame([b"K0"]))

    def repaired_after(took: float) -> list:
        f1, f2 = s.frame([b"d1", b"x"]), s.frame([b"d2", b"y"])
        feed(buf, [f1[1], *f2])
        clock.t += took
        return feed(buf, [f1[0]])

    for _ in range(MIN_REPAIRS):
        assert repaired_after(0.09) == [(False, b"d1x")]
    assert buf.wait_s() == pytest.approx(0.09 + RTX_MARGIN_S)
    assert buf.renack_every_s() == pytest.approx(0.09 + 0.015)
    assert buf.counters.repair_ms == pytest.approx(90.0)
    assert repaired_after(0.125) == [(False, b"d1x")]  # waited for: 125 ms < 130 ms
    assert buf.counters.gaps_given_up == 0 and buf.counters.repairs == MIN_REPAIRS + 1
    # one never repaired in time is given up; its retransmission, 2 s late, moves nothing
    wait = buf.wait_s()
    f1, f2 = s.frame([b"d1", b"x"]), s.frame([b"d2", b"y"])
    feed(buf, [f1[1], *f2])
    clock.t += wait + 0.01
    feed(buf, s.frame([b"K5"]))
    clock.t += 2.0
    assert feed(buf, [f1[0]]) == [(False, None)]
    assert buf.counters.gaps_given_up == 1 and buf.counters.late_repairs == 1
    assert buf.wait_s() == wait


def test_repairs_faster_than_the_floor_keep_the_floor_and_a_silly_one_is_bounded():
    clock, s = Clock(), Stream()
    buf = make(clock)
    feed(buf, s.frame([b"K0"]))
    for _ in range(5):  # repaired in 5 ms
        f1, f2 = s.frame([b"d1", b"x"]), s.frame([b"d2", b"y"])
        feed(buf, [f1[1], *f2])
        clock.t += 0.005
        feed(buf, [f1[0]])
    assert buf.wait_s() == WAIT and buf.renack_every_s() == 0.025
    for _ in range(REPAIRS_KEPT):  # then 30 s each (a stalled peer)
        f1, f2 = s.frame([b"d1", b"x"]), s.frame([b"d2", b"y"])
        feed(buf, [f1[1], *f2])
        clock.t += 30.0
        feed(buf, [f1[0]])
    assert buf.wait_s() <= 1.0 and buf.pli_every_s() <= 1.0


def test_waiting_for_a_keyframe_the_frames_before_it_are_not_waited_for():
    """After a gap was given up only a keyframe helps: when one starts to arrive, an older
    incomplete frame (which could not be decoded anyway) must not hold it back for the
    whole wait."""
    clock, s = Clock(), Stream()
    buf = make(clock)
    feed(buf, s.frame([b"K0"]))
    feed(buf, s.frame([b"d1", b"x"])[1:])
    clock.t += 2 * WAIT
    out = feed(buf, s.frame([b"d2", b"y"]))  # d1 given up: a keyframe is asked for
    assert any(p for p, _ in out) and buf.waiting_for_keyframe
    d3 = s.frame([b"d3", b"z"])  # its last packet lost too
    feed(buf, d3[:1])
    key = s.frame([b"K4", b"a", b"b"])
    assert feed(buf, key)[-1] == (False, b"K4ab")  # at once, not WAIT later
    assert buf.counters.skipped_to_keyframe == 1 and not buf.waiting_for_keyframe
    assert feed(buf, s.frame([b"d5"])) == [(False, b"d5")]
    assert feed(buf, d3[1:]) == [(False, None)] and buf.counters.late_packets == 1


def test_a_backlog_that_drains_after_a_repair_asks_for_no_keyframe():
    """On a long round trip several frames complete behind a repaired packet; frames of two
    or more packets drain that backlog by themselves (each packet releases one): a keyframe
    request for it was a keyframe (3-10 delta frames of bits) after nearly every repair."""
    clock, s = Clock(), Stream()
    buf = make(clock, rtt=lambda: 0.25)
    feed(buf, s.frame([b"K0"]))
    f1 = s.frame([b"d1", b"x"])
    out = feed(buf, f1[1:])
    for i in range(5):  # 250 ms of frames complete behind d1
        out += feed(buf, s.frame([b"d" + bytes([50 + i]), b"y"]))
    clock.t += 0.25
    out += feed(buf, f1[:1])  # the retransmission: d1 leaves, five frames wait
    released = []
    for i in range(8):  # the stream goes on
        for pli, frame in feed(buf, s.frame([b"n" + bytes([48 + i]), b"z"])):
            out.append((pli, frame))
            released.append(frame)
    assert not any(pli for pli, _ in out) and buf.counters.plis == 0
    assert released[-1] == b"n7z"  # caught up: the newest frame leaves on its last packet


def test_the_packets_given_up_are_handed_out_once_not_to_be_asked_for_again():
    clock, s = Clock(), Stream(seq=65534)  # across the 16-bit wrap
    buf = make(clock)
    feed(buf, s.frame([b"K0"]))  # 65534
    f1 = s.frame([b"d1", b"x"])  # 65535 (lost for good), 0
    feed(buf, [f1[1]])
    assert buf.take_given_up() == []  # still waited for
    clock.t += 2 * WAIT
    feed(buf, s.frame([b"dn", b"y"]))  # the wait has passed: given up
    assert buf.counters.gaps_given_up == 1
    assert buf.take_given_up() == [65535]  # its 16-bit number, as NACKs carry it
    assert buf.take_given_up() == []  # once
    buf.take_nacks()
    clock.t += 2 * WAIT
    feed(buf, s.frame([b"dn", b"y"]))
    assert 65535 not in buf.take_nacks()  # nor asked for again by the buffer itself


def test_the_packets_given_up_stay_bounded_if_nobody_takes_them():
    from humantele.media.jitter import GONE_KEPT

    clock, s = Clock(), Stream()
    buf = make(clock)
    feed(buf, s.frame([b"K0"]))
    for _ in range(GONE_KEPT * 2):  # one packet of each frame lost for good
        clock.t += 2 * WAIT
        f = s.frame([b"d", b"x", b"y"])
        feed(buf, [f[0], f[2]])
    assert buf.counters.gaps_given_up > 0
    assert 0 < len(buf.take_given_up()) <= GONE_KEPT


def test_a_give_up_while_the_keyframe_asked_for_is_on_its_way_asks_no_second_one():
    """Waiting for the keyframe asked for, an older frame given up asks for none (the encoder
    would send a second keyframe behind the first: the burst a thin link drops, a PLI storm);
    the request is repeated on its interval, and at once when the keyframe itself is lost."""
    clock, s = Clock(), Stream()
    buf = make(clock, pli_interval_s=0.5)
    feed(buf, s.frame([b"K0"]))
    feed(buf, s.frame([b"d1", b"x"])[1:])
    clock.t += 2 * WAIT
    assert any(p for p, _ in feed(buf, s.frame([b"d2", b"y"])))  # d1 given up: asked
    feed(buf, s.frame([b"d3", b"z"])[1:])  # d3's first packet lost too
    clock.t += 2 * WAIT
    assert not any(p for p, _ in feed(buf, s.frame([b"d4", b"w"])))  # d3 given up: held
    assert buf.counters.gaps_given_up == 2 and buf.counters.plis_held == 1
    clock.t += 0.5  # the repeat
    assert any(p for p, _ in feed(buf, s.frame([b"d5", b"v"])))
    key = s.frame([b"K6", b"a", b"b"])
    feed(buf, [key[0], key[2]])  # the keyframe arrives, one packet lost
    clock.t += 2 * WAIT
    assert any(p for p, _ in feed(buf, s.frame([b"d7", b"u"])))  # the keyframe lost: at once
    assert buf.counters.plis == 3 and buf.counters.plis_held == 1
    assert feed(buf, s.frame([b"K8", b"c"]))[-1] == (False, b"K8c")


def test_late_repairs_set_the_wait_too():
    """On a thin link the retransmissions queue behind the media: they came after the wait
    (83 late, 25 in time on the rural link), and timed only within it, the wait never grew to
    cover them. Late ones are timed too (up to LATE_REPAIR_MAX_S): the wait follows."""
    clock, s = Clock(), Stream()
    buf = make(clock, rtt=lambda: 0.03)
    feed(buf, s.frame([b"K0"]))
    for _ in range(MIN_REPAIRS):  # three repairs in 60 ms
        f1, f2 = s.frame([b"d1", b"x"]), s.frame([b"d2", b"y"])
        feed(buf, [f1[1], *f2])
        clock.t += 0.06
        feed(buf, [f1[0]])
    assert buf.wait_s() == WAIT
    f1, f2 = s.frame([b"d1", b"x"]), s.frame([b"d2", b"y"])  # then one takes 250 ms:
    feed(buf, [f1[1], *f2])
    clock.t += 0.25
    feed(buf, s.frame([b"K", b"k"]))  # the wait ran out: d1 given up (a keyframe came)
    feed(buf, [f1[0]])  # its retransmission, late
    assert buf.counters.late_repairs == 1 and buf.counters.gaps_given_up == 1
    assert buf.wait_s() == pytest.approx(0.25 + RTX_MARGIN_S)
    for _ in range(3):  # the next ones taking as long are waited for
        f1, f2 = s.frame([b"d1", b"x"]), s.frame([b"d2", b"y"])
        feed(buf, [f1[1], *f2])
        clock.t += 0.25
        assert feed(buf, [f1[0]]) == [(False, b"d1x")]
    assert buf.counters.gaps_given_up == 1


def test_a_missing_packet_is_asked_for_again_between_packets_when_polled():
    """At 15 % loss the US's packets came 50-160 ms apart: asked again only on a packet's
    arrival, a lost retransmission got one more try or none within the wait. Polled between
    packets, the buffer asks again every round trip and a little, packets or not."""
    clock, s = Clock(), Stream()
    buf = make(clock, rtt=lambda: 0.03)
    every = buf.renack_every_s()
    feed(buf, s.frame([b"K0"]))
    f1 = s.frame([b"d1", b"x"])
    feed(buf, [f1[1]])  # the gap shows (aiortc's own NACK)
    asked = 0
    for _ in range(int(2 * every / 0.01) + 2):  # no packet for two round trips and more
        clock.t += 0.01
        buf.poll()
        asked += len(buf.take_nacks())
    assert asked == 2 and buf.counters.renacks == 2
    assert feed(buf, [f1[0]]) == [(False, b"d1x")]
    buf.poll()
    assert buf.take_nacks() == []

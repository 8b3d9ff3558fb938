"""A healthy force board on a starved machine (issue 34, the whole-suite run at load 10-17):
the sensing process's reader thread did not run for 0.2 s, so a board that sent every 10 ms
read stale, and the landmark calibration waited for presses the replay did not repeat.

Staleness is decided by the board's evidence: the reports it queued in the HID buffer while the
reader slept are fresh; only a read that comes back empty past the deadline is stale (issue 30's
unplug test, tests/devices/test_force_board_unplug.py, keeps its 0.2 s). The same seam in the
replay: a recording made by a starved recorder holds bursts of reports at one receive time;
replayed at those times, a board silent for the length of the stall. Timing on clocks the test
drives by hand (10 ms steps, the board's 100 Hz)."""

from __future__ import annotations

import sys
import threading

import numpy as np
import pytest
from fake_hidapi import FakeHid

from humantele.forcesense.calibration import calibrate_sim
from humantele.forcesense.contact import ContactConfig
from humantele.forcesense.hid import HidForceConfig, HidForceSensor, encode_report
from humantele.forcesense.reader import ForceReader
from humantele.forcesense.replay import ReplayForceConfig, ReplayForceSensor
from humantele.forcesense.sim import SimForceSensor
from humantele.forcesense.sim_config import SimForceConfig
from humantele.recording.device_file import HID_REPORT, DeviceRecordingWriter

VID, PID = 0x1209, 0x4854
PRESS_N = np.array([0.0, 0.0, -6.0])  # probe frame: above the contact threshold (3 N)
STEP_S = 0.01


class Clock:
    def __init__(self, t: float = 50.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.t += dt


@pytest.fixture(scope="module")
def board_model():
    """The sim board's calibration, and report k of it pressed at PRESS_N (board time k*10 ms,
    starting at ``t0_us``)."""
    sim = SimForceSensor(SimForceConfig())
    cal = calibrate_sim(sim, n=400)
    sim.set_force(PRESS_N)

    def report(k: int, t0_us: int = 0) -> bytes:
        r = sim.read(k * STEP_S)
        return encode_report(k, t0_us + int(k * STEP_S * 1e6), r.a, r.b, r.temperature_c)

    return cal, report


def test_a_starved_reader_finds_the_board_alive_in_what_it_queued(monkeypatch, board_model):
    cal, report = board_model
    clock = Clock()
    hub = FakeHid(VID, PID, [])
    monkeypatch.setitem(sys.modules, "hid", hub)
    sensor = HidForceSensor(HidForceConfig(read_timeout_ms=0), clock=clock)
    sensor.open()
    reader = ForceReader(sensor, cal, ContactConfig(), stale_s=0.2, clock=clock)
    k = 0

    def board_sends() -> None:  # 10 ms of the board's time: one report in the HID buffer
        nonlocal k
        clock.t += STEP_S
        if not hub.unplugged:
            hub.reports.append(report(k))
            k += 1

    for _ in range(20):
        board_sends()
        reader.poll()
    assert reader.sample().contact
    # The reader thread does not run for 0.5 s; the sensing's main thread samples meanwhile.
    for _ in range(50):
        board_sends()
        s = reader.sample()
        assert not s.stale and s.contact, "stale for the reader's scheduling, not the board's"
    assert len(hub.reports) == 50  # queued in the HID buffer, as hidraw keeps them
    reader.poll()  # it wakes and drains them: the newest is fresh
    s = reader.sample()
    assert not s.stale and s.contact and s.age_s == 0.0
    assert reader.late_polls == 1 and reader.caught_up == 1 and reader.stale_spells == 0
    assert not hub.reports and sensor.received == k
    np.testing.assert_allclose(s.force_probe, PRESS_N, atol=0.5)
    stats = reader.stats()
    assert stats["late_polls"] == 1 and stats["caught_up"] == 1 and not stats["stale"]

    # Starved again, and the board is unplugged meanwhile: the read that wakes finds nothing,
    # past the deadline: stale at once, and the press is not carried over.
    board_sends()
    reader.poll()
    hub.unplug()
    for _ in range(30):
        board_sends()
    assert not reader.sample().stale  # nothing read yet says otherwise
    reader.poll()
    s = reader.sample()
    assert s.stale and not s.contact and s.age_s == pytest.approx(0.3)
    assert reader.late_polls == 2 and reader.caught_up == 1 and reader.stale_spells == 1
    assert not reader.contact.in_contact


def test_a_reader_thread_that_died_or_stopped_reading_makes_the_force_stale(board_model):
    cal, report = board_model
    clock = Clock()
    hub = FakeHid(VID, PID, [report(0)])
    sensor = HidForceSensor(HidForceConfig(read_timeout_ms=0), device=hub.device(), clock=clock)
    reader = ForceReader(sensor, cal, ContactConfig(), stale_s=0.2, clock=clock,
                         reader_silent_s=2.0)  # fmt: skip
    reader.poll()
    assert not reader.sample().stale
    hold = threading.Event()
    wedged = threading.Thread(target=hold.wait, daemon=True)  # a reader stuck, alive
    wedged.start()
    reader._thread = wedged
    try:
        clock.t += 1.9  # a starved reader: its last read's verdict holds
        assert not reader.sample().stale
        clock.t += 0.2  # no read for 2 s: not a busy machine any more
        assert reader.sample().stale and reader.stale_spells == 1
    finally:
        hold.set()
        wedged.join()
    clock.t -= 2.1
    hub.reports.append(report(1))
    reader.poll()
    assert reader.sample().stale  # a thread that has died vouches for nothing
    reader._thread = None
    reader.poll()
    assert not reader.sample().stale


def _starved_recording(path, report, n: int, gap: range) -> None:
    """n reports sent every 10 ms (board time from 4294.9 s: the board's clock wraps inside),
    received 1 ms later, except those of ``gap``: received at once at the gap's end (the
    recorder's thread did not run meanwhile)."""
    t0_us = (1 << 32) - 100_000
    with_burst = STEP_S * gap.stop + 0.001
    writer = DeviceRecordingWriter(path)
    for k in range(n):
        t = 1000.0 + (with_burst if k in gap else k * STEP_S + 0.001)
        writer.write(HID_REPORT, t, {"t_receive": t}, {"report": report(k, t0_us)})
    writer.close()


def test_a_recording_made_by_a_starved_recorder_replays_as_the_board_sent(tmp_path, board_model):
    cal, report = board_model
    path = tmp_path / "starved.mcap"
    _starved_recording(path, report, 100, range(30, 80))
    clock = Clock(0.0)
    sensor = ReplayForceSensor(ReplayForceConfig(file=str(path), read_timeout_ms=0), clock,
                               clock.sleep)  # fmt: skip
    sensor.open()
    reader = ForceReader(sensor, cal, ContactConfig(), stale_s=0.2, clock=clock)
    clock.t = STEP_S / 2  # read half-way between the board's reports
    seqs = []
    try:
        for _ in range(100):
            reader.poll()
            s = reader.sample()
            assert not s.stale, f"stale at {clock.t:.2f} s: the recorder's stall replayed"
            seqs.append(sensor.received)
            clock.t += STEP_S
    finally:
        sensor.close()
    assert seqs == list(range(1, 101))  # one report every 10 ms, as the board sent them
    assert reader.readings == 100 and reader.stale_spells == 0


def test_a_board_clock_ahead_of_the_receive_times_is_anchored_again(tmp_path, board_model):
    """Never due after it was received: a board whose clock restarts (or runs fast) is paced
    by its receive time from there."""
    cal, report = board_model
    path = tmp_path / "restart.mcap"
    writer = DeviceRecordingWriter(path)
    times = [0.0, 0.01, 0.02, 0.03, 0.04]
    boards = [500_000, 510_000, 520_000, 5_000, 15_000]  # restarted between 3rd and 4th
    for t, b in zip(times, boards, strict=True):
        r = report(0, b)
        writer.write(HID_REPORT, t, {"t_receive": t}, {"report": r})
    writer.write(HID_REPORT, 0.05, {"t_receive": 0.05}, {"report": b"\x02" + bytes(63)})
    writer.write(HID_REPORT, 0.06, {"t_receive": 0.06}, {"report": report(0, 25_000)})
    writer.close()
    clock = Clock(0.0)
    sensor = ReplayForceSensor(ReplayForceConfig(file=str(path)), clock, clock.sleep)
    sensor.open()
    dev = sensor._dev
    due = []
    while (got := dev.read(64, 1000)) != [] or dev._next is not None:
        if got:
            due.append(round(clock.t, 6))
    sensor.close()
    # the bad report (id 2) goes with the one before it; the last is 10 ms after that one
    assert due == [0.0, 0.01, 0.02, 0.03, 0.04, 0.04, 0.05]

"""The force board unplugged and plugged in again, through the HID seam (the ``hid`` module the
backend opens the board with, replaced by a fake that refuses as cython-hidapi does): the
force goes stale within 0.2 s and is never fed to the contact detector meanwhile, the board
is looked for with back-off and read again within 2 s of the replug; a binding's
RuntimeError is caught like hidapi's OSError; a board that never stops sending cannot hold
one read. Timing on a clock the test drives by hand (10 ms steps, the board's 100 Hz),
except the threaded reader's test, which waits for events with generous deadlines."""

from __future__ import annotations

import sys
import time

import numpy as np
import pytest
from fake_hidapi import FakeHid

from humantele.follower.clinic import DeviceClinicConfig
from humantele.follower.sensing import ProbeSensing, Sensing, SensingConfig, SensingSetup
from humantele.follower.sensing_devices import SensingDevices
from humantele.forcesense.calibration import calibrate_sim
from humantele.forcesense.contact import ContactConfig
from humantele.forcesense.hid import HidForceConfig, HidForceSensor, encode_report
from humantele.forcesense.reader import ForceReader
from humantele.forcesense.sim import SimForceSensor
from humantele.forcesense.sim_config import SimForceConfig
from humantele.tracking.frames import FrameSource
from waits import wait_for

VID, PID = 0x1209, 0x4854
PRESS_N = np.array([0.0, 0.0, -6.0])  # probe frame: above the contact threshold (3 N)
STEP_S = 0.01


class Clock:
    def __init__(self) -> None:
        self.t = 50.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture(scope="module")
def board_model():
    """The sim board's calibration, and a report of it pressed at PRESS_N."""
    sim = SimForceSensor(SimForceConfig())
    cal = calibrate_sim(sim, n=400)
    sim.set_force(PRESS_N)

    def report(k: int) -> bytes:
        r = sim.read(k * STEP_S)
        return encode_report(k, int(k * STEP_S * 1e6), r.a, r.b, r.temperature_c)

    return cal, report


def plugged(monkeypatch, clock, **kw):
    hub = FakeHid(VID, PID, [])
    monkeypatch.setitem(sys.modules, "hid", hub)
    sensor = HidForceSensor(HidForceConfig(read_timeout_ms=0, **kw), clock=clock)
    sensor.open()  # hidapi's enumerate and open_path, as with the board
    return hub, sensor


def test_unplugged_board_goes_stale_in_0_2_s_and_is_back_within_2_s_of_replug(
    monkeypatch, board_model
):
    cal, report = board_model
    clock = Clock()
    hub, sensor = plugged(monkeypatch, clock)
    reader = ForceReader(sensor, cal, ContactConfig(), stale_s=0.2, clock=clock)
    k = 0

    def step() -> None:  # 10 ms: the board sends one report (while plugged), the reader reads
        nonlocal k
        clock.t += STEP_S
        if not hub.unplugged:
            hub.reports.append(report(k))
            k += 1
        reader.poll()

    for _ in range(20):
        step()
    s = reader.sample()
    assert not s.stale and s.contact and s.event == "press"
    np.testing.assert_allclose(s.force_probe, PRESS_N, atol=0.5)
    first_handle = sensor._dev

    hub.unplug()
    unplugged_at = clock.t
    stale_at = None
    while stale_at is None:
        step()
        s = reader.sample()
        if s.stale:
            stale_at = clock.t
        else:
            assert s.contact  # the last good force is still fresh
        assert clock.t - unplugged_at < 1.0
    # the last good reading came one step before the unplug: stale once it is 0.2 s old
    assert 0.2 - STEP_S - 1e-9 <= stale_at - unplugged_at <= 0.2 + STEP_S + 1e-9
    assert not s.contact and sensor.dropped["io"] == 1 and sensor.unplugs == 1
    assert first_handle.closed and not sensor.connected
    readings = reader.readings
    for _ in range(300):  # 3 s unplugged: looked for with back-off, never fresh
        step()
        s = reader.sample()
        assert s.stale and not s.contact and s.event is None
    assert reader.readings == readings and not reader.contact.in_contact
    # tries at 0.25 s, then 0.5, 1, 1, 1 s apart: 3 s holds 4 of them
    assert sensor.dropped["reopen_failed"] == 4 and hub.opened == 1

    hub.replug()  # on a new hidraw node
    replugged_at = clock.t
    while reader.sample().stale:
        step()
        assert clock.t - replugged_at <= 2.0, "not back within 2 s of the replug"
    assert sensor.reopens == 1 and hub.opened == 2 and sensor.connected
    assert reader.stale_spells == 1
    for _ in range(5):  # the press is found again, from fresh readings only
        step()
    assert reader.sample().contact


def test_a_runtime_error_from_the_binding_is_caught_like_an_os_error(monkeypatch, board_model):
    cal, report = board_model
    clock = Clock()
    hub, sensor = plugged(monkeypatch, clock)
    hub.read_error = RuntimeError  # another hidapi binding's "read error"
    hub.reports.append(report(0))
    assert sensor.read() is not None
    hub.unplug()
    assert sensor.read() is None and sensor.dropped == {"io": 1} and not sensor.connected
    clock.t += 0.25
    hub.replug()
    hub.reports.append(report(1))
    assert sensor.read() is not None and sensor.reopens == 1


def test_a_board_that_never_stops_sending_cannot_hold_one_read(monkeypatch, board_model):
    cal, report = board_model
    clock = Clock()
    hub, sensor = plugged(monkeypatch, clock, max_reports=5, max_read_ms=1000.0)
    hub.flood = report(0)
    assert sensor.read() is not None and hub.reads == 5  # the count bound
    hub2, sensor2 = plugged(monkeypatch, clock, max_reports=10_000, max_read_ms=30.0)
    hub2.flood = report(0)
    t0 = time.monotonic()
    assert sensor2.read() is not None
    assert time.monotonic() - t0 < 5.0  # the time bound (30 ms), not 10,000 reports
    assert hub2.reads < 10_000


class NoFrames(FrameSource):
    """A camera that gives nothing (its stream stalled): the force must not wait on it."""

    stalled = True

    def open(self) -> None:
        pass

    def read(self, t=None):
        time.sleep(0.05)  # a read bounded by its deadline, which the force does not wait for
        return None

    def close(self) -> None:
        pass


def test_the_follower_reads_the_board_at_its_own_rate_and_sends_no_stale_force(
    monkeypatch, board_model
):
    cal, report = board_model
    hub = FakeHid(VID, PID, [])
    monkeypatch.setitem(sys.modules, "hid", hub)
    hub.flood = report(0)  # always a report waiting: the board pressed
    sensor = HidForceSensor(HidForceConfig(read_timeout_ms=0, max_reports=2))
    devices = SensingDevices(NoFrames(), sensor, cal)  # real devices: no observe()
    config = SensingConfig()
    ps = ProbeSensing(config, devices=devices)
    # what the sensing reads of the follower's config, for a clinic on its devices
    setup = SensingSetup("probe_default", DeviceClinicConfig(), "pipeline", 1.0)
    view = Sensing(setup, config, build=False)
    view.pipeline, view.unbuilt = ps, False
    try:
        m = view.measure(time.monotonic())
        assert ps.force.running  # the board's own thread, started at the first measure
        reads = ps.force.reads
        assert wait_for(lambda: ps.force.reads >= reads + 10)  # read with no measure() at all
        assert wait_for(lambda: ps.force.sample().contact)
        m = view.measure(time.monotonic())
        assert m.contact and not m.force_stale and m.camera_stalled
        assert m.force_tip is not None and np.linalg.norm(m.force_world) > 3.0
        hub.unplug()
        assert wait_for(lambda: ps.force.sample().stale)
        m = view.measure(time.monotonic())
        assert m.force_stale and not m.contact and m.force_tip is None
        assert np.all(m.force_world == 0.0)
        hub.replug()
        assert wait_for(lambda: not ps.force.sample().stale)
        m = view.measure(time.monotonic())
        assert not m.force_stale and m.force_tip is not None
        stats = ps.device_stats()
        assert stats["force"]["board"]["unplugs"] == 1 and stats["force_stale"] >= 1
        assert stats["camera"]["stalled"] and stats["no_frame"] == 4
    finally:
        ps.close()
    assert not ps.force.running

"""HID devices (SpaceMouse profile, force sensor board) replayed through their real open/read
paths with a stand-in hidapi module; malformed and random reports are dropped and counted."""

import math
import struct
import sys
from pathlib import Path

import pytest
from fake_hidapi import FakeHid, load_recording
from hypothesis import given, settings
from hypothesis import strategies as st

from fuzz_examples import examples
from humantele.forcesense.hid import (
    ForceSensorUnavailable,
    HidForceConfig,
    HidForceSensor,
    encode_report,
    parse_report,
)
from humantele.haptics.devices import DeviceError, HidDevice, HidDeviceConfig

DATA = Path(__file__).parent / "data"
SPACEMOUSE = (0x256F, 0xC635)


def rep(report_id: int, *values: int) -> bytes:
    return bytes([report_id]) + struct.pack(f"<{len(values)}h", *values)


def spacemouse(monkeypatch, reports):
    hub = FakeHid(*SPACEMOUSE, reports)
    monkeypatch.setitem(sys.modules, "hid", hub)
    dev = HidDevice(HidDeviceConfig())
    dev.open()
    return hub, dev


def test_spacemouse_session_replayed_through_open_and_read(monkeypatch):
    reports = load_recording(DATA / "spacemouse_session.hex")
    hub, dev = spacemouse(monkeypatch, reports)
    assert hub.opened == 1
    states = []
    buttons_seen = set()
    while hub.reports:
        s = dev.read()  # drains up to 32 reports per call, as in the servo loop
        states.append(s)
        buttons_seen.add(dev.integrator.buttons)
        assert s.is_finite()
    p = states[-1].position
    half = [w / 2 for w in dev.spec.workspace_m]
    assert all(abs(p[i]) <= half[i] + 1e-12 for i in range(3))
    assert dev.parser.dropped == 3  # the short read, the unknown id, the out-of-range axis
    assert dev.parser.parsed == len(reports) - 3
    assert dev.integrator.buttons == 0  # released at the end


def test_spacemouse_direction_of_each_axis(monkeypatch):
    """Push right -> +x; push the cap down -> -y (device y up); raw twist -> -ry."""
    hub, dev = spacemouse(monkeypatch, [rep(1, 300, 0, 0)])
    dev.read()
    assert dev.integrator.rates["tx"] > 0 and dev.integrator.rates["ty"] == 0
    hub.reports += [rep(1, 0, 0, 250), rep(2, 0, 0, 200), bytes([3, 1])]
    dev.read()
    assert dev.integrator.rates["ty"] < 0 and dev.integrator.rates["ry"] < 0
    assert dev.read().buttons == 1


def test_spacemouse_unplugged_is_a_clear_error(monkeypatch):
    hub, dev = spacemouse(monkeypatch, [])
    hub.unplug()
    with pytest.raises(DeviceError, match="stopped answering"):
        dev.read()
    dev.close()
    with pytest.raises(DeviceError, match="no 3Dconnexion SpaceMouse found.*udev"):
        HidDevice(HidDeviceConfig()).open()


@settings(max_examples=examples(150), deadline=None)
@given(st.lists(st.binary(min_size=1, max_size=70), max_size=40))  # empty = "no data"
def test_spacemouse_random_bytes_never_crash_or_escape_the_workspace(reports):
    mp = pytest.MonkeyPatch()
    try:
        hub, dev = spacemouse(mp, reports)
        while hub.reports:
            s = dev.read()
            assert s.is_finite()
            assert all(abs(s.position[i]) <= dev.spec.workspace_m[i] / 2 + 1e-12 for i in range(3))
            assert abs(math.fsum(c * c for c in s.quaternion) - 1.0) < 1e-9
        assert dev.parser.parsed + dev.parser.dropped == len(reports)
    finally:
        mp.undo()


# --------------------------------------------------------------------------- force board
def board(monkeypatch, reports):
    hub = FakeHid(0x1209, 0x4854, reports, serial="FS-0042")
    monkeypatch.setitem(sys.modules, "hid", hub)
    sensor = HidForceSensor(HidForceConfig(serial="FS-0042", read_timeout_ms=0))
    sensor.open()  # through hidapi's enumerate and open_path, as with the board
    return hub, sensor


def test_force_board_session_replayed_keeps_every_good_report(monkeypatch):
    reports = load_recording(DATA / "force_board_session.hex")
    hub, sensor = board(monkeypatch, reports)
    seqs = []
    while hub.reports:
        r = sensor.feed(hub.device().read(64))  # report by report, to see each sequence number
        if r is not None:
            seqs.append(r.seq)
    assert seqs == [k for k in range(30) if k not in (7, 13, 21)]
    assert sensor.dropped == {"short": 1, "crc": 1, "report_id": 1}


def test_force_board_read_drains_and_returns_the_newest_good_report(monkeypatch):
    reports = load_recording(DATA / "force_board_session.hex")
    hub, sensor = board(monkeypatch, reports)
    r = sensor.read(t=12.5)
    assert r.seq == 29 and r.t == 12.5 and r.temperature_c == pytest.approx(31.5)
    assert r.a[:3] == pytest.approx([2.9, 1.45, -0.58], abs=0.005)
    assert sensor.received == 27 and sum(sensor.dropped.values()) == 3
    assert sensor.read() is None  # nothing new


def test_force_board_unplugged_and_absent(monkeypatch):
    hub, sensor = board(monkeypatch, [])
    hub.unplug()
    assert sensor.read() is None and sensor.dropped == {"io": 1}
    with pytest.raises(ForceSensorUnavailable, match="serial 'FS-0042'.*udev"):
        HidForceSensor(HidForceConfig(serial="FS-0042")).open()


@settings(max_examples=examples(200), deadline=None)
@given(st.binary(min_size=0, max_size=80))
def test_force_board_random_bytes_are_dropped_with_a_reason(data):
    sensor = HidForceSensor(device=object())
    r = sensor.feed(data)
    if r is None:
        assert sum(sensor.dropped.values()) == 1
    else:  # only a report with a valid CRC, id, version and pair count gets through
        assert all(math.isfinite(x) for x in (*r.a, *r.b, r.temperature_c))


@settings(max_examples=examples(200), deadline=None)
@given(st.integers(0, 61 * 8 - 1), st.integers(0, 65535))
def test_force_board_any_single_bit_flip_is_caught(bit, seq):
    raw = bytearray(encode_report(seq, 123456, [1.0, -2.0, 0.5], [0.1, 0.2, 0.3]))
    parse_report(bytes(raw))
    raw[bit // 8] ^= 1 << (bit % 8)
    sensor = HidForceSensor(device=object())
    assert sensor.feed(bytes(raw)) is None

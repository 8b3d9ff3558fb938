import struct

import numpy as np
import pytest

from humantele.forcesense.contact import ContactConfig, ContactDetector
from humantele.forcesense.hid import (
    FLAG_FAULT,
    ForceSensorUnavailable,
    HidForceConfig,
    HidForceSensor,
    ReportError,
    crc16_ccitt,
    encode_report,
    parse_report,
)
from humantele.forcesense.sensors import load_force_config, make_force_sensor

# A fixture written out byte by byte: seq 0x0102, t 1 000 000 us, 3 pairs, 25.00 deg C,
# a = (10, 20, 30) mT -> 2000, 4000, 6000 counts; b = (-5, 0, 1.25) -> -1000, 0, 250.
FIXTURE = bytes.fromhex(
    "01 01 0201 40420f00 03 00 c409d007 18fc a00f 0000 7017 fa00" + "0000" * 6 + "00" * 26
)
FIXTURE += struct.pack("<H", crc16_ccitt(FIXTURE))


def test_crc_matches_the_standard_check_value():
    assert crc16_ccitt(b"123456789") == 0x29B1  # CRC-16/CCITT-FALSE check


def test_parse_fixture():
    r, flags = parse_report(FIXTURE)
    assert flags == 0 and r.seq == 0x0102 and r.t == pytest.approx(1.0)
    assert r.temperature_c == pytest.approx(25.0)
    np.testing.assert_allclose(r.a, [10.0, 20.0, 30.0])
    np.testing.assert_allclose(r.b, [-5.0, 0.0, 1.25])
    assert encode_report(0x0102, 1_000_000, r.a, r.b, 25.0) == FIXTURE


@pytest.mark.parametrize(
    "data, reason",
    [
        (FIXTURE[:40], "short"),
        (b"", "short"),
        (b"\x02" + FIXTURE[1:], "report_id"),
        (FIXTURE[:1] + b"\x07" + FIXTURE[2:], "version"),
        (FIXTURE[:20] + b"\xff" + FIXTURE[21:], "crc"),
        (encode_report(1, 0, [1, 2, 3], [1, 2, 3], flags=FLAG_FAULT), "fault"),
    ],
)
def test_bad_reports_raise_with_a_reason(data, reason):
    with pytest.raises(ReportError) as exc:
        parse_report(data)
    assert exc.value.reason == reason


class FakeDevice:
    """Stands in for hidapi's device: returns queued reports, then nothing."""

    def __init__(self, reports):
        self.reports = list(reports)

    def read(self, n, timeout):
        return list(self.reports.pop(0)) if self.reports else []

    def close(self):
        pass


def test_hid_sensor_drops_and_counts_garbage_and_keeps_the_newest_good_report():
    good1 = encode_report(1, 10, [1, 2, 3], [0, 0, 0])
    good2 = encode_report(2, 20, [4, 5, 6], [0, 0, 0])
    garbled = bytearray(good2)
    garbled[15] ^= 0xFF
    dev = FakeDevice([good1, b"\x01\x01", bytes(garbled), good2, b"\x09" * 64])
    s = HidForceSensor(HidForceConfig(), device=dev)
    r = s.read(t=5.0)
    assert r is not None and r.seq == 2 and r.t == 5.0
    np.testing.assert_allclose(r.a, [4, 5, 6])
    assert s.dropped == {"short": 1, "crc": 1, "report_id": 1} and s.received == 2
    assert s.read() is None  # nothing waiting


def test_no_hid_device_is_a_clear_error():
    sensor = make_force_sensor(HidForceConfig(serial="not-plugged-in"))
    assert isinstance(sensor, HidForceSensor)  # made, not opened: no board needed yet
    with pytest.raises(ForceSensorUnavailable, match="not open"):
        sensor.read()
    with pytest.raises(ForceSensorUnavailable, match="no force sensor board with USB id 1209:4854"):
        sensor.open()
    with pytest.raises(TypeError, match="not a force sensor configuration"):
        make_force_sensor(object())  # type: ignore[arg-type]
    assert load_force_config("hid").sensor.backend == "hid"


def test_one_press_gives_one_event_despite_noise():
    rng = np.random.default_rng(0)
    det = ContactDetector(ContactConfig(on_n=3.0, off_n=1.5, hold_s=0.03))
    t = np.arange(0, 3, 0.01)
    profile = np.clip(8 * np.sin(np.pi * (t - 0.5) / 2.0), 0, None) * ((t > 0.5) & (t < 2.5))
    events = []
    for ti, f in zip(t, profile, strict=True):
        e = det.update(ti, [0, 0, f + rng.normal(0, 0.4)])
        if e:
            events.append((e, ti))
    assert [e for e, _ in events] == ["press", "release"] and det.presses == 1
    # without hysteresis (on == off, no hold) the same signal chatters
    from humantele.forcesense import contact as cmod

    naive = cmod.ContactDetector.__new__(cmod.ContactDetector)
    naive.__init__(ContactConfig.model_construct(on_n=3.0, off_n=2.999, hold_s=0.0))
    rng = np.random.default_rng(0)
    n = sum(
        naive.update(ti, [0, 0, f + rng.normal(0, 0.4)]) == "press"
        for ti, f in zip(t, profile, strict=True)
    )
    assert n > 1


def test_contact_config_and_bad_samples():
    with pytest.raises(ValueError, match="off_n"):
        ContactConfig(on_n=2.0, off_n=3.0)
    det = ContactDetector()
    assert det.update(0.0, [np.nan, 0, 0]) is None and not det.in_contact

"""HID backend: the SpaceMouse report map on byte fixtures, garbled reports, integration."""

import math
import struct

import pytest

from humantele.haptics.devices import DeviceError, HidDevice, HidDeviceConfig
from humantele.haptics.devices.hid import (
    HidReportParser,
    VelocityIntegrator,
    load_profile,
)

S = 2.857e-4  # m/s per count in the profile
R = 2.857e-3  # rad/s per count


def rep(report_id: int, *values: int) -> bytes:
    return bytes([report_id]) + struct.pack(f"<{len(values)}h", *values)


@pytest.fixture
def parser():
    return HidReportParser(load_profile("spacemouse"))


def test_profile_ids(parser):
    assert parser.profile.vendor_ids == [0x046D, 0x256F]


def test_old_model_translation_and_rotation_reports(parser):
    # Raw HID x right, y toward the user, z down -> device x, z, -y.
    t = parser.parse(rep(1, 100, -50, 200))
    assert t == pytest.approx({"tx": 100 * S, "tz": -50 * S, "ty": -200 * S})
    r = parser.parse(rep(2, 10, 20, -30))
    assert r == pytest.approx({"rx": 10 * R, "rz": 20 * R, "ry": 30 * R})


def test_new_model_sends_six_axes_in_report_one(parser):
    v = parser.parse(rep(1, 1, 2, 3, 40, 50, 60))
    assert v == pytest.approx(
        {"tx": 1 * 0, "tz": 2 * 0, "ty": -3 * 0, "rx": 40 * R, "rz": 50 * R, "ry": -60 * R}
    )  # 1..3 counts are inside the deadband (8)
    assert len(v) == 6


def test_buttons_bitmask(parser):
    assert parser.parse(bytes([3, 0b10, 0]))["buttons"] == 2
    assert parser.parse(bytes([3, 0x01, 0x01]))["buttons"] == 257
    assert parser.parse(bytes([3, 5]))["buttons"] == 5


@pytest.mark.parametrize(
    "garbled",
    [
        b"",  # empty
        bytes([1, 0x10, 0x00, 0x20]),  # short
        bytes([9, 0, 0, 0, 0, 0, 0]),  # unknown report id
        rep(1, 30000, 0, 0),  # out of range: not a SpaceMouse value
        bytes([3]),  # buttons without payload
    ],
)
def test_garbled_reports_are_dropped_and_counted(parser, garbled):
    assert parser.parse(garbled) is None
    assert parser.dropped == 1 and parser.parsed == 0


def test_integrator_turns_rates_into_a_bounded_pose():
    it = VelocityIntegrator((0.16, 0.12, 0.12))
    it.update({"tx": 0.05, "rz": math.pi / 2})
    for _ in range(100):
        it.step(0.01)  # 1 s
    assert it.position[0] == pytest.approx(0.05)
    x, y, z, w = it.quaternion
    assert 2 * math.atan2(z, w) == pytest.approx(math.pi / 2, abs=1e-9)
    for _ in range(300):
        it.step(0.01)
    assert it.position[0] == pytest.approx(0.08)  # held at the workspace edge


def test_device_integrates_fed_reports_and_ignores_garbage():
    dev = HidDevice(HidDeviceConfig())
    assert dev.feed(rep(1, 350, 0, 0))
    assert not dev.feed(b"\x01\x02")
    assert dev.parser.dropped == 1
    dev.integrator.step(0.1)
    assert dev.integrator.position[0] == pytest.approx(350 * S * 0.1)
    dev.command_force((1.0, 0.0, 0.0))  # no force output: accepted and ignored


def test_no_device_is_a_clear_error(monkeypatch):
    import hid

    monkeypatch.setattr(hid, "enumerate", lambda *a: [])
    dev = HidDevice(HidDeviceConfig())
    with pytest.raises(DeviceError, match=r"no 3Dconnexion SpaceMouse found.*0x046d, 0x256f"):
        dev.open()
    with pytest.raises(DeviceError, match="not open"):
        dev.read()


def test_profile_field_past_report_end_is_refused(tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text(
        "[[reports]]\nid = 1\nlength = 3\nfields = [{ slot = 'tx', offset = 2, type = 'i16le' }]\n"
    )
    with pytest.raises(ValueError, match="runs past"):
        HidReportParser(load_profile(str(f)))

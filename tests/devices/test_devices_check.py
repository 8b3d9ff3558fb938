"""``humantele devices check`` on the sim devices, the fake libHD, a replayed force board and a
headset that is not there."""

import json
import socket
import sys
from pathlib import Path

import pytest
from fake_hidapi import FakeHid, load_recording

from humantele.cli import main
from humantele.haptics.devices import TouchXConfig

DATA = Path(__file__).parent / "data"


def run_check(capsys, *args: str) -> tuple[int, dict]:
    code = main(["devices", "check", "--samples", "5", "--json", *args])
    return code, json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_sim_devices_all_give_samples(capsys):
    code, out = run_check(capsys)
    assert code == 0
    by = {c["device"]: c for c in out["checks"]}
    assert set(by) == {"haptic device", "tracker camera", "force sensor"}
    assert all(c["ok"] and c["backend"] == "sim" for c in by.values())
    assert by["haptic device"]["figures"]["samples"] == 5
    assert by["tracker camera"]["figures"]["size"] == [512, 512]
    assert by["tracker camera"]["figures"]["tracked"] >= 3
    assert by["force sensor"]["figures"]["pairs"] == 3
    code = main(["devices", "check", "--samples", "3", "--only", "haptic"])
    assert code == 0 and "[ok  ] haptic device (sim): 3 states" in capsys.readouterr().out


def test_touchx_on_the_fake_openhaptics_library(capsys, tmp_path, fake_hd):
    path, fake = fake_hd
    fake.fake_reset(0)  # the fake's own 1 kHz servo thread, as the real driver
    key = "backend" if "backend" in TouchXConfig.model_fields else "kind"
    cfg = tmp_path / "expert.toml"
    cfg.write_text(f'[servo.device]\n{key} = "touchx"\nlibrary = "{path}"\n')
    code, out = run_check(capsys, "--expert-config", str(cfg), "--only", "haptic")
    (c,) = out["checks"]
    assert code == 0 and c["ok"] and c["backend"] == "touchx", c
    assert "calibration ok" in c["summary"] and "Touch X (fake)" in c["summary"]
    fake.fake_reset(1)


def test_force_board_replayed_and_hid_listing(capsys, tmp_path, monkeypatch):
    hub = FakeHid(0x1209, 0x4854, load_recording(DATA / "force_board_session.hex"))
    monkeypatch.setitem(sys.modules, "hid", hub)
    cfg = tmp_path / "follower.toml"
    cfg.write_text('[sensing.force.sensor]\nbackend = "hid"\nread_timeout_ms = 0\n')
    code, out = run_check(capsys, "--follower-config", str(cfg), "--only", "force",
                          "--only", "hid")  # fmt: skip
    (c,) = out["checks"]
    assert code == 0 and c["ok"] and c["backend"] == "hid"
    assert c["figures"]["dropped"] == {"short": 1, "crc": 1, "report_id": 1}
    assert out["hid"][0]["vendor_id"] == "0x1209" and out["hid"][0]["path"] == "/dev/hidraw7"


def test_missing_devices_fail_with_their_own_message(capsys, tmp_path, monkeypatch):
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    monkeypatch.setitem(sys.modules, "hid", FakeHid(0x1, 0x2, []))
    cfg = tmp_path / "follower.toml"
    cfg.write_text(f'[sensing.camera]\nbackend = "hl2ss"\nhost = "127.0.0.1"\nport = {port}\n'
                   '[sensing.force.sensor]\nbackend = "hid"\n')  # fmt: skip
    code = main(["devices", "check", "--follower-config", str(cfg), "--only", "tracker",
                 "--only", "force"])  # fmt: skip
    text = capsys.readouterr().out
    assert code == 1
    assert "[FAIL] tracker camera (hl2ss): hl2ss: cannot reach the HoloLens 2" in text
    assert "[FAIL] force sensor (hid): no force sensor board with USB id 1209:4854" in text


@pytest.mark.parametrize("argv", [["devices"], ["devices", "check", "--samples", "x"]])
def test_bad_command_lines(argv, capsys):
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    assert code == 2

"""Regenerate the HID byte recordings replayed by tests/devices/test_hid_replay.py.

No SpaceMouse or force board is attached to the build machine, so these "recordings" are
written in each device's report layout (the spacemouse HID profile, docs/force_sensor_hid.md)
from a short scripted session, with the faults seen on real USB links mixed in (short reads,
unknown report ids, out-of-range axes, bad CRC). One report per line, hex; '#' comments.
Run: python3 tests/devices/data/make_recordings.py
"""

import struct
from pathlib import Path

from humantele.forcesense.hid import encode_report

HERE = Path(__file__).parent


def rep(report_id: int, *values: int) -> str:
    return (bytes([report_id]) + struct.pack(f"<{len(values)}h", *values)).hex()


def spacemouse() -> list[str]:
    out = ["# SpaceMouse (old model): push right, press down, twist, button 1, release"]
    out += [rep(1, 300, 0, 0)] * 20 + [rep(2, 0, 0, 0)] * 2
    out += ["# short read", "01 2c01".replace(" ", "")]
    out += [rep(1, 0, 0, 250)] * 20  # raw z down (pushing the cap) -> device -y
    out += ["# unknown report id", rep(9, 1, 2, 3)]
    out += [rep(1, 0, 0, 0), rep(2, 0, 0, 200)] * 10  # raw rz -> device ry (negated)
    out += ["# out of range (not a SpaceMouse value)", rep(1, 30000, 0, 0)]
    out += ["# button 1 down then up", bytes([3, 1]).hex(), bytes([3, 0]).hex()]
    out += [rep(1, 0, 0, 0), rep(2, 0, 0, 0)]
    return out


def force_board() -> list[str]:
    out = ["# force board: 30 reports of a press, with corrupted ones mixed in"]
    for k in range(30):
        a = [0.1 * k, 0.05 * k, -0.02 * k]
        b = [0.0, 0.01 * k, 0.02 * k]
        raw = encode_report(k, 1000 * k, a, b, temperature_c=31.5)
        if k == 7:
            out += ["# short read", raw[:40].hex()]
            continue
        if k == 13:
            out += [
                "# one bit flipped in transit",
                (raw[:20] + bytes([raw[20] ^ 0x04]) + raw[21:]).hex(),
            ]
            continue
        if k == 21:
            out += ["# wrong report id", (b"\x02" + raw[1:]).hex()]
            continue
        out.append(raw.hex())
    return out


if __name__ == "__main__":
    (HERE / "spacemouse_session.hex").write_text("\n".join(spacemouse()) + "\n")
    (HERE / "force_board_session.hex").write_text("\n".join(force_board()) + "\n")

"""The tracker's and the force board's replays of one device recording stay together (issue 34:
`humantele demo --replay` stayed at "press right (3 of 4)" on a loaded machine, its presses
refused as "only 1 mm from the xiphoid": the frames were paced from the sensing's first read,
the board from its open, each looped at its own length, so a press came with another place's
tip). Both now run on the recording's timeline from the first open, each loop the recording's
span. On a clock the test drives by hand."""

from __future__ import annotations

import numpy as np
import pytest

from humantele.forcesense.hid import encode_report
from humantele.forcesense.replay import ReplayForceConfig, ReplayForceSensor
from humantele.recording.device_file import AHAT_FRAME, HID_REPORT, DeviceRecordingWriter
from humantele.tracking.hl2ss_protocol import AHAT_HEIGHT, AHAT_WIDTH
from humantele.tracking.replay_source import ReplayFrameConfig, ReplayFrameSource

T0 = 1000.0  # the recorder's clock at the board's first report (s)
CAMERA_LATE_S = 0.5  # the headset's stream came this long after the board's first report
TS0 = 133_000_000_000  # hl2ss ticks (100 ns) of the first frame
FRAMES, FRAME_S = 30, 0.1
REPORTS, REPORT_S = 300, 0.01


class Clock:
    def __init__(self) -> None:
        self.t = 5.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.t += dt


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """3 s of the board (100 Hz) and 2.9 s of frames (10 Hz, from 0.5 s in), each received
    1-3 ms after it was sent."""
    path = tmp_path_factory.mktemp("together") / "clinic.mcap"
    writer = DeviceRecordingWriter(path)
    zeros = np.zeros((AHAT_HEIGHT, AHAT_WIDTH), np.uint16)
    rng = np.random.default_rng(3)
    items = [(T0 + k * REPORT_S + rng.uniform(0.001, 0.003), "r", k) for k in range(REPORTS)]
    items += [(T0 + CAMERA_LATE_S + j * FRAME_S + rng.uniform(0.001, 0.003), "f", j)
              for j in range(FRAMES)]  # fmt: skip
    for t, kind, i in sorted(items):
        if kind == "r":
            report = encode_report(i, 7_000_000 + int(i * REPORT_S * 1e6), [0.1] * 3, [0.2] * 3)
            writer.write(HID_REPORT, t, {"t_receive": t}, {"report": report})
        else:
            fields = {"t_receive": t, "timestamp": TS0 + i * int(FRAME_S * 1e7),
                      "sensor_ticks": i, "seq": i}  # fmt: skip
            writer.write(AHAT_FRAME, t, fields, {"depth": zeros, "ab": zeros})
    writer.close()
    return path


def frame_time(ts: int) -> float:
    """A frame's send time on the recorder's clock (s)."""
    return T0 + CAMERA_LATE_S + (ts - TS0) / 1e7


def test_frames_and_presses_stay_together_across_a_late_first_read_and_loops(recording):
    clock = Clock()
    camera = ReplayFrameSource(ReplayFrameConfig(file=str(recording), loop=True), clock,
                               clock.sleep)  # fmt: skip
    board = ReplayForceSensor(ReplayForceConfig(file=str(recording), loop=True,
                                                read_timeout_ms=0), clock, clock.sleep)  # fmt: skip
    camera.open()  # as the sensing process opens them: the camera, then the board
    board.open()
    clock.t += 2.03  # the sensing's first read comes 2 s later (a slow start under load)
    gaps, loops = [], 0
    try:
        while loops < 4:
            frame = camera.read()
            assert frame is not None
            if frame.seq > 1 and camera.last_timestamp == TS0:
                loops += 1
            reading = None
            while (r := board.read()) is not None:  # the reader drains what is due
                reading = r
            if reading is None:
                continue
            gaps.append(T0 + reading.seq * REPORT_S - frame_time(camera.last_timestamp))
    finally:
        camera.close()
        board.close()
    assert camera.dropped["stale"] >= 19  # the late first read skipped to the frame due
    assert len(gaps) > 2 * FRAMES
    # the board's newest report is the one sent with the frame (within a report's period),
    # in every loop (the first read's frame was due 30 ms before it: the newest due then)
    assert abs(gaps[0] - 0.03) <= REPORT_S + 0.004
    assert max(abs(g) for g in gaps[1:]) <= REPORT_S + 0.004, (min(gaps), max(gaps))


def test_one_replay_alone_starts_at_its_own_first_sample(recording):
    """A replay of the board alone (the tests' and a real camera's case): its first report is
    due at once, whatever the frames did."""
    clock = Clock()
    board = ReplayForceSensor(ReplayForceConfig(file=str(recording)), clock, clock.sleep)
    board.open()
    assert board._dev.read(64, 0) and clock.t == 5.0
    board.close()

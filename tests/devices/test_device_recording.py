"""Record a clinic once, replay it as a test (issue 18 §4).

The clinic is made of replayed devices (an hl2ss replay server thread serving simulated AHAT
frames with rig poses and the calibration, the force board's reports through the replayed
``hid`` module, two small AVI files through OpenCV); ``humantele devices record`` records
them; the ``replay`` backends read the file back into the probe sensing, which must place the
probe where the simulation put it. A truncated file replays its intact part and says so; a
foreign one is refused in one line."""

from __future__ import annotations

import importlib.util
import io
import logging
import math
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from humantele.devices import record as record_cmd
from humantele.follower.sensing import ProbeSensing, SensingConfig
from humantele.follower.sensing_devices import real_sensing_devices
from humantele.forcesense.base import ForceSensorUnavailable
from humantele.forcesense.calibration import calibrate_sim
from humantele.forcesense.hid import encode_report
from humantele.forcesense.replay import ReplayForceConfig, ReplayForceSensor
from humantele.forcesense.sim import SimForceConfig, SimForceSensor
from humantele.geometry import Pose, quat_from_axis_angle
from humantele.recording.device_file import (
    AHAT_CALIBRATION,
    AHAT_FRAME,
    HID_REPORT,
    VIDEO,
    DeviceRecording,
)
from humantele.recording.replay_timeline import DeviceClock
from humantele.recording.writer import McapLog
from humantele.tracking.frames import FrameSourceUnavailable
from humantele.tracking.hl2ss_calibration import Hl2ssAhatCalibration
from humantele.tracking.hl2ss_protocol import AHAT_DEPTH_MASK
from humantele.tracking.hl2ss_replay import AhatRecord, Hl2ssReplayServer, load_mcap_records
from humantele.tracking.hl2ss_replay import main as hl2ss_replay_main
from humantele.tracking.replay_source import TICKS_PER_S, ReplayFrameConfig, ReplayFrameSource
from humantele.tracking.sim import SimFrameConfig, SimFrameSource, default_sim_pose
from humantele.tracking.tool import load_tool
from humantele.video.base import VideoSourceError, VideoSourceUnavailable
from humantele.video.replay_source import ReplayVideoConfig, ReplayVideoSource
from humantele.video.sources import make_video_source

HERE = Path(__file__).parent
FRAMES = 36  # 0.8 s at 45 Hz
TS0, DTS = 50_000_000, 222_222  # hl2ss timestamps, 100 ns ticks
T_RIG_CAMERA = Pose([0.003, -0.08, -0.01], quat_from_axis_angle([0.0, 1.0, 0.2], 0.15))
FORCE_PROBE_N = np.array([0.5, -0.3, 6.0])  # the press the board reports (probe frame)
VIDEO_FRAMES = 12

PAIRING = "13572468"  # the headset page's pairing code the follower is given


def _clinic(out: Path) -> dict:
    """The simulated data the devices deliver: AHAT records with rig poses (the headset
    moving), the calibration, the board's reports (~100 Hz), two AVIs; the truth."""
    tool = load_tool("probe_default")
    camera = SimFrameSource(SimFrameConfig(seed=3), tool)
    base = default_sim_pose()
    records, truth = [], {}
    for k in range(FRAMES):
        wob = Pose(
            [0.01 * math.sin(k / 6), 0.006 * math.cos(k / 5), 0.0],
            quat_from_axis_angle([0.0, 0.0, 1.0], 0.1 * math.sin(k / 7)),
        )
        T_camera_probe = wob @ base
        rig = Pose(
            [0.2 + 0.002 * k, 1.4, -0.1], quat_from_axis_angle([1.0, 0.3, 0.0], -1.2 + 0.004 * k)
        )
        frame = camera.render(T_camera_probe, k / 45)
        records.append(AhatRecord(TS0 + k * DTS, frame.depth_mm, frame.ir, 1000 + k, rig))
        truth[TS0 + k * DTS] = (rig @ T_RIG_CAMERA @ T_camera_probe).apply(tool.tip)
    cal = Hl2ssAhatCalibration.pinhole(camera.intrinsics, T_RIG_CAMERA)
    cal.save(out / "ahat_calibration.json")
    board = SimForceSensor(SimForceConfig())
    board.set_force(FORCE_PROBE_N)
    reports = []
    for j in range(2 * FRAMES + 10):
        r = board.read(j / 100)
        reports.append(encode_report(j, int(r.t * 1e6), r.a, r.b, r.temperature_c))
    reports.insert(5, b"\x07" + bytes(63))  # a report the parser drops: recorded as read
    (out / "board.hex").write_text("\n".join(r.hex() for r in reports) + "\n")
    calibrate_sim(SimForceSensor(SimForceConfig())).save(out / "board_calibration.json")
    for name, (w, h) in {"us": (96, 64), "pov": (80, 48)}.items():
        video = cv2.VideoWriter(
            str(out / f"{name}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 20, (w, h)
        )
        for k in range(VIDEO_FRAMES):
            img = np.full((h, w, 3), 40 + 10 * k, np.uint8)
            cv2.circle(img, (w // 2 + 2 * k, h // 2), 12, (200, 220, 240), -1)
            video.write(img)
        video.release()
    return {"records": records, "truth": truth, "reports": reports, "calibration": cal}


def _follower_toml(rec: Path, port: int, clinic: str = "devices") -> str:
    return f"""
[follower.clinic]
backend = "{clinic}"
[follower.video.us]
backend = "opencv"
device = "{rec / "us.avi"}"
pixel_spacing_mm = [0.3, 0.3]
[follower.video.pov]
backend = "opencv"
device = "{rec / "pov.avi"}"
[sensing.camera]
backend = "hl2ss"
ab_profile = "raw"
host = "127.0.0.1"
port = {port}
calibration_file = "{rec / "ahat_calibration.json"}"
download_calibration = false
read_timeout_s = 0.2
[sensing.force]
calibration_file = "{rec / "board_calibration.json"}"
[sensing.force.sensor]
backend = "hid"
"""


def _replay_hid_module():
    """tests/devices/replay_hid/hid.py as the ``hid`` module: the board replayed at 100 Hz from
    the .hex file ``HUMANTELE_HID_REPLAY`` names."""
    spec = importlib.util.spec_from_file_location("hid", HERE / "replay_hid" / "hid.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A recording of the replayed clinic, made once by `devices record` in this process."""
    out = tmp_path_factory.mktemp("clinic")
    clinic = _clinic(out)
    progress = io.StringIO()
    with (
        pytest.MonkeyPatch.context() as mp,
        Hl2ssReplayServer([clinic["records"]], clinic["calibration"], rate_hz=45) as server,
    ):
        mp.setenv("HUMANTELE_HID_REPLAY", str(out / "board.hex"))
        mp.setitem(sys.modules, "hid", _replay_hid_module())
        cfg = out / "follower.toml"
        cfg.write_text(_follower_toml(out, server.port))
        counts, notes = record_cmd.record(
            cfg,
            out / "clinic.mcap",
            duration=60,
            progress=progress,
            until=lambda c: (
                c["ahat"] >= FRAMES
                and c["force"] >= len(clinic["reports"])
                and min(c["us"], c["pov"]) >= VIDEO_FRAMES
            ),
        )
    return {
        **clinic,
        "dir": out,
        "file": out / "clinic.mcap",
        "counts": counts,
        "notes": notes,
        "progress": progress.getvalue(),
    }


def _sensing_config(d: Path, file: Path, pace: bool = True) -> SensingConfig:
    return SensingConfig.model_validate(
        {
            "camera": {"backend": "replay", "file": str(file), "pace": pace, "newest": False},
            "force": {
                "calibration_file": str(d / "board_calibration.json"),
                "sensor": {"backend": "replay", "file": str(file), "pace": pace},
            },
        }
    )


def test_record_writes_every_device_into_one_complete_mcap(recorded):
    counts = recorded["counts"]
    assert counts["ahat"] == FRAMES and counts["force"] == len(recorded["reports"])
    assert counts["us"] == counts["pov"] == VIDEO_FRAMES
    line = recorded["progress"].strip().splitlines()[-1].split("\r")[-1]
    assert "ahat" in line and "force" in line and line.endswith("MB")
    rec = DeviceRecording(recorded["file"])
    assert rec.complete and rec.problem is None
    got = {t: [] for t in (AHAT_CALIBRATION, AHAT_FRAME, HID_REPORT, *VIDEO.values())}
    for s in rec.samples(set(got)):
        got[s.topic].append(s)
    assert len(got[AHAT_CALIBRATION]) == 1
    cal = Hl2ssAhatCalibration.from_bytes(got[AHAT_CALIBRATION][0].blobs["calibration"])
    assert np.array_equal(cal.extrinsics, recorded["calibration"].extrinsics)
    # AHAT frames as hl2ss sent them: timestamps, ticks, images, the pose matrix's bytes
    for s, r in zip(got[AHAT_FRAME], recorded["records"], strict=True):
        assert s.fields["timestamp"] == r.timestamp and s.fields["sensor_ticks"] == r.sensor_ticks
        assert np.array_equal(
            s.blobs["depth"], np.where(r.depth_mm >= AHAT_DEPTH_MASK, 0, r.depth_mm)
        )
        assert np.array_equal(s.blobs["ab"], r.ab)
        sent = np.frombuffer(r.packet(1)[-64:], "<f4").reshape(4, 4)  # hl2ss's bytes
        assert s.blobs["pose"].tobytes() == sent.tobytes()
    # the raw HID reports, the bad one too, in order, with increasing receive times
    assert [s.blobs["report"] for s in got[HID_REPORT]] == recorded["reports"]
    assert np.all(np.diff([s.fields["t_receive"] for s in got[HID_REPORT]]) >= 0)
    us = got[VIDEO["us"]][0]
    assert us.fields["pixel_spacing_mm"] == [0.3, 0.3] and us.fields["width"] == 96


def test_a_device_that_stops_ends_its_track_and_the_others_go_on(tmp_path):
    """A video source that stops (a pulled cable) ends its track, said in the notes; the
    force board goes on being recorded."""
    from fake_hidapi import FakeHid

    from humantele.forcesense.hid import HidForceSensor
    from humantele.video.base import VideoFrame, VideoSource

    class Stops(VideoSource):
        size, fps = (8, 8), 30.0

        def open(self) -> None:
            self.n = 0

        def read(self) -> VideoFrame:
            self.n += 1
            if self.n > 2:
                raise VideoSourceError("capture card unplugged")
            return VideoFrame(np.zeros((8, 8, 3), np.uint8), self.n, time.monotonic())

        def close(self) -> None:
            pass

    reports = [encode_report(k, k * 10_000, [0.1] * 3, [0.2] * 3) for k in range(20)]
    sensor = HidForceSensor(device=FakeHid(0x1209, 0x4854, reports).device())
    plan = record_cmd.DevicePlan([("us", Stops(), "video"), ("force", sensor, "hid")])
    writer = record_cmd.DeviceRecordingWriter(tmp_path / "r.mcap")
    rec = record_cmd.DeviceRecorder(plan, writer)
    rec.open()
    rec.start()
    deadline = time.monotonic() + 30
    while (rec.counts["force"] < 20 or not rec.notes) and time.monotonic() < deadline:
        time.sleep(0.01)
    rec.finish()
    writer.close()
    assert rec.counts == {"us": 2, "force": 20}
    assert rec.notes == ["us: stopped (capture card unplugged)"]
    assert DeviceRecording(tmp_path / "r.mcap").complete


def test_replay_backends_place_the_probe_where_the_simulation_put_it(recorded):
    cfg = _sensing_config(recorded["dir"], recorded["file"])
    tool = load_tool("probe_default")
    sensing = ProbeSensing(cfg, tool, real_sensing_devices(cfg, tool))
    errors, forces = [], []
    try:
        assert sensing.source.calibration is not None  # from the recording
        for _ in range(FRAMES + 3):
            m = sensing.measure(time.monotonic())
            if m.tip_world is not None:
                errors.append(
                    np.linalg.norm(m.tip_world - recorded["truth"][sensing.source.last_timestamp])
                )
            forces.append(m.force_probe)
        assert sensing.source.dropped.get("end", 0) >= 1  # the whole file was read
        assert sensing.sensor.dropped.get("report_id") == 1  # the real parser saw the bad one
    finally:
        sensing.close()
    assert len(errors) >= FRAMES - 2, "the replayed frames did not place the probe"
    assert max(errors) < 2e-3, errors
    assert np.linalg.norm(forces[-1] - FORCE_PROBE_N) < 0.5  # the board's press, calibrated


def test_replay_is_paced_at_the_recorded_times(recorded):
    """With a fake clock: the frames come at their hl2ss timestamps' spacing, the reports at
    their receive times', counted from the first read."""
    now = [100.0]

    def sleep(dt: float) -> None:
        now[0] += dt

    src = ReplayFrameSource(ReplayFrameConfig(file=str(recorded["file"])), lambda: now[0], sleep)
    src.open()
    times = []
    while (f := src.read()) is not None:
        times.append(f.t)
    src.close()
    assert len(times) == FRAMES and src.dropped.get("stale", 0) == 0
    # At the hl2ss timestamps' spacing, but where the device clock was anchored again on a
    # frame received sooner than that (the recorder's first read came late: the server's
    # queue then came quicker than 45 Hz); never back in time.
    gaps = np.diff(times)
    assert np.all(gaps >= 0.0), gaps
    assert np.sum(~np.isclose(gaps, DTS / 1e7, atol=1e-9)) <= src._device.reanchored, gaps
    # a reader 10 frame periods late skips to the newest frame due, as the hl2ss client does
    src = ReplayFrameSource(ReplayFrameConfig(file=str(recorded["file"])), lambda: now[0], sleep)
    src.open()
    first = src.read()
    now[0] += 10 * DTS / 1e7 + 1e-4
    late = src.read()
    src.close()
    # the newest due then, by the times the first reader met (10 periods, or one more where
    # the device clock was anchored again on a recording read late)
    k = max(i for i, t in enumerate(times) if t - times[0] <= 10 * DTS / 1e7 + 1e-4)
    assert k >= 10
    assert first.device_time_s == pytest.approx(TS0 / 1e7)
    assert late.device_time_s == pytest.approx((TS0 + k * DTS) / 1e7)
    assert src.dropped["stale"] == k - 1
    now[0] = 0.0
    sensor = ReplayForceSensor(ReplayForceConfig(file=str(recorded["file"])), lambda: now[0], sleep)
    sensor.open()
    got = sensor._dev.read(64, 0)  # the first report is due at once
    assert got and now[0] == 0.0
    assert sensor._dev.read(64, 0) == []  # the next is not due yet: an idle board
    sensor.close()


def test_replay_loops_and_video_frames_come_back(recorded):
    src = ReplayFrameSource(ReplayFrameConfig(file=str(recorded["file"]), pace=False, loop=True))
    src.open()
    stamps = [src.read() and src.last_timestamp for _ in range(FRAMES + 2)]
    src.close()
    assert stamps[FRAMES] == stamps[0] == TS0
    video = make_video_source(ReplayVideoConfig(file=str(recorded["file"]), pace=False))
    video.open()
    assert video.size == (96, 64)
    cap = cv2.VideoCapture(str(recorded["dir"] / "us.avi"))
    for _ in range(recorded["counts"]["us"]):
        frame = video.read()
        ok, want = cap.read()
        assert ok and frame.pixel_spacing_mm == (0.3, 0.3)
        assert np.mean(np.abs(frame.image.astype(int) - want.astype(int))) < 4  # JPEG
    with pytest.raises(VideoSourceError, match="ended"):
        video.read()
    video.close()


def test_truncated_file_replays_its_intact_part_and_says_so(recorded, tmp_path, caplog):
    data = recorded["file"].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    caplog.set_level(logging.WARNING, logger="humantele.devices.replay")
    src = ReplayFrameSource(ReplayFrameConfig(file=str(cut), pace=False))
    src.open()
    n = 0
    while src.read() is not None:
        n += 1
    src.close()
    assert 0 < n < FRAMES
    assert n >= FRAMES // 2 - 4  # about its first half (a chunk or two is lost at the cut)
    assert src.problem and "truncated" in src.problem
    assert any("truncated" in r.getMessage() for r in caplog.records)
    records, cal, problem = load_mcap_records(cut)  # the hl2ss replay server's view
    assert len(records) == n and cal is not None and "truncated" in problem
    sensor = ReplayForceSensor(ReplayForceConfig(file=str(cut), pace=False))
    sensor.open()  # the reports of the first half are there
    assert sensor.read() is not None
    sensor.close()


def test_replay_backends_are_a_real_clinic_s_devices_in_the_follower_config(tmp_path):
    from humantele.follower.config import FollowerConfig

    rec = str(tmp_path / "clinic.mcap")
    video = {"us": {"backend": "replay", "file": rec}, "pov": {"backend": "replay", "file": rec}}
    FollowerConfig.model_validate(  # the replay gives the scale it recorded
        {"clinic": {"backend": "devices"}, "video": {"enabled": True, **video}}
    )
    with pytest.raises(ValueError, match="pixel_spacing_mm"):  # a capture card must say it
        FollowerConfig.model_validate({"clinic": {"backend": "devices"}, "video": {
            "enabled": True, "us": {"backend": "opencv"}, "pov": video["pov"]}})  # fmt: skip
    video["us"].update(pixel_spacing_mm=[0.3, 0.3], depth_origin_row=4.0)
    c = FollowerConfig.model_validate(
        {"clinic": {"backend": "devices"}, "video": {"enabled": True, **video}}
    )
    assert (c.video.us.track, c.video.pov.track) == ("us", "pov")
    s = _sensing_config(tmp_path, Path(rec))
    assert (s.camera.backend, s.force.sensor.backend) == ("replay", "replay")


@pytest.mark.parametrize("kind", ["random bytes", "session recording", "empty"])
def test_a_foreign_file_is_refused_in_one_line(tmp_path, kind, capsys):
    path = tmp_path / "foreign.mcap"
    if kind == "random bytes":
        path.write_bytes(np.random.default_rng(1).bytes(5000))
    elif kind == "empty":
        path.write_bytes(b"")
    else:
        log = McapLog(path, {"role": "follower", "session_id": "x"}, fsync=False)
        log.close()
    makers = [
        (FrameSourceUnavailable, lambda: ReplayFrameSource(ReplayFrameConfig(file=str(path)))),
        (ForceSensorUnavailable, lambda: ReplayForceSensor(ReplayForceConfig(file=str(path)))),
        (VideoSourceUnavailable, lambda: ReplayVideoSource(ReplayVideoConfig(file=str(path)))),
    ]
    for error, make in makers:
        with pytest.raises(error) as info:
            make().open()
        msg = str(info.value)
        assert "\n" not in msg and "foreign.mcap" in msg
        assert "not a device recording" in msg or "not an MCAP" in msg, msg
    assert hl2ss_replay_main([str(path)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "device recording" in err


def test_record_refuses_the_simulated_clinic(tmp_path, capsys):
    cfg = tmp_path / "follower.toml"
    cfg.write_text(_follower_toml(tmp_path, 9, clinic="sim"))
    from humantele.cli import main

    assert (
        main(
            ["devices", "record", "--follower-config", str(cfg), "--out", str(tmp_path / "x.mcap")]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "simulator" in err
    assert not (tmp_path / "x.mcap").exists()


@pytest.mark.e2e
@pytest.mark.slow
def test_cli_records_from_an_hl2ss_server_serving_the_mcap_and_ends_cleanly_on_ctrl_c(
    recorded, tmp_path
):
    """The hl2ss replay server (its own process) serves the recording's frames as the headset
    sent them; `humantele devices record` (its own process, the replayed ``hid`` module)
    records them; Ctrl-C ends it with a complete file holding the same frames."""
    server = subprocess.Popen(
        [sys.executable, "-m", "humantele.tracking.hl2ss_replay", str(recorded["file"])],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    rec = None
    try:
        line = server.stdout.readline()
        port = int(line.rsplit(":", 1)[1].split()[0]) if ":" in line else 0
        assert port > 0, f"the replay server said {line!r}: {server.stderr.read()}"
        cfg = tmp_path / "follower.toml"
        cfg.write_text(_follower_toml(recorded["dir"], port))
        env = dict(
            os.environ,
            HUMANTELE_HID_REPLAY=str(recorded["dir"] / "board.hex"),
            PYTHONPATH=os.pathsep.join(
                [str(HERE / "replay_hid"), os.environ.get("PYTHONPATH", "")]
            ),
        )
        out = tmp_path / "again.mcap"
        rec = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "humantele",
                "devices",
                "record",
                "--follower-config",
                str(cfg),
                "--out",
                str(out),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=env,
            start_new_session=True,
        )
        seen = b""
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and rec.poll() is None:  # until 10 frames are in
            if not select.select([rec.stderr], [], [], 1.0)[0]:
                continue
            chunk = os.read(rec.stderr.fileno(), 4096)
            seen += chunk
            last = seen.split(b"\r")[-1].split()
            if b"ahat" in last and int(last[last.index(b"ahat") + 1]) >= 10:
                break
        rec.send_signal(signal.SIGINT)
        out_text, err_text = rec.communicate(timeout=30)
    finally:
        for p in (rec, server):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        server.communicate(timeout=10)
    assert rec.returncode == 0, (seen + err_text).decode(errors="replace")
    assert b"recorded" in out_text
    again = DeviceRecording(out)
    assert again.complete
    first = {
        s.fields["timestamp"]: s for s in DeviceRecording(recorded["file"]).samples({AHAT_FRAME})
    }
    frames = list(again.samples({AHAT_FRAME}))
    assert len(frames) >= 10
    for s in frames:
        o = first[s.fields["timestamp"]]
        assert np.array_equal(s.blobs["ab"], o.blobs["ab"])
        assert np.array_equal(s.blobs["pose"], o.blobs["pose"])  # the matrix's exact bytes


@pytest.mark.e2e
@pytest.mark.slow
async def test_follower_runs_on_the_recording_with_no_simulator(recorded, tmp_path):
    """The follower daemon (its own process, sensing child, video child) on the replay
    backends: it places the probe where the simulation put it, and loads no simulator."""
    import asyncio
    import json

    import aiohttp

    rec = recorded["file"]
    cfg = tmp_path / "follower.toml"
    cfg.write_text(f"""
[follower]
state_dir = "{tmp_path / "state"}"
[follower.clinic]
backend = "devices"
[follower.link]
signaling_url = "ws://127.0.0.1:9/ws"
realtime_priority = 0
[follower.feed]
host = "127.0.0.1"
port = 0
tls = false
[follower.video]
enabled = true
[follower.video.us]
backend = "replay"
file = "{rec}"
loop = true
pixel_spacing_mm = [0.3, 0.3]
depth_origin_row = 4.0
[follower.video.pov]
backend = "replay"
file = "{rec}"
loop = true
[sensing.camera]
backend = "replay"
file = "{rec}"
loop = true
[sensing.force]
calibration_file = "{recorded["dir"] / "board_calibration.json"}"
[sensing.force.sensor]
backend = "replay"
file = "{rec}"
loop = true
""")
    stats = tmp_path / "stats.json"
    follower = subprocess.Popen(
        [sys.executable, "-m", "humantele", "follower", "--config", str(cfg),
         "--duration", "60", "--stats-file", str(stats)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        env=dict(os.environ, HUMANTELE_PAIRING_CODE=PAIRING),  # the feed wants it
    )  # fmt: skip
    probes, figures, killed = [], {}, False
    try:
        url = None
        for _ in range(600):  # the feed's address, once it serves (60 s at most)
            if stats.exists():
                try:
                    url = json.loads(stats.read_text()).get("feed_url")
                except ValueError:
                    pass
            if url or follower.poll() is not None:
                break
            await asyncio.sleep(0.1)
        assert url, f"no feed: {follower.communicate(timeout=10)}"
        async with aiohttp.ClientSession() as s, s.ws_connect(f"{url}?code={PAIRING}") as ws:
            deadline = asyncio.get_running_loop().time() + 60
            while len(probes) < 20 and asyncio.get_running_loop().time() < deadline:
                try:
                    msg = await ws.receive_json(timeout=5)
                except (ValueError, TimeoutError, TypeError):
                    continue
                if msg.get("type") == "probe" and msg.get("tracking") == "tracked":
                    probes.append(msg)
        for _ in range(300):  # each child reports its modules once it runs (the stats file
            # is written now and then: the one read may predate the sensing child's report)
            figures = json.loads(stats.read_text())
            mods = figures.get("simulator_modules", {})
            if mods.get("video") is not None and mods.get("sensing") is not None:
                break
            await asyncio.sleep(0.1)
    finally:
        if follower.poll() is None:
            os.killpg(follower.pid, signal.SIGTERM)
        try:
            out, err = follower.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            killed = True
            os.killpg(follower.pid, signal.SIGKILL)
            out, err = follower.communicate(timeout=10)
    assert len(probes) >= 20, err[-3000:]
    tips = np.array(list(recorded["truth"].values()))
    errs = [np.min(np.linalg.norm(tips - np.array(p["position"]), axis=1)) for p in probes]
    assert float(np.median(errs)) < 2e-3, errs
    assert figures["simulator_modules"]["daemon"] == []
    assert figures["simulator_modules"]["sensing"] == []
    assert figures["simulator_modules"]["video"] == [], figures["simulator_modules"]
    assert not killed, "the follower outlived its SIGTERM by 30 s"


def test_a_pause_in_the_recording_does_not_hold_one_read(recorded):
    """A read waits at most MAX_WAIT_S for a frame's recorded time (a recorded stall must not
    hold the sensing process, which the follower would take as hung); the frame comes later."""
    from humantele.tracking.replay_source import MAX_WAIT_S

    now = [100.0]
    slept = []

    def sleep(dt: float) -> None:
        slept.append(dt)
        now[0] += dt

    src = ReplayFrameSource(ReplayFrameConfig(file=str(recorded["file"])), lambda: now[0], sleep)
    src.open()
    first = src.read()
    assert first is not None and first.device_time_s == pytest.approx(TS0 / 1e7)
    now[0] -= 2.0  # the next frame is now 2 s and a frame period away: a pause
    assert src.read() is None and src.read() is None  # each read waited MAX_WAIT_S
    assert slept == [MAX_WAIT_S, MAX_WAIT_S] and src.dropped["timeout"] == 2
    second = src.read()  # the frame it waited for, not one after it
    assert second is not None and second.device_time_s == pytest.approx((TS0 + DTS) / 1e7)
    src.close()


def test_a_device_clock_anchored_on_a_late_first_sample_never_goes_back():
    """The first sample received 80 ms late, the device's queue then read quicker than its
    45 Hz clock: each sample at its device spacing while that stays within 50 ms of its
    receive time, then anchored again, no earlier than the sample before it."""
    clock = DeviceClock(TICKS_PER_S)
    dt = DTS / 1e7
    receive = [0.08 + 0.01 * k for k in range(8)]  # 100/s until the queue is empty
    times = [clock.time(r, TS0 + k * DTS) for k, r in enumerate(receive)]
    # forward, never two at one time: three there (frames 4-6 here), a paced reader that skips
    # to the newest due frame skipped the middle one (test_replay_is_paced_at_the_recorded_times
    # failed so, 35 frames of 36, in a whole-suite run)
    assert np.all(np.diff(times) > 0.0), times
    assert times[:3] == pytest.approx([0.08, 0.08 + dt, 0.08 + 2 * dt])
    assert clock.reanchored >= 1
    assert all(t <= r + 0.05 + 1e-9 for t, r in zip(times, receive, strict=True)), times


def _board_from_epoch(tmp_path, monkeypatch, lines: list[str], now_s: float, since_s: float):
    """The replayed board (looped) opened at ``now_s`` on a hand clock, its epoch ``since_s``
    before: (the opened device, the clock as a one-item list that sleeping moves on)."""
    (tmp_path / "board.hex").write_text("\n".join(lines) + "\n")
    now = [now_s]
    hid = _replay_hid_module()
    monkeypatch.setattr(hid.time, "monotonic", lambda: now[0])
    monkeypatch.setattr(hid.time, "sleep", lambda s: now.__setitem__(0, now[0] + s))
    monkeypatch.setenv("HUMANTELE_HID_REPLAY", str(tmp_path / "board.hex"))
    monkeypatch.setenv("HUMANTELE_HID_LOOP", "1")
    monkeypatch.setenv("HUMANTELE_HID_EPOCH", repr(now_s - since_s))
    board = hid.device()
    board.open_path(hid.PATH)
    return board, now


def test_the_replayed_board_from_an_epoch_runs_on_unread_and_its_buffer_drops_the_newest(
    tmp_path, monkeypatch
):
    """With HUMANTELE_HID_EPOCH the replayed board sends report n at epoch + n / rate whether
    it is read or not (as the hl2ss replay with the same --epoch): a reader that opens late
    starts at the report of now; one that reads late gets the 64 reports the kernel's hidraw
    buffer held, the newer ones dropped as the kernel drops them."""
    lines = [f"{n:02x}{n:02x}" for n in range(200)]  # report n: [n, n]
    board, now = _board_from_epoch(tmp_path, monkeypatch, lines, 1000.0, 0.505)  # 50 reports in
    assert board.read(64, 100) == [51, 51]  # the next one the board sends, on its time
    assert now[0] == pytest.approx(1000.0 - 0.505 + 0.51)
    now[0] += 1.0  # not read for a second: 100 sent, 64 held
    got = [board.read(64, 0)[0] for _ in range(64)]
    assert got == list(range(52, 116)) and board.dropped_full == 36
    assert board.read(64, 100)[0] == 152  # after the drop: the next one sent
    now[0] += 0.5  # looped: 200 reports a turn
    assert [board.read(64, 0)[0] for _ in range(49)][-1] == 201 % 200


def test_the_replayed_board_s_clock_runs_on_across_the_turns_end(tmp_path, monkeypatch):
    """Looped from an epoch, a report of the second round carries the board's time and
    counter moved on by one round (a valid report, its CRC remade), as the hl2ss replay's
    timestamps run on: a board's clock never goes back."""
    from humantele.forcesense.hid import encode_report, parse_report

    lines = [encode_report(n, 5_000_000 + n * 10_000, [1.0] * 3, [2.0] * 3).hex()
             for n in range(50)]  # fmt: skip
    board, _ = _board_from_epoch(tmp_path, monkeypatch, lines, 100.0, 0.455)  # 45 reports in
    got = [parse_report(board.read(64, 100))[0] for _ in range(10)]  # reports 46..55
    assert [r.seq for r in got] == list(range(46, 56))
    times = [r.t for r in got]
    assert times == pytest.approx([5.0 + 0.01 * n for n in range(46, 56)])
    assert all(b > a for a, b in zip(times, times[1:], strict=False))


def test_the_replays_of_one_clinic_start_together_at_the_first_read_of_either(tmp_path):
    """The first replay read claims the start in the shared file; another, opened later,
    takes the same start (so its turn is where the first one's is, not at its beginning)."""
    from humantele.runtime.shared_start import shared_start

    path = tmp_path / "clinic_start"
    assert shared_start(path, now=12.5) == 12.5
    assert shared_start(path, now=14.0) == 12.5  # opened 1.5 s later: the same start
    assert [p.name for p in tmp_path.iterdir()] == ["clinic_start"]  # no claim left behind


@pytest.mark.parametrize("text", ["", "garbage", "nan", "1e300", "\x00\xff"])
def test_a_start_file_with_no_start_of_this_clock_is_refused_naming_it(tmp_path, text):
    """Garbled, or another boot's (a monotonic time ahead of now): a clear error naming the
    file, never a start taken from it; the file is left as it was."""
    from humantele.runtime.shared_start import BadStartFile, shared_start

    path = tmp_path / "clinic_start"
    path.write_text(text)
    with pytest.raises(BadStartFile, match="clinic_start.*not a start time"):
        shared_start(path, now=100.0)
    assert path.read_text() == text and len(list(tmp_path.iterdir())) == 1

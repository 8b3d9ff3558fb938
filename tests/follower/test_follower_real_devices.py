"""The follower on real device backends fed by recorded device data, with no simulator in any
of its processes (issue 18 §1): AHAT frames and rig poses from an hl2ss replay server in its
own process (hl2ss's wire format, the clinic's calibration file), the force board's HID reports
through the real HID reader (a replayed ``hid`` module), US and POV video from files through
the OpenCV source. The recording is made here, once per run, by the simulator (in the test's
process, never the follower's)."""

from __future__ import annotations

import asyncio
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import aiohttp
import cv2
import numpy as np
import pytest

from humantele.follower.sensing import tip_transform
from humantele.follower.sim_human import probe_down_quat
from humantele.follower.sim_world import SimWorld
from humantele.forcesense.calibration import calibrate_sim
from humantele.forcesense.hid import encode_report
from humantele.forcesense.sim import SimForceConfig, SimForceSensor
from humantele.geometry import Pose, quat_from_axis_angle
from humantele.tracking.hl2ss_calibration import Hl2ssAhatCalibration
from humantele.tracking.hl2ss_replay import AhatRecord, save_records
from humantele.tracking.sim import SimFrameConfig, SimFrameSource
from humantele.tracking.tool import load_tool

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

HERE = Path(__file__).parent
FRAMES = 135  # 3 s at 45 Hz
T_RIG_CAMERA = Pose([0.003, -0.08, -0.01], quat_from_axis_angle([0.0, 1.0, 0.2], 0.15))


def make_clinic_recording(out: Path) -> tuple[Path, list[Pose]]:
    """The simulated clinic recorded as its devices deliver it: AHAT frames with rig poses
    and the calibration, force board reports (100 Hz), two video files; and the true probe
    (body) poses in the world, the ground truth."""
    tool = load_tool("probe_default")
    world = SimWorld()
    camera = SimFrameSource(SimFrameConfig(seed=5), tool)
    board = SimForceSensor(SimForceConfig())
    T_tip_probe = tip_transform(tool).inverse()
    press = world.patient.landmarks()["xiphoid"] - np.array([0.0, 0.008, 0.0])
    world.human.hand = Pose(press, probe_down_quat([0.0, 1.0, 0.0]))  # the probe in hand
    records, truths, reports = [], [], []
    for k in range(FRAMES):
        t = k / 45.0
        wobble = np.array([0.01 * math.sin(k / 15), 0.0, 0.008 * math.cos(k / 11)])
        world.step(t, Pose(press + wobble, probe_down_quat([0.0, 1.0, 0.0])))
        truth = world.truth(t)
        probe = truth.T_world_tip @ T_tip_probe
        frame = camera.render(truth.T_world_camera.inverse() @ probe, t)
        rig = truth.T_world_camera @ T_RIG_CAMERA.inverse()
        records.append(AhatRecord(10_000_000 + k * 222_222, frame.depth_mm, frame.ir, k, rig))
        truths.append(probe)
        for j in range(2 + (k % 4 == 0)):  # ~100 Hz of reports beside 45 Hz of frames
            board.set_force(probe.rotation_matrix.T @ truth.force_world)
            r = board.read(t + j / 100.0)
            reports.append(encode_report(len(reports), int(r.t * 1e6), r.a, r.b, r.temperature_c))
    calibration = Hl2ssAhatCalibration.pinhole(camera.intrinsics, T_RIG_CAMERA)
    save_records(out / "ahat.npz", records, calibration)
    calibration.save(out / "ahat_calibration.json")
    (out / "board.hex").write_text("\n".join(r.hex() for r in reports) + "\n")
    calibrate_sim(SimForceSensor(SimForceConfig())).save(out / "board_calibration.json")
    for name, (w, h) in {"us": (640, 480), "pov": (640, 360)}.items():
        video = cv2.VideoWriter(str(out / f"{name}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 20,
                                (w, h))  # fmt: skip
        for k in range(200):
            img = np.full((h, w, 3), 40 + (k % 50), np.uint8)
            cv2.circle(img, (w // 2 + k % 100, h // 2), 30, (200, 200, 200), -1)
            video.write(img)
        video.release()
    return out, truths


def follower_config(rec: Path, port: int, state: Path) -> str:
    return f"""
[follower]
state_dir = "{state}"
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
backend = "opencv"
device = "{rec / "us.avi"}"
loop = true
pixel_spacing_mm = [0.3, 0.3]
depth_origin_row = 20.0
[follower.video.pov]
backend = "opencv"
device = "{rec / "pov.avi"}"
loop = true
[sensing.camera]
backend = "hl2ss"
host = "127.0.0.1"
port = {port}
calibration_file = "{rec / "ahat_calibration.json"}"
download_calibration = false
[sensing.force]
calibration_file = "{rec / "board_calibration.json"}"
[sensing.force.sensor]
backend = "hid"
"""


async def test_follower_on_replayed_devices_places_the_probe_and_loads_no_simulator(tmp_path):
    rec, truths = make_clinic_recording(tmp_path)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(HERE.parent / "devices" / "replay_hid"), os.environ.get("PYTHONPATH", "")]),
        HUMANTELE_HID_REPLAY=str(rec / "board.hex"))  # fmt: skip
    server = subprocess.Popen(
        [sys.executable, "-m", "humantele.tracking.hl2ss_replay", str(rec / "ahat.npz")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    follower = None
    try:
        line = server.stdout.readline()
        port = int(line.rsplit(":", 1)[1].split()[0]) if ":" in line else 0
        assert port > 0, f"the replay server said {line!r}: {server.stderr.read()}"
        cfg = tmp_path / "follower.toml"
        cfg.write_text(follower_config(rec, port, tmp_path / "state"))
        stats = tmp_path / "stats.json"
        follower = subprocess.Popen(
            [sys.executable, "-m", "humantele", "follower", "--config", str(cfg),
             "--duration", "60", "--stats-file", str(stats)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
            start_new_session=True,
        )  # fmt: skip
        url, probes = None, []
        for _ in range(600):  # the feed's address, once it serves (60 s at most)
            if stats.exists():
                with _suppress():
                    url = json.loads(stats.read_text()).get("feed_url")
            if url or follower.poll() is not None:
                break
            await asyncio.sleep(0.1)
        assert url, f"no feed: {follower.communicate(timeout=10)}"
        async with aiohttp.ClientSession() as s, s.ws_connect(url) as ws:
            deadline = asyncio.get_running_loop().time() + 60
            while len(probes) < 30 and asyncio.get_running_loop().time() < deadline:
                with _suppress():
                    msg = await ws.receive_json(timeout=5)
                    if msg.get("type") == "probe" and msg.get("tracking") == "tracked":
                        probes.append(msg)
        figures = json.loads(stats.read_text())
    finally:
        for p in (follower, server):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, 15)
        if follower is not None:
            out, err = follower.communicate(timeout=30)
            if not probes:
                print(out, err)
        server.communicate(timeout=10)
    assert len(probes) >= 30, "the follower placed no probe from the replayed devices"
    # Where the probe is, from device data alone (rig pose x extrinsics x tracker), against
    # the recording's truth: the tip position within 2 mm of the nearest true tip.
    tips = np.array([t.apply(load_tool("probe_default").tip) for t in truths])
    errs = [np.min(np.linalg.norm(tips - np.array(p["position"]), axis=1)) for p in probes]
    assert float(np.median(errs)) < 2e-3, errs
    assert max(np.linalg.norm(p["force"]) for p in probes) > 1.0  # the board's press, read
    assert any(p["contact"] for p in probes)  # contact from the force board
    assert figures["simulator_modules"] == {"daemon": [], "sensing": [], "video": []}
    for track in ("us", "pov"):  # the files through the OpenCV source, in the video process
        assert figures["video"][track]["captured"] > 10 and figures["video"][track]["errors"] == 0


class _suppress:
    """Ignore a half-written stats file or a feed message that is not JSON."""

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind, exc, tb) -> bool:
        return kind is not None and issubclass(kind, ValueError | TimeoutError | TypeError)

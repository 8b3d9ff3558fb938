"""A clinic recorded as its devices deliver it, made by the simulator in the test's process (never
the follower's): AHAT frames with rig poses and the AHAT calibration (hl2ss's formats), the
force board's HID reports at 100 Hz, two video files; with the ground truth (the probe's tip in
the world at each frame). The follower then runs on real backends fed from these files: the
hl2ss replay server in its own process, the replayed ``hid`` module
(tests/devices/replay_hid), the OpenCV source on the files."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from humantele.follower.sensing import tip_transform
from humantele.follower.sim_human import CalibrationScript, probe_down_quat
from humantele.follower.sim_world import SimWorld
from humantele.forcesense.calibration import calibrate_sim
from humantele.forcesense.hid import encode_report
from humantele.forcesense.sim import SimForceConfig, SimForceSensor
from humantele.geometry import Pose, quat_from_axis_angle
from humantele.tracking.hl2ss_calibration import Hl2ssAhatCalibration
from humantele.tracking.hl2ss_replay import AhatRecord, save_records
from humantele.tracking.sim import SimFrameConfig, SimFrameSource
from humantele.tracking.tool import load_tool

RATE_HZ = 45.0
HID_RATE_HZ = 100.0  # the board's (tests/devices/replay_hid replays at this rate)
TICKS = 222_222  # hl2ss timestamps: 100 ns ticks, one frame at 45 Hz
T0_TICKS = 10_000_000
T_RIG_CAMERA = Pose([0.003, -0.08, -0.01], quat_from_axis_angle([0.0, 1.0, 0.2], 0.15))
REPLAY_HID = Path(__file__).parent.parent / "devices" / "replay_hid"


@dataclass
class Recording:
    """The files, and the true tip pose and the headset's rig pose (world) of each frame by
    its device time (s)."""

    dir: Path
    truth: dict[float, Pose]
    rigs: dict[float, Pose]
    records: list[AhatRecord] | None = None  # the AHAT frames, when not saved to ahat.npz
    calibration: Hl2ssAhatCalibration | None = None


def device_time(k: int) -> float:
    return (T0_TICKS + k * TICKS) * 1e-7


def hold_then_wobble(world: SimWorld, seconds: float) -> Callable[[float], Pose]:
    """Targets (tip, world): the probe pressed gently on the xiphoid, sliding a little."""
    press = world.patient.landmarks()["xiphoid"] - np.array([0.0, 0.008, 0.0])
    q = probe_down_quat([0.0, 1.0, 0.0])
    world.human.hand = Pose(press, q)  # the probe in hand from the start

    def target(t: float) -> Pose:
        return Pose(press + [0.01 * math.sin(t / 0.33), 0.0, 0.008 * math.cos(t / 0.24)], q)

    return target


def calibration_presses(world: SimWorld, hover_s: float = 2.0) -> tuple[Callable, float]:
    """Targets: hover over the xiphoid ``hover_s``, press the four landmarks in the order the
    follower asks for them, then rest on the abdomen; and when the presses end (s)."""
    script = CalibrationScript(world.patient)
    order = CalibrationScript.LANDMARK_ORDER
    start = script.target(order[0], 0.0)
    world.human.hand = start
    end = hover_s + script.segment_s * len(order)
    rest = Pose(world.patient.landmarks()["xiphoid"] + [0.04, -0.004, 0.02], start.quaternion)

    def target(t: float) -> Pose:
        if t < hover_s:
            return start
        k, u = divmod(t - hover_s, script.segment_s)
        if k >= len(order):
            return rest
        return script.target(order[int(k)], u) or start

    return target, end


def make_recording(out: Path, seconds: float, targets: Callable[[float], Pose],
                   world: SimWorld, save_ahat: bool = True) -> Recording:  # fmt: skip
    """Record ``seconds`` of the sim clinic with its novice moving to ``targets(t)``. The AHAT
    frames go to ahat.npz uncompressed (1 MB a frame of noise: deflating 15 s of them took 11
    s, and the replay server 4 s to read them back); without ``save_ahat`` they stay in memory
    (``records``), for a caller that serves them itself."""
    tool = load_tool("probe_default")
    camera = SimFrameSource(SimFrameConfig(seed=5), tool)
    board = SimForceSensor(SimForceConfig())
    T_tip_probe = tip_transform(tool).inverse()
    records, truth, rigs, reports = [], {}, {}, []
    for k in range(int(seconds * RATE_HZ)):
        t = k / RATE_HZ
        world.step(t, targets(t))
        now = world.truth(t)
        probe = now.T_world_tip @ T_tip_probe
        frame = camera.render(now.T_world_camera.inverse() @ probe, t)
        rig = now.T_world_camera @ T_RIG_CAMERA.inverse()
        records.append(AhatRecord(T0_TICKS + k * TICKS, frame.depth_mm, frame.ir, k, rig))
        truth[round(device_time(k), 6)] = now.T_world_tip
        rigs[round(device_time(k), 6)] = rig
        board.set_force(probe.rotation_matrix.T @ now.force_world)
        while len(reports) / HID_RATE_HZ < (k + 1) / RATE_HZ:  # 100 Hz of reports exactly
            r = board.read(len(reports) / HID_RATE_HZ)
            reports.append(encode_report(len(reports), int(r.t * 1e6), r.a, r.b, r.temperature_c))
    calibration = Hl2ssAhatCalibration.pinhole(camera.intrinsics, T_RIG_CAMERA)
    if save_ahat:
        save_records(out / "ahat.npz", records, calibration, compress=False)
    calibration.save(out / "ahat_calibration.json")
    (out / "board.hex").write_text("\n".join(r.hex() for r in reports) + "\n")
    calibrate_sim(SimForceSensor(SimForceConfig())).save(out / "board_calibration.json")
    for name, (w, h) in {"us": (640, 480), "pov": (640, 360)}.items():
        video = cv2.VideoWriter(str(out / f"{name}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 20,
                                (w, h))  # fmt: skip
        for k in range(60):
            img = np.full((h, w, 3), 40 + (k % 50), np.uint8)
            cv2.circle(img, (w // 2 + k, h // 2), 30, (200, 200, 200), -1)
            video.write(img)
        video.release()
    if save_ahat:
        return Recording(out, truth, rigs)
    return Recording(out, truth, rigs, records, calibration)


def fake_libhd(tmp_path: Path) -> str:
    """The fake OpenHaptics libHD (tests/devices/fake_libhd.c) built into ``tmp_path`` (by
    the haptics bench's builder); skipped without a C compiler."""
    import pytest

    from humantele.bench.haptics_callback import build_fake_libhd

    try:
        return str(build_fake_libhd(tmp_path))
    except RuntimeError as exc:
        pytest.skip(f"the fake OpenHaptics libHD: {exc}")


def expert_on_fake_touchx(tmp_path: Path, env: dict[str, str], video: bool = True) -> Path:
    """An expert config on the fake libHD (a configured Touch driver directory in ``env``),
    receiving the follower's video (``video``)."""
    (tmp_path / "3DSystems" / "config").mkdir(parents=True, exist_ok=True)
    env["GTDD_HOME"] = str(tmp_path / "3DSystems")
    cfg = tmp_path / "expert.toml"
    cfg.write_text(f'[servo.device]\nbackend = "touchx"\nlibrary = "{fake_libhd(tmp_path)}"\n'
                   "[expert.link]\nrealtime_priority = 0\n"
                   f"[expert.video]\nenabled = {str(video).lower()}\n")  # fmt: skip
    return cfg


def follower_config(rec: Path, port: int, state: Path, video: bool = True, extra: str = "") -> str:
    """The follower on real backends reading the recording (hl2ss server on ``port``);
    ``extra``: more TOML appended."""
    return f"""
[follower]
state_dir = "{state}"
[follower.clinic]
backend = "devices"
[follower.link]
realtime_priority = 0
[follower.feed]
host = "127.0.0.1"
port = 0
tls = false
[follower.video]
enabled = {str(video).lower()}
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
ab_profile = "raw"
host = "127.0.0.1"
port = {port}
calibration_file = "{rec / "ahat_calibration.json"}"
download_calibration = false
[sensing.force]
calibration_file = "{rec / "board_calibration.json"}"
[sensing.force.sensor]
backend = "hid"
{extra}"""


def replay_env(rec: Path, loop: bool = False, start_file: Path | None = None) -> dict[str, str]:
    """Environment additions for the follower: the replayed ``hid`` module and its reports
    (``loop``: again and again, as the frames with the server's ``--loop``; ``start_file``:
    the board and the frames' server with the same ``--start-file`` start together)."""
    import os

    path = os.pathsep.join([str(REPLAY_HID), os.environ.get("PYTHONPATH", "")])
    env = {"PYTHONPATH": path, "HUMANTELE_HID_REPLAY": str(rec / "board.hex"),
           "HUMANTELE_HID_LOOP": "1" if loop else "0"}  # fmt: skip
    if start_file is not None:
        env["HUMANTELE_HID_START_FILE"] = str(start_file)
    return env


def start_hl2ss_server(npz: Path, loop: bool = False, start_file: Path | None = None):
    """The hl2ss replay server in its own process (paced at 45 Hz, as the headset sends;
    ``loop``: the recording again at its end; ``start_file``: it starts with the other
    replays of the clinic sharing it): (subprocess.Popen, port)."""
    import subprocess
    import sys

    # (in the caller's process group: a scenario killed at its timeout takes it along)
    server = subprocess.Popen(
        [sys.executable, "-m", "humantele.tracking.hl2ss_replay", str(npz),
         *(["--loop"] if loop else []), *(["--start-file", str(start_file)] if start_file else [])],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    line = server.stdout.readline()
    port = int(line.rsplit(":", 1)[1].split()[0]) if ":" in line else 0
    if port <= 0:
        server.kill()
        raise AssertionError(f"the hl2ss replay server said {line!r}: {server.stderr.read()}")
    return server, port

"""``humantele devices check`` fails, naming why, when no frame of the headset's stream carried
the camera's pose (the headset not located): the follower could place no probe with it."""

from __future__ import annotations

import re

import numpy as np

from humantele.cli import main
from humantele.geometry import Pose
from humantele.tracking.camera import CameraIntrinsics
from humantele.tracking.hl2ss_calibration import Hl2ssAhatCalibration
from humantele.tracking.hl2ss_replay import AhatRecord, Hl2ssReplayServer


def records(located: bool) -> list[AhatRecord]:
    rng = np.random.default_rng(2)
    depth = np.full((512, 512), 700, np.uint16)
    pose = Pose([0.1, 1.6, 0.0], [0.0, 0.0, 0.0, 1.0]) if located else None
    return [AhatRecord(10_000_000 + k * 222_222, depth,
                       rng.integers(0, 3000, (512, 512), dtype=np.uint16), k, pose)
            for k in range(4)]  # fmt: skip


def check(tmp_path, capsys, located: bool) -> tuple[int, str]:
    cal = Hl2ssAhatCalibration.pinhole(CameraIntrinsics(), Pose([0.0, -0.09, 0.0], [1, 0, 0, 0]))
    with Hl2ssReplayServer([records(located) * 20], calibration=cal, rate_hz=45.0) as srv:
        # RAW AB: the check is about the camera's pose, not the codec (no x264 encode/decode)
        conf = tmp_path / "follower.toml"
        conf.write_text(f'[sensing.camera]\nbackend = "hl2ss"\nhost = "127.0.0.1"\n'
                        f'port = {srv.port}\nab_profile = "raw"\n')  # fmt: skip
        code = main(["devices", "check", "--follower-config", str(conf), "--only", "tracker",
                     "--samples", "4"])  # fmt: skip
    return code, capsys.readouterr().out


def test_a_stream_without_any_camera_pose_fails_the_check_and_says_why(tmp_path, capsys):
    code, text = check(tmp_path, capsys, located=False)
    assert code == 1, text
    assert "[FAIL] tracker camera (hl2ss)" in text and "camera pose in 0" in text
    # every frame read said why it had no pose (a loaded machine may read fewer than 4 in time)
    frames = int(re.search(r"(\d)/4 frames", text).group(1))
    assert frames >= 1 and f"no frame carried the camera's pose (not_located {frames})" in text


def test_a_located_headset_passes(tmp_path, capsys):
    code, text = check(tmp_path, capsys, located=True)
    assert code == 0, text
    frames = int(re.search(r"(\d)/4 frames", text).group(1))
    assert "[ok  ] tracker camera (hl2ss)" in text and f"camera pose in {frames}" in text

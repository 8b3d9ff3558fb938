"""humantele's hl2ss wire format against hl2ss's own Python client (vendored unmodified in
tests/devices/vendor/hl2ss, commit 9a70fad2): the configuration bytes, the AHAT packets, the
calibration download and the matrix conventions (row-vector, translation in the last row)."""

import math
import struct
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from humantele.geometry import Pose, quat_from_axis_angle, quat_multiply
from humantele.tracking.camera import CameraIntrinsics
from humantele.tracking.hl2ss_calibration import Hl2ssAhatCalibration
from humantele.tracking.hl2ss_protocol import (
    AHAT_PIXELS,
    DEFAULT_RAW_BITRATE,
    RAW_PAYLOAD_SIZE,
    AhatConfiguration,
    ConfigurationRefused,
    PacketError,
    decode_ahat_payload,
    encode_ahat_packet,
    hl2ss_matrix_from_pose,
    pose_from_hl2ss,
    read_configuration,
    rig_camera_from_extrinsics,
)
from humantele.tracking.hl2ss_replay import AhatRecord, Hl2ssReplayServer
from humantele.tracking.hl2ss_source import ahat_configuration

VENDOR = Path(__file__).parent / "vendor" / "hl2ss"


def _device_portal_stand_in() -> types.ModuleType:
    """What ``hl2ss_lnm`` imports of ``hl2ss_dp`` (the Device Portal's mixed-reality-capture
    client over HTTPS, which needs ``requests``): its chunk size, read for a default argument
    at import. The tests use none of it, so it is not vendored; anything else of it raises."""
    dp = types.ModuleType("hl2ss_dp")
    dp.ChunkSize = types.SimpleNamespace(MRC=4096)  # hl2ss_dp.ChunkSize.MRC at 9a70fad2

    def __getattr__(name: str):
        raise AttributeError(f"hl2ss_dp.{name}: the Device Portal client is not vendored")

    dp.__getattr__ = __getattr__
    return dp


def load_vendored():
    """hl2ss's own modules: (hl2ss, hl2ss_lnm, hl2ss_3dcv), with the Device Portal stand-in."""
    sys.path.insert(0, str(VENDOR))
    sys.modules.setdefault("hl2ss_dp", _device_portal_stand_in())
    try:
        import hl2ss as h
        import hl2ss_3dcv
        import hl2ss_lnm
    finally:
        sys.path.remove(str(VENDOR))
    return h, hl2ss_lnm, hl2ss_3dcv


@pytest.fixture(scope="module")
def hl2ss():
    """hl2ss's own modules: (hl2ss, hl2ss_lnm, hl2ss_3dcv)."""
    pytest.importorskip("av")  # hl2ss.py imports PyAV and OpenCV at module level
    return load_vendored()


@pytest.mark.e2e  # runs a Python process (the fast lane leaves it out)
def test_the_vendored_client_loads_without_requests():
    """Only what the tests use is imported: nothing of the Device Portal client, whose
    ``requests`` neither the package nor its [test] extra installs."""
    code = (
        "import sys; sys.modules['requests'] = None; sys.path.insert(0, sys.argv[1]); "
        "import test_hl2ss_protocol as t; h, lnm, _ = t.load_vendored(); "
        "print(lnm.get_video_codec_default_bitrate(512, 512, 45, 1, h.VideoProfile.RAW))"
    )
    res = subprocess.run([sys.executable, "-c", code, str(Path(__file__).parent)],
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    assert int(res.stdout.split()[-1]) > 0


# a known non-symmetric pose: a rotation about a skew axis and a translation
T_WORLD_RIG = Pose([0.31, -0.12, 1.7], quat_from_axis_angle([0.3, 1.0, -0.2], 0.9))
T_RIG_CAMERA = Pose([0.004, -0.09, -0.012],
                    quat_multiply(quat_from_axis_angle([1, 0, 0], math.pi),  # fmt: skip
                                  quat_from_axis_angle([0, 1, 0], 0.2)))  # fmt: skip


def reader(data: bytes):
    pos = [0]

    def recv_exactly(n: int) -> bytes:
        if pos[0] + n > len(data):
            raise ConnectionError("short")
        pos[0] += n
        return data[pos[0] - n : pos[0]]

    return recv_exactly


def images(seed: int = 0):
    rng = np.random.default_rng(seed)
    depth = rng.integers(0, 1055, (512, 512), dtype=np.uint16)
    depth[0, :8] = [4089, 4090, 4095, 65535, 0, 1, 2, 3]  # the app zeroes >= 4090
    return depth, rng.integers(0, 3000, (512, 512), dtype=np.uint16)


def test_configuration_bytes_are_the_ones_hl2ss_builds_and_the_app_accepts(hl2ss):
    h, lnm, _ = hl2ss
    # what hl2ss_lnm.rx_rm_depth_ahat sends for depth SAME + AB RAW, mode 1
    bitrate = lnm.get_video_codec_default_bitrate(512, 512, 45, 1, h.VideoProfile.RAW) * 16
    options = lnm.get_video_codec_default_options(512, 512, 45, 1, h.VideoProfile.RAW)
    theirs = h._create_configuration_for_rm_depth_ahat(
        1, 1, h.DepthProfile.SAME, h.VideoProfile.RAW, h.H26xLevel.DEFAULT, bitrate, options
    )
    assert bitrate == DEFAULT_RAW_BITRATE > 0
    assert ahat_configuration(1) == theirs
    cfg = read_configuration(reader(theirs))
    assert (cfg.mode, cfg.divisor, cfg.profile_z, cfg.profile_ab, cfg.bitrate) == (
        1, 1, 0, 0xFF, bitrate)  # fmt: skip
    assert cfg.options == {10: 1}
    assert h._create_configuration_for_rm_mode2(2) == AhatConfiguration(mode=2).pack()


@pytest.mark.parametrize(("fields", "why"), [
    ({"bitrate": 0}, "bitrate"),
    ({"divisor": 0}, "divisor"),
    ({"profile_z": 2}, "depth profile"),
    ({"profile_ab": 7}, "AB profile"),
    ({"mode": 3}, "reserved"),
])  # fmt: skip
def test_the_app_s_refusals(fields, why):
    base = {"mode": 1, "divisor": 1, "profile_z": 0, "profile_ab": 255, "level": 255,
            "bitrate": 1000}  # fmt: skip
    base.update(fields)
    data = struct.pack("<BBBBBIB", *base.values(), 0)
    with pytest.raises(ConfigurationRefused, match=why):
        read_configuration(reader(data))
    # the client before this change sent bitrate 0: refused by the app for RAW too
    with pytest.raises(ConfigurationRefused, match="bitrate"):
        read_configuration(reader(struct.pack("<BBBBBIB", 0, 1, 0, 0xFF, 0xFF, 0, 0)))


def test_packet_layout_is_hl2ss_s():
    depth, ab = images()
    pose = hl2ss_matrix_from_pose(T_WORLD_RIG)
    pkt = encode_ahat_packet(123456789, depth, ab, 42, pose)
    ts, size = struct.unpack_from("<QI", pkt, 0)
    size_z, size_ab = struct.unpack_from("<II", pkt, 12)
    assert (ts, size, size_z, size_ab) == (123456789, RAW_PAYLOAD_SIZE, 0, 4 * AHAT_PIXELS)
    assert size == 4 + 4 + size_z + size_ab + 8  # full_size in stream_rm_zht.cpp
    assert len(pkt) == 12 + size + 64
    assert struct.unpack_from("<Q", pkt, 12 + size - 8)[0] == 42
    assert np.array_equal(np.frombuffer(pkt, "<f4", 16, 12 + size).reshape(4, 4), pose)
    p = decode_ahat_payload(pkt[12 : 12 + size])
    expect = np.where(depth >= 4090, 0, depth)
    assert np.array_equal(p.depth_mm, expect) and np.array_equal(p.ab, ab)
    assert p.depth_mm[0, :4].tolist() == [4089, 0, 0, 0] and p.sensor_ticks == 42


def test_bad_payloads_are_named():
    depth, ab = images()
    pkt = encode_ahat_packet(1, depth, ab)
    payload = bytearray(pkt[12:])
    with pytest.raises(PacketError) as e:
        decode_ahat_payload(payload[:-100])  # truncated: sizes disagree with the length
    assert e.value.reason == "size"
    zdepth_like = struct.pack("<II", 100, 2 * AHAT_PIXELS) + bytes(100 + 2 * AHAT_PIXELS + 8)
    with pytest.raises(PacketError) as e:
        decode_ahat_payload(zdepth_like)  # consistent, but Zdepth + RAW AB: not ours
    assert e.value.reason == "encoding"
    with pytest.raises(PacketError) as e:
        decode_ahat_payload(bytes(8) + payload[8:])  # the old encoder's 8 zero bytes
    assert e.value.reason == "size"


def test_hl2ss_s_own_client_reads_the_replay_server(hl2ss):
    h, lnm, _ = hl2ss
    frames = [images(k) for k in range(3)]
    poses = [T_WORLD_RIG, None, Pose([1, 2, 3], quat_from_axis_angle([0, 0, 1], -0.4))]
    recs = [AhatRecord(1000 + k, d, a, 50 + k, p)
            for k, ((d, a), p) in enumerate(zip(frames, poses, strict=True))]  # fmt: skip
    with Hl2ssReplayServer([recs]) as srv:
        rx = lnm.rx_rm_depth_ahat("127.0.0.1", srv.port, mode=h.StreamMode.MODE_1,
                                  profile_z=h.DepthProfile.SAME, profile_ab=h.VideoProfile.RAW,
                                  sockopt=lnm.create_sockopt(settimeout=10))  # fmt: skip
        rx.open()
        got = [rx.get_next_packet() for _ in recs]
        rx.close()
    assert not srv.refusals and srv.configs[0].bitrate == DEFAULT_RAW_BITRATE
    for k, (g, (d, a), p) in enumerate(zip(got, frames, poses, strict=True)):
        assert g.timestamp == 1000 + k and int(g.payload.sensor_ticks[0]) == 50 + k
        assert np.array_equal(g.payload.depth, np.where(d >= 4090, 0, d))
        assert np.array_equal(g.payload.ab, a)
        assert h.is_valid_pose(g.pose) == (p is not None)
        if p is not None:  # what hl2ss hands its users is our pose in its convention
            assert np.array_equal(g.pose, hl2ss_matrix_from_pose(p))


def test_hl2ss_s_own_client_skipped_the_old_packets(hl2ss):
    """The old encoder wrote 8 zero bytes where size_z/size_ab go: hl2ss's client skips a
    packet whose size_ab is 0, so it never returned one of them."""
    h, lnm, _ = hl2ss
    depth, ab = images()
    good = encode_ahat_packet(7, depth, ab, 1)
    old = bytearray(good)
    old[12:20] = bytes(8)
    with Hl2ssReplayServer([[bytes(old), bytes(old), good]]) as srv:
        rx = lnm.rx_rm_depth_ahat("127.0.0.1", srv.port, mode=h.StreamMode.MODE_0,
                                  profile_ab=h.VideoProfile.RAW, decoded=False,
                                  sockopt=lnm.create_sockopt(settimeout=10))  # fmt: skip
        rx.open()
        first = rx.get_next_packet()
        rx.close()
    assert first.timestamp == 7 and struct.unpack_from("<II", first.payload)[1] > 0


def test_hl2ss_s_calibration_download_reads_ours(hl2ss):
    h, lnm, _ = hl2ss
    k = CameraIntrinsics(fx=210.5, fy=209.0, cx=250.0, cy=260.5)
    cal = Hl2ssAhatCalibration.pinhole(k, T_RIG_CAMERA)
    with Hl2ssReplayServer([], calibration=cal) as srv:
        theirs = lnm.download_calibration_rm_depth_ahat("127.0.0.1", srv.port)
    assert srv.calibration_sent == 1
    assert np.array_equal(theirs.extrinsics, cal.extrinsics)
    assert np.allclose(theirs.intrinsics[2, :2], [250.0, 260.5])  # their K: row-vector too
    assert np.allclose([theirs.intrinsics[0, 0], theirs.intrinsics[1, 1]], [210.5, 209.0])
    assert np.array_equal(theirs.uv2xy[..., 0], cal.uv2x)
    assert np.array_equal(theirs.undistort_map[..., 1], cal.mapy)
    assert float(theirs.scale[0]) == 1000.0 and float(theirs.alias[0]) == 1055.0
    assert Hl2ssAhatCalibration.from_bytes(cal.to_bytes()).intrinsics() == cal.intrinsics()


def test_rig_pose_convention_row_major_translation_in_the_last_row(hl2ss):
    _, _, cv = hl2ss
    M = hl2ss_matrix_from_pose(T_WORLD_RIG)
    assert np.allclose(M[3, :3], T_WORLD_RIG.position)  # translation: last ROW
    assert np.allclose(M[:3, 3], 0.0) and M[3, 3] == 1.0
    assert not np.allclose(M[:3, :3], M[:3, :3].T)  # non-symmetric: a transpose would show
    pts_rig = np.array([[0.1, 0.2, 0.3], [-0.5, 0.0, 1.0], [0.0, 0.0, 0.0]])
    # hl2ss maps points as p @ M (hl2ss_3dcv.transform); ours as T.apply(p)
    assert np.allclose(cv.transform(pts_rig, M), T_WORLD_RIG.apply(pts_rig), atol=1e-6)
    back, why = pose_from_hl2ss(M)
    assert why == "" and back.distance_to(T_WORLD_RIG)[0] < 1e-6
    assert back.distance_to(T_WORLD_RIG)[1] < 1e-6


def test_camera_pose_is_rig_pose_times_extrinsics_as_hl2ss_composes_it(hl2ss):
    _, _, cv = hl2ss
    E = hl2ss_matrix_from_pose(T_RIG_CAMERA.inverse())  # what research mode's extrinsics hold
    M = hl2ss_matrix_from_pose(T_WORLD_RIG)
    T_rig_camera = rig_camera_from_extrinsics(E)
    assert T_rig_camera.distance_to(T_RIG_CAMERA)[0] < 1e-6
    T_world_camera = T_WORLD_RIG @ T_rig_camera
    pts_cam = np.array([[0.0, 0.0, 0.5], [0.1, -0.05, 0.3], [-0.2, 0.1, 0.8]])
    # hl2ss's own camera -> world: camera_to_rignode(E) @ reference_to_world(pose), row-vector
    theirs = cv.transform(pts_cam, cv.camera_to_rignode(E) @ cv.reference_to_world(M))
    assert np.allclose(theirs, T_world_camera.apply(pts_cam), atol=1e-5)
    # and the optical axis (OpenCV z forward) points where hl2ss's (x, y, 1) rays point
    ray = np.array([[0.0, 0.0, 1.0]])
    assert np.allclose(cv.orient(ray, cv.camera_to_rignode(E) @ M),
                       T_world_camera.rotate(ray), atol=1e-5)  # fmt: skip


@pytest.mark.parametrize(("matrix", "why"), [
    (np.zeros((4, 4)), "not_located"),
    (np.full((4, 4), np.nan), "not_finite"),
    (hl2ss_matrix_from_pose(T_WORLD_RIG).T, "not_rigid"),  # a column-vector matrix
    (np.diag([2.0, 1.0, 1.0, 1.0]), "not_rigid"),
])  # fmt: skip
def test_unusable_poses(matrix, why):
    assert pose_from_hl2ss(matrix) == (None, why)


def test_calibration_file_round_trip_and_axes_check(tmp_path):
    k = CameraIntrinsics(fx=210.5, fy=209.0, cx=250.0, cy=260.5)
    cal = Hl2ssAhatCalibration.pinhole(k, T_RIG_CAMERA)
    cal.check_axes()
    path = tmp_path / "ahat.json"
    cal.save(path, source="test")
    back = Hl2ssAhatCalibration.load(path)
    assert back.intrinsics() == k and np.array_equal(back.extrinsics, cal.extrinsics)
    assert back.T_rig_camera().distance_to(T_RIG_CAMERA)[0] < 1e-6
    flipped = Hl2ssAhatCalibration.pinhole(k, T_RIG_CAMERA)
    flipped.uv2y = -flipped.uv2y  # y up: not the OpenCV axes hl2ss uses
    with pytest.raises(ValueError, match="axes"):
        flipped.check_axes()
    (tmp_path / "other.json").write_text('{"kind": "something else"}')
    with pytest.raises(ValueError, match="other.json"):
        Hl2ssAhatCalibration.load(tmp_path / "other.json")

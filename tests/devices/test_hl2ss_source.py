"""The hl2ss AHAT backend against the strict replay server (it refuses what the hl2ss app
refuses and writes hl2ss's own packets) replaying the project's simulated AHAT frames: same
frames and tracking figures; rig pose and camera pose per frame; frames without a pose counted;
bad bytes, a stalled or dropped connection and an unreachable headset handled."""

import fcntl
import math
import socket
import struct
import subprocess
import sys
import termios
import threading
import zipfile

import numpy as np
import pytest
from pydantic import ValidationError

from humantele.cli import main
from humantele.geometry import Pose, quat_from_axis_angle, quat_multiply
from humantele.tracking.frames import FrameSourceUnavailable
from humantele.tracking.hl2ss_calibration import Hl2ssAhatCalibration
from humantele.tracking.hl2ss_protocol import AHAT_PIXELS, encode_ahat_packet
from humantele.tracking.hl2ss_replay import (
    AhatRecord,
    Hl2ssReplayServer,
    load_records,
    save_records,
)
from humantele.tracking.hl2ss_source import (
    Hl2ssFrameConfig,
    Hl2ssFrameSource,
    ahat_configuration,
)
from humantele.tracking.pipeline import Tracker
from humantele.tracking.sim import SimFrameConfig, SimFrameSource, default_sim_pose
from humantele.tracking.sources import make_frame_source
from humantele.tracking.tool import load_tool
from waits import wait_for

T_RIG_CAMERA = Pose([0.004, -0.09, -0.012],
                    quat_multiply(quat_from_axis_angle([1, 0, 0], math.pi),  # fmt: skip
                                  quat_from_axis_angle([0, 1, 0], 0.2)))  # fmt: skip


def sim_frames(n: int, seed: int = 3):
    sim = SimFrameSource(SimFrameConfig(seed=seed))
    base = default_sim_pose()
    frames = []
    for k in range(n):  # the probe sweeping and turning in front of the headset
        q = quat_multiply(quat_from_axis_angle([0, 1, 0], 0.3 * math.sin(k / 5)), base.quaternion)
        p = base.position + np.array([0.05 * math.sin(k / 7), 0.02 * math.cos(k / 4), 0.0])
        frames.append(sim.render(Pose(p, q), t=k / 45.0))
    return frames


def rig_pose(k: int) -> Pose:
    """The headset walking and turning: a non-symmetric pose per frame."""
    return Pose([0.2 + 0.01 * k, 1.6, -0.3 * k / 40],
                quat_from_axis_angle([0.2, 1.0, 0.1], 0.05 * k + 0.4))  # fmt: skip


def record(frame, k: int, pose: Pose | None = None) -> AhatRecord:
    return AhatRecord(10_000_000 + k * 222_222, frame.depth_mm, frame.ir, k, pose)


def calibration(frames) -> Hl2ssAhatCalibration:
    return Hl2ssAhatCalibration.pinhole(frames[0].intrinsics, T_RIG_CAMERA)


def cfg(port: int, **kw) -> Hl2ssFrameConfig:
    base = {
        "host": "127.0.0.1",
        "port": port,
        "mode": 0,
        "download_calibration": False,
        "newest": False,
        "ab_profile": "raw",
    }  # every frame in order (the follower's default skips to the newest)
    return Hl2ssFrameConfig(**{**base, **kw})


def figures(frames) -> dict:
    """Tracking figures of a stream: statuses, poses, median and max position error (mm)."""
    tracker = Tracker(load_tool("probe_default"))
    errs, poses, statuses = [], [], []
    for f, truth in frames:
        r = tracker.process(f)
        statuses.append(r.status)
        if r.T_camera_probe is not None:
            poses.append(np.r_[r.T_camera_probe.position, r.T_camera_probe.quaternion])
            errs.append(np.linalg.norm(r.T_camera_probe.position - truth.position) * 1e3)
    return {"statuses": statuses, "poses": np.array(poses),
            "median_mm": float(np.median(errs)), "max_mm": float(np.max(errs))}  # fmt: skip


def test_replayed_stream_gives_the_sim_source_s_frames_and_tracking_figures():
    frames = sim_frames(40)
    with Hl2ssReplayServer([[record(f, k) for k, f in enumerate(frames)]]) as srv:
        src = make_frame_source(cfg(srv.port))
        src.open()
        got = [src.read(t=f.t) for f in frames]
        src.close()
    (c,) = srv.configs  # RAW depth and AB asked for, with a bitrate the app accepts
    assert (c.mode, c.profile_z, c.profile_ab) == (0, 0, 0xFF) and c.bitrate > 0
    assert all(g is not None for g in got) and src.received == 40 and not src.dropped
    assert src.no_pose == {"mode_0": 40}  # mode 0: frames, no pose to place them
    for g, f in zip(got, frames, strict=True):
        assert np.array_equal(g.ir, f.ir) and np.array_equal(g.depth_mm, f.depth_mm)
        assert g.T_world_camera is None and g.T_world_rig is None
    assert src.last_timestamp == 10_000_000 + 39 * 222_222 and src.last_sensor_ticks == 39
    truths = [f.T_camera_probe_true for f in frames]
    sim_fig = figures(list(zip(frames, truths, strict=True)))
    net_fig = figures(list(zip(got, truths, strict=True)))
    assert net_fig["statuses"] == sim_fig["statuses"]
    assert np.array_equal(net_fig["poses"], sim_fig["poses"])
    assert net_fig["median_mm"] == sim_fig["median_mm"] and net_fig["max_mm"] == sim_fig["max_mm"]
    assert sim_fig["statuses"].count("tracked") >= 30  # the replay tracks, it is not all lost


def test_mode_1_frames_carry_rig_and_camera_pose_and_place_the_probe_in_the_world():
    frames = sim_frames(30)
    recs = [record(f, k, rig_pose(k)) for k, f in enumerate(frames)]
    recs[7].T_world_rig = None  # the headset lost tracking there: hl2ss sends zeros
    with Hl2ssReplayServer([recs], calibration=calibration(frames)) as srv:
        src = Hl2ssFrameSource(cfg(srv.port, mode=1, download_calibration=True))
        src.open()  # downloads the calibration (mode 2), then streams
        got = [src.read() for _ in frames]
        src.close()
    assert srv.calibration_sent == 1 and srv.configs[0].mode == 1
    assert src.T_rig_camera.distance_to(T_RIG_CAMERA)[0] < 1e-6
    assert src.no_pose == {"not_located": 1} and not src.dropped
    assert got[7] is not None and got[7].T_world_camera is None and got[7].T_world_rig is None
    tracker = Tracker(load_tool("probe_default"))
    errs = []
    for k, (g, f) in enumerate(zip(got, frames, strict=True)):
        r = tracker.process(g)
        if k == 7:
            continue
        dp, da = g.T_world_rig.distance_to(rig_pose(k))
        assert dp < 1e-6 and da < 1e-6  # float32 on the wire
        truth_cam = rig_pose(k) @ T_RIG_CAMERA
        dp, da = g.T_world_camera.distance_to(truth_cam)
        assert dp < 1e-6 and da < 1e-5
        if r.T_camera_probe is not None:  # the probe in hl2ss's world, from device data only
            world = g.T_world_camera @ r.T_camera_probe
            truth = truth_cam @ f.T_camera_probe_true
            errs.append(np.linalg.norm(world.position - truth.position) * 1e3)
    assert len(errs) >= 20 and np.median(errs) < 2.0  # the tracker's own error, not a frame's


def test_calibration_saved_by_the_command_is_used_and_divisor_honoured(tmp_path, capsys):
    frames = sim_frames(6)
    out = tmp_path / "hl2ss_ahat.json"
    recs = [record(f, k, rig_pose(k)) for k, f in enumerate(frames)]
    with Hl2ssReplayServer([recs], calibration=calibration(frames)) as srv:
        code = main(["devices", "hl2ss-calibration", "--host", "127.0.0.1", "--port",
                     str(srv.port), "--out", str(out)])  # fmt: skip
        assert code == 0 and "saved" in capsys.readouterr().out
        src = Hl2ssFrameSource(cfg(srv.port, mode=1, divisor=2, calibration_file=str(out)))
        src.open()
        got = [src.read() for _ in range(3)]
        src.close()
    assert srv.calibration_sent == 1  # by the command only; the source read the file
    assert out.with_suffix(".maps.npz").exists()
    assert [g.seq for g in got] == [1, 2, 3]
    for g, k in zip(got, (0, 2, 4), strict=True):  # every 2nd frame, as the app sends them
        assert np.array_equal(g.ir, frames[k].ir)
        assert g.T_world_camera.distance_to(rig_pose(k) @ T_RIG_CAMERA)[0] < 1e-6


def test_calibration_undistorts_the_raw_images_to_its_pinhole():
    frames = sim_frames(1)
    cal = calibration(frames)
    cal.mapx = cal.mapx + 3.0  # the raw image is the pinhole one shifted 3 px right
    cal.k[2] -= 1.5  # and the pinhole's principal point differs from the configured one
    depth, ab = frames[0].depth_mm, frames[0].ir
    with Hl2ssReplayServer([[record(frames[0], 0, rig_pose(0))]], calibration=cal) as srv:
        src = Hl2ssFrameSource(cfg(srv.port, mode=1, download_calibration=True))
        src.open()
        g = src.read()
        src.close()
    assert g.intrinsics.cx == pytest.approx(float(cal.k[2])) == src.intrinsics.cx
    assert np.array_equal(g.depth_mm[:, :-3], depth[:, 3:]) and not g.depth_mm[:, -3:].any()
    assert np.array_equal(g.ir[:, :-3], ab[:, 3:])


def closed_without_a_byte(s: socket.socket) -> bool:
    """The peer closed: EOF, or a reset when it left configuration bytes unread."""
    try:
        return s.recv(1) == b""
    except ConnectionResetError:
        return True


def test_the_replay_server_refuses_what_the_app_refuses():
    frames = sim_frames(1)
    with Hl2ssReplayServer([[record(frames[0], 0)]]) as srv:
        for bad in (struct.pack("<BBBBBIB", 0, 1, 0, 0xFF, 0xFF, 0, 0),  # bitrate 0: old client
                    struct.pack("<BBBBBIB", 0, 0, 0, 0xFF, 0xFF, 1000, 0),  # divisor 0
                    struct.pack("<BBBBBIB", 0, 1, 3, 0xFF, 0xFF, 1000, 0)):  # fmt: skip
            with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as s:
                s.sendall(bad)
                assert closed_without_a_byte(s)
        src = Hl2ssFrameSource(cfg(srv.port))
        src.open()
        assert src.read() is not None  # the turn was kept for a client the app accepts
        src.close()
    assert len(srv.refusals) == 3 and "bitrate" in srv.refusals[0]
    assert [c.bitrate > 0 for c in srv.configs] == [True]
    assert ahat_configuration(0)[4:9] == struct.pack("<BI", 0xFF, srv.configs[0].bitrate)


def test_bad_bytes_are_dropped_and_counted_and_the_stream_recovers():
    frames = sim_frames(5)
    good = [encode_ahat_packet(k, f.depth_mm, f.ir, k) for k, f in enumerate(frames)]
    size_lie = struct.pack("<QI", 1, 100) + bytes(100)  # size_z/size_ab disagree with 100
    h264 = struct.pack("<QIII", 2, 8 + 5000 + 8, 0, 5000) + bytes(5000 + 8)  # not RAW
    garbage = b"\xff" * 64  # out of step: an impossible payload size
    truncated = good[3][: len(good[3]) // 2]
    srv = Hl2ssReplayServer([[good[0], size_lie, h264, good[1], garbage],
                             [good[2], truncated, None], [good[4]]])  # fmt: skip
    src = Hl2ssFrameSource(cfg(srv.port, retry_s=0.0))
    src.open()
    assert np.array_equal(src.read().ir, frames[0].ir)
    assert src.read() is None and src.dropped == {"size": 1}
    assert src.read() is None and src.dropped["encoding"] == 1
    assert np.array_equal(src.read().ir, frames[1].ir)  # still in step after both
    assert src.read() is None and src.dropped["out_of_step"] == 1  # connection dropped
    assert np.array_equal(src.read().ir, frames[2].ir)  # reconnected: the next turn
    assert src.read() is None and src.dropped["disconnected"] == 1  # cut mid-packet
    assert np.array_equal(src.read().depth_mm, frames[4].depth_mm)
    assert len(srv.configs) == 3 and src.received == 4
    src.close()
    srv.close()


def test_a_stalled_packet_times_out_and_is_completed_on_the_next_read():
    frames = sim_frames(2)
    p0 = encode_ahat_packet(0, frames[0].depth_mm, frames[0].ir)
    p1 = encode_ahat_packet(1, frames[1].depth_mm, frames[1].ir)
    gate = threading.Event()

    class GatedServer(Hl2ssReplayServer):  # sends half of p1, waits for the test, then the rest
        def _serve(self, conn):
            from humantele.tracking.hl2ss_protocol import read_configuration

            read_configuration(lambda n: self._recv_exactly(conn, n))
            conn.sendall(p0 + p1[:700_000])
            gate.wait(30)
            conn.sendall(p1[700_000:])
            conn.recv(1)

    with GatedServer([]) as srv:
        src = Hl2ssFrameSource(cfg(srv.port, read_timeout_s=0.3))
        src.open()
        assert np.array_equal(src.read().ir, frames[0].ir)
        assert src.read() is None and src.dropped == {"timeout": 1}  # half a packet so far
        gate.set()
        g = src.read()
        src.close()
    assert g is not None and np.array_equal(g.ir, frames[1].ir)  # not out of step


def test_unreachable_headset_is_a_clear_error():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there
    for c in (cfg(port), cfg(port, mode=1, download_calibration=True)):
        with pytest.raises(FrameSourceUnavailable, match="hl2ss app running"):
            Hl2ssFrameSource(c).open()


def test_mode_1_needs_a_source_of_extrinsics(tmp_path):
    with pytest.raises(ValidationError, match="calibration_file"):
        Hl2ssFrameConfig(mode=1, download_calibration=False)
    assert Hl2ssFrameConfig().mode == 1  # the follower's default: frames with the rig pose
    with pytest.raises(FrameSourceUnavailable, match="hl2ss-calibration"):
        Hl2ssFrameSource(cfg(1, mode=1, calibration_file=str(tmp_path / "none.json"))).open()


def test_devices_check_reads_an_hl2ss_headset(tmp_path, capsys):
    frames = sim_frames(8)
    recs = [record(f, k, rig_pose(k)) for k, f in enumerate(frames)]
    # paced as the headset sends, for as long as the check reads (it takes the newest frame,
    # as the follower does, so a slow check skips some)
    with Hl2ssReplayServer([recs * 40], calibration=calibration(frames),
                           rate_hz=45.0) as srv:  # fmt: skip
        conf = tmp_path / "follower.toml"
        conf.write_text(f'[sensing.camera]\nbackend = "hl2ss"\nhost = "127.0.0.1"\n'
                        f'port = {srv.port}\nab_profile = "raw"\n')  # fmt: skip
        code = main(["devices", "check", "--follower-config", str(conf), "--only", "tracker",
                     "--samples", "8"])  # fmt: skip
    text = capsys.readouterr().out
    assert code == 0, text
    assert "[ok  ] tracker camera (hl2ss): 8/8 frames 512x512" in text
    assert "camera pose in 8" in text
    assert AHAT_PIXELS == 512 * 512


@pytest.mark.parametrize("compress", [True, False])
def test_records_file_round_trip(tmp_path, compress):
    frames = sim_frames(3)
    recs = [record(f, k, None if k == 1 else rig_pose(k)) for k, f in enumerate(frames)]
    path = tmp_path / "ahat.npz"
    save_records(path, recs, calibration(frames), compress=compress)
    back, cal = load_records(path)
    assert cal.T_rig_camera().distance_to(T_RIG_CAMERA)[0] < 1e-6
    assert [r.timestamp for r in back] == [r.timestamp for r in recs]
    assert back[1].T_world_rig is None and back[2].T_world_rig.distance_to(rig_pose(2))[0] < 1e-6
    assert np.array_equal(back[2].ab, recs[2].ab)
    assert np.array_equal(back[0].depth_mm, recs[0].depth_mm)
    stored = {i.compress_type for i in zipfile.ZipFile(path).infolist()}
    assert stored == {zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED}
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="bad.npz"):
        load_records(tmp_path / "bad.npz")


@pytest.mark.e2e
@pytest.mark.slow
def test_replay_server_in_its_own_process_paced_like_the_headset(tmp_path):
    frames = sim_frames(5)
    path = tmp_path / "ahat.npz"
    save_records(path, [record(f, k, rig_pose(k)) for k, f in enumerate(frames)],
                 calibration(frames))  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-m", "humantele.tracking.hl2ss_replay", str(path),
                             "--rate", "45"], stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        line = proc.stdout.readline()
        assert line.startswith("hl2ss replay listening on 127.0.0.1:"), line
        port = int(line.rsplit(":", 1)[1])
        for _ in range(2):  # every client gets the recording (repeat)
            src = Hl2ssFrameSource(cfg(port, mode=1, download_calibration=True,
                                       read_timeout_s=5.0))  # fmt: skip
            src.open()
            got = [src.read() for _ in frames]
            src.close()
            assert all(g is not None and g.T_world_camera is not None for g in got)
            assert np.array_equal(got[4].ir, frames[4].ir)
    finally:
        proc.terminate()
        proc.wait(10)
    assert proc.returncode == 0


def test_a_reader_that_fell_behind_skips_to_the_newest_frame():
    """TCP keeps every frame the headset sent: a reader slower than 45 Hz would see ever older
    frames. By default it takes the newest complete one there and counts the rest as stale.
    H.264 (the follower's default): the skipped frames still go through the decoder, so the
    newest, which refers to them, decodes. The server holds the turn after its first frame
    until the reader has it, then sends the other eleven (small packets: all fit in the
    sockets' buffers), so what has arrived does not depend on the machine's speed."""
    frames = sim_frames(12)
    records = [record(f, k) for k, f in enumerate(frames)]
    first_read = threading.Event()

    def turn():
        yield records[0]
        first_read.wait(30)
        yield from records[1:]

    with Hl2ssReplayServer([turn()]) as srv:
        src = Hl2ssFrameSource(cfg(srv.port, newest=True, ab_profile="h264_main",
                                   bitrate=12_000_000))  # fmt: skip
        src.open()
        first = src.read()
        k0 = src.last_sensor_ticks  # the frame's index (record()'s sensor ticks)
        first_read.set()
        # busy elsewhere while they arrive: all sent, then the last bytes in from loopback
        wait_for(lambda: srv.sent == len(records), what="the other eleven frames sent")
        arrived = -1
        while arrived != (arrived := _pending_bytes(src)):
            threading.Event().wait(0.05)
        newest = src.read()
        k = src.last_sensor_ticks
        src.close()
    assert srv.sent == len(records)
    assert first is not None and newest is not None
    assert (k0, k) == (0, 11)  # the newest of the eleven that had arrived
    assert src.dropped.get("stale", 0) == 10  # every frame before it but the first
    assert src.received == 2
    r = Tracker(load_tool("probe_default")).process(newest)  # it decoded whole
    assert r.T_camera_probe is not None
    err = np.linalg.norm(r.T_camera_probe.position - frames[11].T_camera_probe_true.position)
    assert err < 3e-3, err


def _pending_bytes(src: Hl2ssFrameSource) -> int:
    """The bytes waiting in the reader's socket (SIOCINQ)."""
    return struct.unpack("i", fcntl.ioctl(src._sock.fileno(), termios.FIONREAD, b"\0" * 4))[0]

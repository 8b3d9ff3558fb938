"""The hl2ss AHAT backend against a small server speaking the hl2ss protocol that replays the
project's simulated AHAT frames: same frames, same tracking figures; bad packets, a dropped
connection and an unreachable headset handled."""

import contextlib
import math
import socket
import struct
import threading

import numpy as np
import pytest

from humantele.geometry import Pose, quat_from_axis_angle, quat_multiply
from humantele.tracking.frames import FrameSourceUnavailable
from humantele.tracking.hl2ss_source import (
    Hl2ssFrameConfig,
    Hl2ssFrameSource,
    ahat_configuration,
    encode_ahat_packet,
)
from humantele.tracking.pipeline import Tracker
from humantele.tracking.sim import SimFrameConfig, SimFrameSource, default_sim_pose
from humantele.tracking.sources import make_frame_source
from humantele.tracking.tool import load_tool


class ReplayServer:
    """Accepts clients one after another; to each, after reading its configuration, sends the
    packets of its turn (a list of bytes; None = close the connection there)."""

    def __init__(self, turns: list[list[bytes | None]]):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.port = self.sock.getsockname()[1]
        self.configs: list[bytes] = []
        self.turns = turns
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        for packets in self.turns:
            conn, _ = self.sock.accept()
            with conn:
                cfg = b""
                while len(cfg) < 10:
                    cfg += conn.recv(10 - len(cfg))
                self.configs.append(cfg)
                cut = False  # None in the turn: the server drops the connection there
                for p in packets:
                    try:
                        if p is None:
                            cut = True
                            break
                        conn.sendall(p)
                    except ConnectionError:  # the client may leave before the last packet
                        cut = True
                        break
                if not cut:
                    with contextlib.suppress(ConnectionError):  # a client may reset it
                        conn.recv(1)  # keep it open until the client leaves

    def close(self) -> None:
        self.sock.close()


def sim_frames(n: int, seed: int = 3):
    sim = SimFrameSource(SimFrameConfig(seed=seed))
    base = default_sim_pose()
    frames = []
    for k in range(n):  # the probe sweeping and turning in front of the headset
        q = quat_multiply(quat_from_axis_angle([0, 1, 0], 0.3 * math.sin(k / 5)), base.quaternion)
        p = base.position + np.array([0.05 * math.sin(k / 7), 0.02 * math.cos(k / 4), 0.0])
        frames.append(sim.render(Pose(p, q), t=k / 45.0))
    return frames


def packet(frame, k: int) -> bytes:
    return encode_ahat_packet(10_000_000 + k * 222_222, frame.depth_mm, frame.ir, k)


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
    srv = ReplayServer([[packet(f, k) for k, f in enumerate(frames)]])
    src = make_frame_source(Hl2ssFrameConfig(host="127.0.0.1", port=srv.port))
    got = [src.read(t=f.t) for f in frames]
    src.close()
    srv.close()
    assert srv.configs == [ahat_configuration(0)]  # RAW depth and AB asked for
    assert struct.unpack("<BBBBBIB", srv.configs[0])[2:4] == (0, 0xFF)
    assert all(g is not None for g in got) and src.received == 40 and not src.dropped
    for g, f in zip(got, frames, strict=True):
        assert np.array_equal(g.ir, f.ir) and np.array_equal(g.depth_mm, f.depth_mm)
    assert src.last_timestamp == 10_000_000 + 39 * 222_222
    truths = [f.T_camera_probe_true for f in frames]
    sim_fig = figures(list(zip(frames, truths, strict=True)))
    net_fig = figures(list(zip(got, truths, strict=True)))
    assert net_fig["statuses"] == sim_fig["statuses"]
    assert np.array_equal(net_fig["poses"], sim_fig["poses"])
    assert net_fig["median_mm"] == sim_fig["median_mm"] and net_fig["max_mm"] == sim_fig["max_mm"]
    assert sim_fig["statuses"].count("tracked") >= 30  # the replay tracks, it is not all lost


def test_wrong_size_packets_are_dropped_and_a_lost_connection_is_retried():
    frames = sim_frames(4)
    bad = struct.pack("<QI", 1, 100) + bytes(100)  # e.g. an H.264 packet: not RAW
    srv = ReplayServer([[packet(frames[0], 0), bad, packet(frames[1], 1), None],
                        [packet(frames[2], 2), packet(frames[3], 3)]])  # fmt: skip
    src = Hl2ssFrameSource(Hl2ssFrameConfig(host="127.0.0.1", port=srv.port, retry_s=0.0))
    assert np.array_equal(src.read().ir, frames[0].ir)
    assert src.read() is None and src.dropped == {"size": 1}
    assert np.array_equal(src.read().ir, frames[1].ir)
    assert src.read() is None and src.dropped["disconnected"] == 1  # the headset went away
    f2 = src.read()  # reconnected
    assert f2 is not None and np.array_equal(f2.depth_mm, frames[2].depth_mm)
    assert len(srv.configs) == 2
    src.close()
    srv.close()


def test_mode_1_packets_carry_the_rig_pose():
    frames = sim_frames(1)
    pose = np.arange(16, dtype=np.float32).reshape(4, 4)
    p = encode_ahat_packet(5, frames[0].depth_mm, frames[0].ir, 0, pose)
    srv = ReplayServer([[p]])
    src = Hl2ssFrameSource(Hl2ssFrameConfig(host="127.0.0.1", port=srv.port, mode=1))
    assert src.read() is not None and np.array_equal(src.last_pose, pose)
    assert srv.configs[0][0] == 1
    src.close()
    srv.close()


def test_unreachable_headset_is_a_clear_error():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there
    with pytest.raises(FrameSourceUnavailable, match="hl2ss app running"):
        Hl2ssFrameSource(Hl2ssFrameConfig(host="127.0.0.1", port=port))

"""hl2ss's AHAT H.26x encodings against hl2ss's own client (vendored, tests/devices/vendor), the
configuration of them, the link model (bandwidth, stalls) and the headset's queue behind a
slow link (BacklogMonitor), and the hand tracker's 5 Hz spells."""

import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from humantele.config import ConfigError, validate_config
from humantele.tracking.hl2ss_backlog import BacklogMonitor
from humantele.tracking.hl2ss_codec import (
    H264_HIGH,
    H265_MAIN,
    AhatDecoder,
    AhatEncoder,
    default_bitrate,
    yuv420p_to_zab,
    zab_to_yuv420p,
)
from humantele.tracking.hl2ss_link import LinkConfig, TcpLinkRelay
from humantele.tracking.hl2ss_protocol import AhatConfiguration, PacketError
from humantele.tracking.hl2ss_replay import (
    AhatRecord,
    EncodedFrame,
    Hl2ssReplayServer,
    sensor_frames,
)
from humantele.tracking.hl2ss_source import Hl2ssFrameConfig, Hl2ssFrameSource
from humantele.tracking.pipeline import Tracker
from humantele.tracking.sim import SimFrameConfig, SimFrameSource, default_sim_pose
from humantele.tracking.tool import load_tool

VENDOR = Path(__file__).parent / "vendor" / "hl2ss"


@pytest.fixture(scope="module")
def hl2ss():
    sys.path.insert(0, str(VENDOR))
    try:
        import hl2ss as h
    finally:
        sys.path.remove(str(VENDOR))
    return h


@pytest.fixture(scope="module")
def frames():
    sim = SimFrameSource(SimFrameConfig(seed=2))
    base = default_sim_pose()
    return [sim.render(base, t=k / 45.0) for k in range(6)]


def test_packing_is_the_app_s_zab_to_nv12():
    depth = np.array([[0, 3, 4, 1023, 1024, 1055, 4089, 4090] * 64] * 512, np.uint16)
    ab = np.tile(np.array([0, 9, 1, 99, 4095, 7, 65535, 3], np.uint16), (512, 64))
    d, a = yuv420p_to_zab(zab_to_yuv420p(depth, ab))
    # Y = depth >> 2 narrowed to 8 bits (1024 mm and up wrap; >= 4090 invalid: 0), times 4
    assert list(d[0, :8]) == [0, 0, 4, 1020, 0, 28, 1016, 0]
    # AB of even columns to float16 (4095 rounds to 4096), square-rooted, toward zero,
    # squared, each over two columns; 65535 is inf in float16, saturated to 255
    assert list(a[0, :8]) == [0, 0, 1, 1, 64**2, 64**2, 255**2, 255**2]


@pytest.mark.parametrize("profile", [H264_HIGH, H265_MAIN])
def test_encoded_frames_decode_as_hl2ss_s_own_client_decodes_them(hl2ss, frames, profile):
    enc = AhatEncoder(AhatConfiguration(profile_ab=profile, bitrate=default_bitrate(profile)))
    ours, theirs = AhatDecoder(0, profile), hl2ss.decode_rm_depth_ahat(0, profile)
    for k, f in enumerate(frames):
        payload = enc.payload(f.depth_mm, f.ir, 70 + k)
        got, ref = ours.decode(payload), theirs.decode(payload)
        assert np.array_equal(got.depth_mm, ref.depth) and np.array_equal(got.ab, ref.ab)
        assert got.sensor_ticks == 70 + k == int(ref.sensor_ticks[0])
        valid = (f.depth_mm > 0) & (f.depth_mm < 1024)
        err = np.abs(got.depth_mm.astype(int) - f.depth_mm)[valid]
        assert np.median(err) <= 4  # 4 mm steps, then lossy
        assert np.median(np.abs(got.ab.astype(int) - f.ir)) < 0.1 * f.ir.max()


def test_a_skipped_frame_keeps_the_stream_decodable_and_bad_bytes_are_named(frames):
    enc = AhatEncoder(AhatConfiguration(profile_ab=H264_HIGH, bitrate=8_000_000))
    payloads = [enc.payload(f.depth_mm, f.ir, k) for k, f in enumerate(frames)]
    full, skipping = AhatDecoder(0, H264_HIGH), AhatDecoder(0, H264_HIGH)
    for p in payloads[:-1]:
        full.decode(p)
        skipping.skip(p)
    a, b = full.decode(payloads[-1]), skipping.decode(payloads[-1])
    assert np.array_equal(a.ab, b.ab) and np.array_equal(a.depth_mm, b.depth_mm)
    raw = AhatEncoder(AhatConfiguration()).payload(frames[0].depth_mm, frames[0].ir)
    with pytest.raises(PacketError) as exc:
        AhatDecoder(0, H264_HIGH).decode(raw)
    assert exc.value.reason == "encoding"
    with pytest.raises(PacketError) as exc:
        AhatDecoder(0, H264_HIGH).decode(payloads[0][:-20])
    assert exc.value.reason == "size"


def test_configuration_of_the_stream_settings():
    c = Hl2ssFrameConfig(ab_profile="h264_high", download_calibration=True)
    assert c.profile_ab == 2 and c.stream_bitrate == 512 * 512 * 45 * 12 // 75 * 16
    assert Hl2ssFrameConfig(ab_profile="h265_main", bitrate=20_000_000).stream_bitrate == 20e6
    for bad, field in [({"depth_profile": "zdepth"}, "depth_profile"),
                       ({"ab_profile": "vp8"}, "ab_profile"),
                       ({"bitrate": 0}, "bitrate")]:  # fmt: skip
        with pytest.raises(ConfigError, match=field):
            validate_config(Hl2ssFrameConfig, {"backend": "hl2ss", **bad}, "follower.toml")
    with pytest.raises(ConfigError, match="pyzdepth"):
        validate_config(Hl2ssFrameConfig, {"depth_profile": "zdepth"}, "follower.toml")


def test_client_reads_h264_from_the_replay_server_and_zdepth_is_refused(frames):
    recs = [AhatRecord(1000 + k, f.depth_mm, f.ir, k) for k, f in enumerate(frames)]
    with Hl2ssReplayServer([recs, recs]) as srv:
        c = Hl2ssFrameConfig(host="127.0.0.1", port=srv.port, mode=0, newest=False,
                             download_calibration=False, ab_profile="h264_main",
                             bitrate=12_000_000)  # fmt: skip
        src = Hl2ssFrameSource(c)
        src.open()
        got = [src.read() for _ in frames]
        src.close()
        with socket.create_connection(("127.0.0.1", srv.port)) as s:  # ZDEPTH: closed
            s.sendall(AhatConfiguration(mode=0, profile_z=1, profile_ab=0, bitrate=1).pack())
            s.settimeout(10)
            assert s.recv(1) == b""
    (cfg,) = srv.configs
    assert (cfg.profile_z, cfg.profile_ab, cfg.bitrate) == (0, 1, 12_000_000)
    assert cfg.options == {10: 45}  # hl2ss_lnm's GOP for H.26x: the frame rate
    assert any("Zdepth" in r for r in srv.refusals)
    assert all(g is not None for g in got) and not src.dropped
    tracker, errs = Tracker(load_tool("probe_default")), []
    for g, f in zip(got, frames, strict=True):
        valid = (f.depth_mm > 0) & (f.depth_mm < 1024)
        assert np.median(np.abs(g.depth_mm.astype(int) - f.depth_mm)[valid]) <= 4
        assert g.ab_paired and g.intrinsics.cx == f.intrinsics.cx + 0.5  # hl2ss's AB shift
        r = tracker.process(g)  # the paired AB's shape check, the biases taken back
        assert r.T_camera_probe is not None
        errs.append(np.linalg.norm(r.T_camera_probe.position - f.T_camera_probe_true.position))
    assert np.median(errs) < 1.5e-3


def test_spells_capture_one_frame_in_nine_and_the_server_sends_those():
    got = sensor_frames(2.0, [(0.0, 1.0)])
    assert [k for k, _ in got[:5]] == [0, 9, 18, 27, 36] and len(got) == 5 + 45
    rng = np.random.default_rng(0)
    d, a = rng.integers(0, 900, (2, 512, 512), dtype=np.uint16)
    recs = [AhatRecord(k, d, a, k) for k in range(90)]
    with Hl2ssReplayServer([recs], rate_hz=45.0, spells=[(0.0, 1.0)]) as srv:
        c = Hl2ssFrameConfig(host="127.0.0.1", port=srv.port, mode=0, newest=False,
                             download_calibration=False, read_timeout_s=5.0,
                             ab_profile="raw")  # fmt: skip
        src = Hl2ssFrameSource(c)
        src.open()
        ticks = []
        for _ in range(50):
            assert src.read() is not None
            ticks.append(src.last_sensor_ticks)
        src.close()
    assert ticks == [k for k, _ in got]


def test_the_link_carries_no_more_than_its_rate_and_a_stall_closes_nothing():
    blob = bytes(range(256)) * 4096  # 1 MiB
    server = socket.create_server(("127.0.0.1", 0))

    def serve():
        conn, _ = server.accept()
        conn.recv(1)
        conn.sendall(blob)
        conn.recv(1)  # until the client leaves
        conn.close()

    threading.Thread(target=serve, daemon=True).start()
    cfg = LinkConfig(bandwidth_mbps=40.0, delay_s=0.02, stalls=[(0.0, 0.3)])
    with TcpLinkRelay(server.getsockname(), cfg) as link:
        t0 = link.t0  # the stall's times count from the relay's start
        with socket.create_connection(("127.0.0.1", link.port)) as c:
            c.sendall(b"x")
            c.settimeout(30)
            got = b""
            while len(got) < len(blob):
                chunk = c.recv(1 << 20)
                assert chunk, "the link closed the connection"
                got += chunk
            took = time.monotonic() - t0
    server.close()
    assert got == blob
    # at least the stall, the delay and 1 MiB at 40 Mbit/s (a lower bound: a busy machine
    # only adds to it)
    assert took >= 0.3 + 0.02 + len(blob) * 8 / 40e6 - 0.005
    assert link.delivered == len(blob) and link.connections == 1


def test_backlog_monitor_finds_a_queue_not_a_clock_offset():
    m = BacklogMonitor(0.25)
    # clocks 1000 s apart, 30 ms transit: no queue however large the offset
    assert not any(m.late(k / 45, 1000.03 + k / 45) for k in range(90))
    # a link carrying 80 % of the stream: each frame 5.6 ms later than the last
    late = [m.late((90 + k) / 45, 1000.03 + (90 + k) / 45 + k * 0.0056) for k in range(60)]
    assert late.index(True) == 45 + 2 and m.backlog_s > 0.25  # 3 late frames in a row
    # one late frame (the client stalled, then read the newest) is not a queue
    m3 = BacklogMonitor(0.25)
    assert not any(m3.late(k / 45, 7.0 + k / 45 + (0.4 if k == 50 else 0)) for k in range(90))
    # a replay starting again (device time back): a new baseline, not a queue
    assert not m.late(0.0, 2000.0)
    # 100 ppm drift over 1000 s is not a queue
    m2 = BacklogMonitor(0.25)
    assert not any(m2.late(t, 5.0 + t * 1.0001) for t in np.arange(0, 1000, 1.0))


def test_a_queue_on_the_headset_drops_the_connection_and_age_stays_bounded(frames):
    """RAW frames (1 MiB) at 45 Hz, live-stamped, through a 60 Mbit/s link: the relay queues
    what the link cannot carry, as the app does; the client drops the connection when a frame
    waited max_backlog_s, so no frame is ever much older than that plus one frame's transit."""
    f = frames[0]
    n = 45 * 3
    recs = [EncodedFrame(k / 45.0, AhatEncoder(AhatConfiguration()).payload(f.depth_mm, f.ir, k),
                         255) for k in range(n)]  # fmt: skip
    with Hl2ssReplayServer([recs], repeat=True, live=True) as srv:
        with TcpLinkRelay(("127.0.0.1", srv.port), LinkConfig(bandwidth_mbps=60.0)) as link:
            c = Hl2ssFrameConfig(host="127.0.0.1", port=link.port, mode=0, newest=True,
                                 download_calibration=False, read_timeout_s=5.0,
                                 max_backlog_s=0.25, retry_s=0.0, ab_profile="raw")  # fmt: skip
            src = Hl2ssFrameSource(c)
            src.open()
            ages = []
            t_end = time.monotonic() + 4.0
            while time.monotonic() < t_end:
                g = src.read()
                if g is not None:
                    ages.append(g.t - g.device_time_s)
            src.close()
    assert src.dropped.get("backlog", 0) >= 1 and link.connections >= 2
    transit = 1.05e6 * 8 / 60e6
    # never a growing backlog: each frame at most the bound, one transit and slack for load
    assert len(ages) >= 3 and max(ages) < 0.25 + 2 * transit + 1.0

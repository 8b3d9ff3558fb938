"""The expert daemon's recording, scans and motion-scale setting, in process (servo and link
replaced by doubles that behave like them)."""

import errno
import io
import math
import time
from types import SimpleNamespace

import numpy as np
import pytest

from daemon_doubles import Clock, LinkDouble, ServoDouble
from humantele.config import ConfigError
from humantele.daemons.session import SessionConfig
from humantele.expert.cli import configs_from_args
from humantele.expert.config import ExpertConfig, servo_config_for
from humantele.expert.daemon import ExpertDaemon
from humantele.expert.mapping import MappingConfig
from humantele.expert.scans import ScanScriptConfig
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.haptics.servo_config import ServoConfig
from humantele.recording import Recorder, RecorderConfig, read_recording
from humantele.transport.clocksync import SyncSample
from humantele.wire import EllipsoidModel, EllipsoidParams, Scan


def make(tmp_path=None, stream=None, **config):
    d = ExpertDaemon(ExpertConfig(**config))
    d.servo, d.link, d.clock = ServoDouble(), LinkDouble(age_s=0.004), Clock()
    if tmp_path is not None or stream is not None:
        target = stream if stream is not None else tmp_path / "s.expert.mcap"
        fast = RecorderConfig(flush_interval_s=0.01)
        d.rec = Recorder(target, "expert", session_id="s01", follower_id="F03",
                         sonographer_id="S1", config=fast)  # fmt: skip
    return d


def at(d, t):
    d.clock.t = t
    d.publish_pose(t)
    d.guarded(d.script_scans, t)
    d.guarded(d.record_reports, t)


def install_model(d):
    e = Ellipsoid((0.0, 0.0, 0.0), (10.0, 0.11, 0.15), 0.0)
    d.on_control(EllipsoidModel(model=EllipsoidParams(**e.to_dict())))


def test_poses_force_and_the_scripted_scan_are_recorded_as_sent(tmp_path):
    d = make(tmp_path, scans=ScanScriptConfig(start_after_model_s=0.5, length_s=1.0))
    d.clock.t = 10.0
    install_model(d)
    for i in range(200):  # 2 s at 100 Hz, the stylus sweeping along x
        d.servo.p_device = np.array([0.05 * math.sin(i / 30.0), 0.0, 0.0])
        at(d, 10.0 + i * 0.01)
    d.guarded(d.stop_scan, 12.0)  # at shutdown: nothing open any more
    d.rec.close()
    rec = read_recording(tmp_path / "s.expert.mcap")
    assert rec.complete and rec.session["follower_id"] == "F03"
    # Every published pose, with the PoseMessage's t, position and quaternion.
    poses = rec.samples("/expert/pose")
    assert len(poses) == len(d.link.poses) == 200
    for s, msg in zip(poses, d.link.poses, strict=True):
        assert s["t"] == pytest.approx(msg.t_sent, abs=1e-6)
        assert np.allclose(s["position"], msg.position, atol=1e-6)
        assert np.allclose(s["quaternion"], msg.quaternion, atol=1e-7)
    forces = rec.samples("/expert/force")
    assert len(forces) == 200 and forces[-1]["force"][1] > forces[0]["force"][1] > 0
    # One scan: from 0.5 s after the model, 1 s long; ids with it; the follower was told.
    scan = rec.samples("/expert/scan")
    assert [(s["event"], s["scan"]) for s in scan] == [("start", 1), ("stop", 1)]
    assert scan[0]["t"] == pytest.approx(10.5, abs=0.011)
    assert scan[1]["t"] - scan[0]["t"] == pytest.approx(1.0, abs=0.011)
    assert scan[0]["follower_id"] == "F03" and scan[0]["sonographer_id"] == "S1"
    sent = [c for c in d.link.controls if isinstance(c, Scan)]
    assert [(c.action, c.scan_id) for c in sent] == [("start", "1"), ("stop", "1")]
    assert d.scan is None and d.scans_started == 1


def test_repeated_scans_and_the_open_scan_stopped_at_shutdown(tmp_path):
    d = make(tmp_path, scans=ScanScriptConfig(start_after_model_s=0.0, length_s=0.5,
                                              repeat=True, gap_s=0.2))  # fmt: skip
    install_model(d)
    for i in range(160):
        at(d, i * 0.01)
    assert d.scans_started == 3 and d.scan == 3  # 0-0.5, 0.7-1.2, 1.4-
    d.stop_scan(1.6)
    d.rec.close()
    events = [(s["event"], s["scan"]) for s in read_recording(d.rec.path).samples("/expert/scan")]
    assert events == [("start", 1), ("stop", 1), ("start", 2), ("stop", 2), ("start", 3),
                      ("stop", 3)]  # fmt: skip


def test_no_scan_without_a_model_or_when_not_scripted():
    d = make(scans=ScanScriptConfig(enabled=True, start_after_model_s=0.0))
    for i in range(50):
        at(d, i * 0.01)
    assert d.scans_started == 0  # no patient model yet
    d = make(scans=ScanScriptConfig(enabled=False))
    install_model(d)
    for i in range(50):
        at(d, i * 0.01)
    assert d.scans_started == 0 and d.link.controls == []
    assert d.start_scan(1.0) == 1 and d.link.controls[-1].action == "start"  # by hand


def test_reports_clock_sync_on_change_servo_stats_and_latency(tmp_path):
    d = make(tmp_path)
    install_model(d)
    best = SyncSample(offset=0.25, rtt=0.002, t_local=0.5)
    for i in range(350):  # 3.5 s
        t = i / 100
        if i == 100:
            d.link.clock.best = best
        if i == 200:
            d.link.clock.best = SyncSample(offset=0.2501, rtt=0.001, t_local=1.95)
        if i % 2 == 0:  # the follower's state stream at 50 Hz
            d.on_state(SimpleNamespace(t_sent=t))
        d.servo.late_ticks = i // 100
        at(d, t)
    d.rec.close()
    rec = read_recording(d.rec.path)
    sync = rec.samples("/expert/clock_sync")
    assert [(s["t"], s["offset_s"], s["rtt_s"]) for s in sync] == [
        (0.5, 0.25, 0.002),
        (1.95, 0.2501, 0.001),
    ]
    stats = rec.samples("/expert/servo_stats")
    assert len(stats) == 4  # t = 0, 1, 2, 3 s
    assert stats[0]["rate_hz"] == 999.5 and stats[0]["period_p99_s"] == pytest.approx(1.04e-3)
    assert [s["late_ticks"] for s in stats] == [0, 1, 1, 1]  # since the last report
    assert {s["state"] for s in stats} == {"running"}
    latency = rec.samples("/expert/latency")
    assert latency and {s["name"] for s in latency} == {"state_one_way"}
    assert all(s["value_s"] == pytest.approx(0.004) for s in latency)


class _FullDisk(io.BytesIO):
    """A file that fills up after ``limit`` bytes (ENOSPC)."""

    def __init__(self, limit):
        super().__init__()
        self.limit = limit

    def write(self, b):
        if self.tell() + len(b) > self.limit:
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(b)

    def fileno(self):
        raise io.UnsupportedOperation("no fileno")


def test_a_full_disk_during_the_session_is_reported_and_the_session_goes_on():
    d = make(stream=_FullDisk(limit=6000))
    install_model(d)
    t = 0.0
    for _ in range(5000):  # until the disk is full (the writer thread flushes every 10 ms)
        t += 0.01
        d.servo.p_device = np.array([0.03 * math.sin(t), 0.0, 0.0])
        at(d, t)
        if d.rec.failed:
            break
        time.sleep(0.002)
    assert d.rec.failed and d.poses_sent > 10
    n = d.poses_sent
    for _ in range(20):  # the session goes on after the failure
        t += 0.01
        at(d, t)
    assert d.poses_sent == n + 20 and d.step_errors == 0
    st = d.stats()["recording"]
    assert "No space" in st["error"] and st["dropped"] > 0


async def test_an_unusable_recording_path_stops_the_daemon_at_start(tmp_path, capsys):
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"a previous session")
    d = ExpertDaemon(ExpertConfig(session=SessionConfig(record=str(existing))))
    assert await d.run(duration_s=0.1) == 2
    assert "exists" in capsys.readouterr().err
    assert existing.read_bytes() == b"a previous session"
    assert d.servo.pid is None  # the servo was never started


def test_one_motion_scale_setting_the_mappings(tmp_path):
    servo = servo_config_for(MappingConfig(scale=0.5), ServoConfig())
    assert servo.motion_scale == 0.5
    # The passivity check sees the scale in use: 2x motion doubles the stiffness at the hand.
    with pytest.raises(ConfigError, match="passive"):
        servo_config_for(MappingConfig(scale=2.0), ServoConfig())
    assert servo_config_for(MappingConfig(scale=2.0), ServoConfig(kp=100.0)).motion_scale == 2.0
    with pytest.raises(ConfigError, match=r"\[expert.mapping\] scale = 1.5"):
        servo_config_for(MappingConfig(), ServoConfig(motion_scale=1.5))
    cfg = tmp_path / "e.toml"
    cfg.write_text("[expert.mapping]\nscale = 1.0\n[servo]\nmotion_scale = 3.0\n")
    args = SimpleNamespace(config=str(cfg), signaling_url=None, room=None, record=None,
                           session_id=None, follower_id=None, sonographer_id=None)  # fmt: skip
    with pytest.raises(ConfigError, match="motion_scale"):
        configs_from_args(args)
    cfg.write_text("[expert.mapping]\nscale = 0.5\n")
    config, servo = configs_from_args(args)
    assert servo.motion_scale == config.mapping.scale == 0.5


def test_participant_ids_must_be_pseudonyms_at_start(tmp_path):
    args = SimpleNamespace(config=None, signaling_url=None, room=None, record="x.mcap",
                           session_id="s01", follower_id="Jane Doe",
                           sonographer_id=None)  # fmt: skip
    with pytest.raises(ConfigError, match="follower_id"):
        configs_from_args(args)
    args.follower_id, args.session_id = "F03", "s 01; rm"
    with pytest.raises(ConfigError, match="session_id"):
        configs_from_args(args)

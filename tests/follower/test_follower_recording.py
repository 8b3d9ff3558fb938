"""The follower daemon's recording, scans and sensing worker, in process on simulated time."""

import asyncio
import threading
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np
import pytest

from daemon_doubles import LinkDouble
from humantele.follower.daemon import FollowerConfig, FollowerDaemon
from humantele.follower.sim_human import probe_down_quat
from humantele.geometry import Pose
from humantele.recording import Recorder, RecorderConfig, read_recording
from humantele.transport.clocksync import SyncSample
from humantele.wire import PoseMessage, Scan


def make(tmp_path, record=True, **kw):
    d = FollowerDaemon(FollowerConfig(state_dir=str(tmp_path), probe_source="truth", **kw))
    d.link = LinkDouble(age_s=0.006)
    if record:
        d.rec = Recorder(tmp_path / "s.follower.mcap", "follower", session_id="s01",
                         config=RecorderConfig(flush_interval_s=0.01))  # fmt: skip
    return d


def calibrate(d, rate=100.0):
    d.start_calibration()
    d.clinic.script_t0 = 0.0
    t = 0.0
    for _ in range(int(12.0 * rate)):
        d.tick(t)
        t += 1.0 / rate
    assert d.calibration is not None
    return t


def follow(d, t0, seconds, rate=100.0):
    b = d.calibration.ellipsoid.semi_axes[1]
    q = probe_down_quat([0.0, 1.0, 0.0])
    t = t0
    for _ in range(int(seconds * rate)):
        p = [0.03 * np.sin(0.5 * t), b + 0.005, 0.02 * np.cos(0.5 * t)]
        d.on_pose(PoseMessage.from_pose(int(t * 100), t, Pose(p, q)))
        d.last_pose_rx = t
        d.tick(t)
        d.record_reports(t)
        t += 1.0 / rate
    return t


def test_calibration_model_probe_pose_and_force_are_recorded(tmp_path):
    d = make(tmp_path)
    t = calibrate(d)
    n_states = len(d.link.states)
    follow(d, t, 3.0)
    d.rec.close()
    rec = read_recording(tmp_path / "s.follower.mcap")
    assert rec.complete and rec.session["role"] == "follower"
    # Calibration: reset, the four landmarks (world frame), the fit; the world-frame model.
    cal = rec.samples("/follower/calibration")
    assert [c["event"] for c in cal] == ["reset", "point", "point", "point", "point", "fit"]
    assert [c["landmark"] for c in cal[1:5]] == ["xiphoid", "left", "right", "bed"]
    truth = d.clinic.world.patient.landmarks()
    for c in cal[1:5]:  # pressed on the true landmark (within the press depth)
        assert np.linalg.norm(np.array(c["position"]) - truth[c["landmark"]]) < 0.03
    (model,) = rec.samples("/follower/ellipsoid")
    assert np.allclose(model["center"], d.calibration.ellipsoid.center, atol=1e-6)
    assert np.allclose(model["semi_axes"], d.calibration.ellipsoid.semi_axes, atol=1e-6)
    assert model["heading"] == pytest.approx(d.calibration.ellipsoid.heading)
    # Probe poses: every tracker frame after the calibration (patient frame), as streamed.
    poses = rec.samples("/follower/probe_pose")
    following = d.link.states[n_states:]
    assert len(poses) >= len(following) > 100 and all(p["tracked"] for p in poses)
    by_t = {round(p["t"], 6): p for p in poses}
    for st in following:
        p = by_t[round(st.t_sent, 6)]
        assert np.allclose(p["position"], st.position, atol=1e-6)
        assert np.allclose(p["quaternion"], st.quaternion, atol=1e-7)
    # Forces: every frame, calibration included, in the tip frame as on the wire.
    forces = rec.samples("/follower/force")  # every frame with the probe in hand
    assert len(forces) == d.measurements > 600  # the force board reads, tracked or not
    f_by_t = {round(f["t"], 6): f["force"] for f in forces}
    pressed = [st for st in following if np.linalg.norm(st.force) > 0.1]
    for st in pressed:
        assert np.allclose(f_by_t[round(st.t_sent, 6)], st.force, atol=1e-6)
    # The pose stream's one-way latency, about once a second.
    lat = [s for s in rec.samples("/follower/latency") if s["name"] == "pose_one_way"]
    assert 2 <= len(lat) <= 4 and all(s["value_s"] == pytest.approx(0.006) for s in lat)
    stale = [s for s in rec.samples("/follower/latency") if s["name"] == "pose_stale_s"]
    # the first report covers the time since the fit (no pose yet: stale); then never stale
    assert len(stale) == len(lat) and all(s["value_s"] == 0.0 for s in stale[1:])


def test_the_time_the_virtual_probe_was_stale_is_recorded_once_a_second(tmp_path):
    d = make(tmp_path)
    t0 = calibrate(d)
    t = follow(d, t0, 1.5)
    for _ in range(200):  # 2 s without a pose: stale after stale_after_s (0.3 s)
        d.tick(t)
        d.record_reports(t)
        t += 0.01
    t = follow(d, t, 1.5)
    d.rec.close()
    rec = read_recording(d.rec.path)
    stale = [s for s in rec.samples("/follower/latency") if s["name"] == "pose_stale_s"]
    stale = [s for s in stale if s["t"] > t0 + 0.5]  # the first: the time before any pose
    total = sum(s["value_s"] for s in stale)
    assert total == pytest.approx(2.0 - d.config.stale_after_s, abs=0.03)
    assert all(0.0 <= s["value_s"] <= 1.01 for s in stale)  # per report, at most its second


def test_untracked_frames_are_recorded_as_such_and_clock_sync_on_change(tmp_path):
    d = make(tmp_path)
    t = calibrate(d)

    class Occluded:  # the sensing pipeline, when the markers are hidden
        def measure(self, t, world):
            f = np.array([0.0, 0.0, 1.5])
            return SimpleNamespace(status="lost", T_world_probe=None, force_world=np.zeros(3),
                                   force_probe=f, contact=False)  # fmt: skip

    d.sensing.pipeline = Occluded()
    d.link.clock.best = SyncSample(offset=-0.5, rtt=0.003, t_local=t)
    follow(d, t, 0.5)
    d.rec.close()
    rec = read_recording(d.rec.path)
    lost = [p for p in rec.samples("/follower/probe_pose") if p["t"] >= t]
    assert len(lost) >= 20
    assert all(not p["tracked"] and p["position"] == [0.0, 0.0, 0.0] for p in lost)
    assert all(p["quaternion"] == [0.0, 0.0, 0.0, 1.0] for p in lost)
    # The force is still measured (the tool's face is along -z: 1.5 N on the probe body's z is
    # -1.5 N along the tip frame's beam axis).
    forces = [f["force"] for f in rec.samples("/follower/force") if f["t"] >= t]
    assert forces and all(abs(abs(f[2]) - 1.5) < 1e-6 for f in forces)
    assert rec.samples("/follower/clock_sync") == [{"t": round(t, 6), "offset_s": -0.5,
                                                     "rtt_s": 0.003}]  # fmt: skip


def test_scans_from_the_expert_are_followed(tmp_path):
    d = make(tmp_path, record=False)
    d.on_control(Scan(action="start", scan_id="1"))
    assert d.stats()["scan"] == 1 and d.scans_seen == 1
    d.on_control(Scan(action="stop", scan_id="1"))
    d.on_control(Scan(action="start", scan_id="2"))
    assert d.scan == 2 and d.scans_seen == 2
    d.on_control(Scan(action="stop", scan_id="2"))
    assert d.scan is None and d.stats()["recording"] is None


def test_scans_from_the_expert_are_recorded_by_the_follower(tmp_path):
    d = make(tmp_path)
    d.on_control(Scan(action="start", scan_id="3"))
    d.on_control(Scan(action="stop", scan_id="3"))
    d.on_control(Scan(action="start", scan_id="not-a-number"))  # followed, not recorded
    d.rec.close()
    rec = read_recording(tmp_path / "s.follower.mcap")
    events = [(s["event"], s["scan"]) for s in rec.samples("/follower/scan")]
    assert events == [("start", 3), ("stop", 3)]


async def test_sensing_runs_off_the_loop_in_order_without_overlap(tmp_path):
    d = make(tmp_path, record=False, sensing_rate_hz=45.0)
    release = threading.Event()
    calls = []
    busy = threading.Lock()

    class SlowPipeline:  # the tracker: held until the test releases it
        def measure(self, t, world):
            assert busy.acquire(blocking=False), "two frames measured at once"
            try:
                calls.append((t, threading.get_ident()))
                assert release.wait(5.0)
                probe = world.T_world_tip @ d.sensing.T_tip_probe  # the sim world's, as measured
                return SimpleNamespace(status="tracked", T_world_probe=probe,
                                       force_world=np.zeros(3), force_probe=np.zeros(3),
                                       contact=False)  # fmt: skip
            finally:
                busy.release()

    d.sensing.pipeline = SlowPipeline()
    d.clinic.world.human.hand = Pose(
        [0.35, 1.0, -0.15], probe_down_quat([0.0, 1.0, 0.0])
    )  # probe in hand
    d.worker.executor = ThreadPoolExecutor(1)
    loop_thread = threading.get_ident()
    try:
        t = 0.0
        for _ in range(30):  # 0.3 s of ticks while the first frame is still being measured
            d.tick(t)
            t += 0.01
            await asyncio.sleep(0)
        assert len(calls) == 1 and calls[0][1] != loop_thread
        assert d.measurements == 0 and d.worker.skipped == 13  # frames due at 45 Hz, skipped
        release.set()
        for _ in range(100):
            d.tick(t)
            t += 0.01
            await asyncio.sleep(0.002)  # the worker's result comes back on the loop
    finally:
        release.set()
        d.worker.executor.shutdown(wait=True)
    await asyncio.sleep(0.05)
    times = [c[0] for c in calls]
    assert times == sorted(times) and len(times) == len(set(times))
    assert d.measurements >= len(calls) - 1 and d.measurements > 20
    assert d.measurement.T_world_tip is not None and d.tick_errors == 0

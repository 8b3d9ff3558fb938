"""The follower daemon's tick and handlers, in process, on simulated time."""

import numpy as np

from daemon_doubles import LinkDouble
from humantele.follower.daemon import FollowerConfig, FollowerDaemon
from humantele.follower.sim_human import probe_down_quat
from humantele.geometry import Pose
from humantele.wire import EllipsoidModel, Hello, PoseMessage


def make(tmp_path, **kw):
    cfg = FollowerConfig(state_dir=str(tmp_path), probe_source="truth", **kw)
    d = FollowerDaemon(cfg)
    d.link = LinkDouble(age_s=0.01)
    return d


def run_ticks(d, t0, seconds, rate=100.0, pose_fn=None):
    t = t0
    for _ in range(int(seconds * rate)):
        if pose_fn is not None:
            d.on_pose(pose_fn(t))
            d.last_pose_rx = t
        d.tick(t)
        t += 1.0 / rate
    return t


def test_calibrates_then_follows_the_virtual_probe(tmp_path):
    d = make(tmp_path)
    d.start_calibration()
    d.clinic.script_t0 = 0.0
    t = run_ticks(d, 0.0, 12.0)
    assert d.calibration is not None and not d.calibrating
    assert (tmp_path / "calibration.json").exists()
    models = [m for m in d.link.controls if isinstance(m, EllipsoidModel)]
    assert len(models) == 1 and models[0].model.center == (0.0, 0.0, 0.0)
    # The expert moves the virtual probe slowly over the model (patient frame, tip frame).
    b = d.calibration.ellipsoid.semi_axes[1]
    down = Pose([0, 0, 0], probe_down_quat([0.0, 1.0, 0.0]))  # beam (+z) along -y

    def pose(t):
        p = [0.03 * np.sin(0.5 * t), b + 0.005, 0.02 * np.cos(0.5 * t)]
        return PoseMessage.from_pose(int(t * 100), t, Pose(p, down.quaternion))

    run_ticks(d, t, 6.0, pose_fn=pose)
    st = d.stats()
    # Lag, offset and tremor of a novice: millimetres to a centimetre, as the anchors.
    assert 2.0 < st["alignment_mm_rms"] < 15.0
    assert 1.0 < st["alignment_deg_rms"] < 12.0
    # The state stream is the measured probe in the patient frame: near the virtual one.
    last = d.link.states[-1]
    assert np.linalg.norm(np.array(last.position) - pose(t + 6.0).position) < 0.03


def test_the_sim_technician_presses_once_the_sensing_process_measures(tmp_path):
    """A press while the sensing process starts would not be seen: the person waits above the
    first landmark, and presses once the tracker images are measured."""
    d = make(tmp_path)

    class Starting:  # the sensing process still importing: its tracker images are skipped
        running, ready = True, False

    d.worker.proc = Starting()
    d.start_calibration()
    d.clinic.script_t0 = 0.0
    forces, t = [], 0.0
    for _ in range(500):  # 5 s, more than two presses' time
        d.tick(t)
        forces.append(float(np.linalg.norm(d.clinic.world.force_world)))
        t += 0.01
    assert max(forces) == 0.0 and d.worker.starting > 0 and d.cal.calibrator.presses == 0
    d.worker.proc = None  # measured in line from now
    run_ticks(d, t, 8.0)
    assert d.calibration is not None and d.cal.calibrator.refusals == 0


def test_stale_without_poses_and_model_resent_on_hello(tmp_path):
    d = make(tmp_path)
    d.start_calibration()
    d.clinic.script_t0 = 0.0
    run_ticks(d, 0.0, 12.0)
    assert d.calibration is not None
    assert d.virtual_stale(100.0)  # no pose ever
    d.on_pose(PoseMessage.from_pose(1, 100.0, Pose.identity()))
    d.last_pose_rx = 100.0
    assert not d.virtual_stale(100.1) and d.virtual_stale(100.5)
    d.link.connected = False
    assert d.virtual_stale(100.1)
    d.link.connected = True
    n = len(d.link.controls)
    d.on_control(Hello(role="expert"))
    assert isinstance(d.link.controls[n], EllipsoidModel)
    # A restarted follower reuses the saved calibration: no presses needed.
    d2 = make(tmp_path)
    assert d2.calibration is not None and d2.cal.reused
    assert d2.calibration.ellipsoid == d.calibration.ellipsoid


def test_a_failing_sensing_step_is_lost_not_a_crash(tmp_path):
    d = make(tmp_path)

    class Broken:
        def measure(self, *a):
            raise RuntimeError("camera unplugged")

    d.sensing.pipeline = Broken()
    d.start_calibration()
    d.clinic.script_t0 = 0.0
    run_ticks(d, 0.0, 1.0)
    assert d.sensing.errors > 0 and d.measurement.T_world_tip is None
    assert d.calibration is None and d.link.states == []


def test_a_real_scanner_s_scale_goes_to_the_expert_after_each_hello(tmp_path):
    """The expert's calipers and depth scale take the follower's configured scanner scale."""
    from humantele.wire import UsScale

    card = {"backend": "opencv", "pixel_spacing_mm": [0.2, 0.25], "depth_origin_row": 96.0}
    d = make(tmp_path, video={"enabled": True, "us": card})
    sim = make(tmp_path / "sim", video={"enabled": True})  # the sim's: the demo tells the expert
    try:
        d.on_control(Hello(role="expert"))
        (scale,) = [m for m in d.link.controls if isinstance(m, UsScale)]
        assert scale.pixel_spacing_mm == (0.2, 0.25) and scale.depth_origin_row == 96.0
        sim.on_control(Hello(role="expert"))
        assert not [m for m in sim.link.controls if isinstance(m, UsScale)]
    finally:  # their video's shared memory (made with the daemon, never run here)
        d.video.close()
        sim.video.close()


async def test_a_start_that_cannot_record_frees_the_video_s_shared_memory(tmp_path):
    """The video's shared memory is made with the daemon; a run that stops at its start (the
    recording refused) frees it, not the resource tracker at exit (or no one, if killed)."""
    from pathlib import Path

    existing = tmp_path / "s.mcap"
    existing.write_bytes(b"an earlier session")
    d = make(tmp_path, video={"enabled": True}, session={"record": str(existing)})
    shm = [Path("/dev/shm", c.shm.name) for c in d.video.process.captures.values()]
    assert all(p.exists() for p in shm)
    assert await d.run(1.0) == 2
    assert not any(p.exists() for p in shm)

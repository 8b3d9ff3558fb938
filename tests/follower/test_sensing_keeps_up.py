"""Nothing stalls silently in the follower's sensing (issue 30 §2): with real devices the next
measurement starts as soon as the last is back (a tick skipped while busy is not a frame lost);
the frames not measured are counted by reason and the one that dominates is said; a sensing
child that stops answering is killed and restarted through its Restarter."""

from __future__ import annotations

import asyncio
import time
from types import SimpleNamespace

import pytest
from sensing_hang_child import hanging_sensing_main

from humantele.demo_report import devices_summary
from humantele.demo_status import devices_status, status_line
from humantele.follower.daemon import FollowerConfig
from humantele.follower.sensing import LOST, TrackerImage
from humantele.follower.sensing_process import SensingProcess
from humantele.follower.sensing_worker import (
    UNMEASURED_WINDOW_S,
    SensingWorker,
    UnmeasuredWindow,
    unmeasured_frames,
)
from waits import until

WAIT_S = 120.0  # a spawned child importing on a loaded machine


class FakeChild:
    """What SensingWorker uses of its SensingProcess: one frame in flight at most."""

    def __init__(self) -> None:
        self.running = self.ready = True
        self.busy = False
        self.sent: list[tuple[int, tuple]] = []
        self.hangs = self.restarts = 0
        self.device_stats = None
        self.failed = False

    def submit(self, job, frame) -> bool:
        if self.busy:
            return False
        self.sent.append((job, frame))
        self.busy = True
        return True

    def check_hung(self) -> bool:
        return False

    def answer(self, worker: SensingWorker) -> None:
        job = self.sent[-1][0]
        self.busy = False
        worker._measured_in_process(job, LOST, 0.01)


def worker_with_fake_child() -> tuple[SensingWorker, FakeChild, list]:
    measured = []
    w = SensingWorker(FollowerConfig(), None, lambda f, m: measured.append(f), lambda r: None)
    w.proc = FakeChild()
    return w, w.proc, measured


def test_with_real_devices_the_next_measurement_starts_as_soon_as_the_last_is_back():
    w, child, measured = worker_with_fake_child()
    w.submit(TrackerImage(1.0, None, "v1", "g1"))
    for k in range(3):  # ticks while the child measures: the device keeps its frames
        w.submit(TrackerImage(1.02 + 0.02 * k, None, f"v{k + 2}", f"g{k + 2}"))
    assert len(child.sent) == 1 and w.skipped == 3
    before = time.monotonic()
    child.answer(w)
    assert len(child.sent) == 2 and w.caught_up == 1  # at once, not at the next tick
    job, (t, world) = child.sent[1]
    assert world is None and t >= before  # stamped now: the device gives its newest frame
    assert measured[0].t == 1.0
    child.answer(w)
    assert measured[1].virtual == "v4" and measured[1].target == "g4"  # the latest tick's guide
    assert len(child.sent) == 2  # nothing due: waits for the next tick
    assert w.device_summary()["unmeasured"]["skipped"] == 0  # no frame was lost to a skipped tick


def test_the_sim_world_s_frames_skipped_while_busy_are_frames_lost():
    w, child, measured = worker_with_fake_child()
    w.submit(TrackerImage(1.0, "world at 1.0", None, None))
    w.submit(TrackerImage(1.02, "world at 1.02", None, None))
    child.answer(w)
    assert len(child.sent) == 1 and w.skipped == 1 and w.caught_up == 0
    assert w.device_summary()["unmeasured"]["skipped"] == 1


def devices(frames=0, no_pose=0, no_frame=0, stale=0, stalls=0, stalled=False):
    return {"frames": frames, "no_camera_pose": no_pose, "no_frame": no_frame,
            "camera": {"dropped": {"stale": stale, "stalled": stalls}, "stalls": stalls,
                       "reconnects": stalls, "stalled": stalled,
                       "no_pose": {"not_located": no_pose}},
            "force": {"stale": False, "board": {"unplugs": 1, "reopens": 1}},
            "force_stale": 3}  # fmt: skip


def test_unmeasured_frames_by_reason_and_the_one_that_dominates_lately():
    counts = unmeasured_frames(devices(40, 5, 2, 7, 1), skipped=3)
    assert counts == {"measured": 40, "no_pose": 5, "no_frame": 2, "stale": 7, "skipped": 3,
                      "stalls": 1}  # fmt: skip
    win = UnmeasuredWindow()
    assert win.update(0.0, unmeasured_frames(devices(100, 0), 0)) is None
    # the headset stops being located: most frames since come without the camera's pose
    assert win.update(1.0, unmeasured_frames(devices(110, 60), 0)) == "no_pose"
    assert 0.8 < win.share < 0.9
    # it is located again: after the window, the old spell no longer counts
    t = 1.0
    for k in range(1, 10):
        t += 1.0
        reason = win.update(t, unmeasured_frames(devices(110 + 45 * k, 60), 0))
    assert t - 1.0 > UNMEASURED_WINDOW_S and reason is None
    assert win.update(t + 1, unmeasured_frames(devices(110 + 45 * 9 + 2, 60), 0)) is None


def test_the_status_line_and_json_say_stalls_stale_force_and_the_dominant_reason():
    f = {"headset_stream_stalled": True, "force_stale": True, "unmeasured_dominant": "no_pose",
         "unmeasured_share": 0.83, "sensing_devices": devices(10, 50, stalls=2, stalled=True),
         "unmeasured": unmeasured_frames(devices(10, 50), 0), "sensing_hangs": 1}  # fmt: skip
    text = devices_status(f)
    assert text == (" | headset stream stalled | force board STALE | tracker frames 83% no "
                    "camera pose")  # fmt: skip
    assert text in status_line({"servo_state": "running"}, f, 3.0)
    assert devices_status({"headset_stream_stalled": False, "force_stale": False}) == ""
    s = devices_summary(f)
    assert s["stream_stalls"] == 2 and s["stream_reconnects"] == 2
    assert s["no_pose_reasons"] == {"not_located": 50} and s["force_board_unplugs"] == 1
    assert s["unmeasured"]["no_pose"] == 50 and s["sensing_hangs"] == 1


@pytest.mark.e2e  # starts the sensing child process (the fast lane leaves it out)
async def test_a_hung_sensing_child_is_killed_and_restarted():
    results = []
    proc = SensingProcess(None, None, lambda *r: results.append(r[0]), hung_s=1.0,
                          target=hanging_sensing_main)  # fmt: skip
    proc.start()
    try:
        await until(lambda: proc.ready, WAIT_S)
        first = proc.pid
        assert proc.submit(1, (0.0, None))
        await until(lambda: results == [1], WAIT_S)
        assert proc.device_stats == {"frames": 1}
        assert proc.submit(2, (0.0, None))
        sent = asyncio.get_running_loop().time()
        while proc.hangs == 0:  # the daemon's ticks: each one that finds it busy checks
            assert not proc.submit(3, (0.0, None))
            await asyncio.sleep(0.05)
        assert asyncio.get_running_loop().time() - sent >= 1.0  # not before hung_s
        assert "hung" in proc.restarter.down or proc.restarts == 1
        await until(lambda: proc.ready and proc.restarts == 1, WAIT_S)
        assert proc.pid != first
        assert proc.submit(4, (0.0, None))  # the replacement measures
        await until(lambda: results == [1, 4], WAIT_S)
    finally:
        proc.close()
    assert proc.hangs == 1


def test_probe_sensing_counts_frames_without_camera_pose_by_reason():
    from humantele.follower.sensing import ProbeSensing, SensingConfig
    from humantele.follower.sensing_devices import SensingDevices
    from humantele.forcesense.calibration import ForceCalibration
    from humantele.tracking.frames import FrameSource

    class Frames(FrameSource):  # an hl2ss-like source: frames without a pose, counted
        no_pose = {"not_located": 0}

        def open(self):
            pass

        def read(self, t=None):
            self.no_pose["not_located"] += 1
            return SimpleNamespace(T_world_rig=None, device_time_s=None, T_world_camera=None)

        def close(self):
            pass

    class Board:
        def open(self):
            pass

        def read(self, t=None):
            return None

        def close(self):
            pass

    import numpy as np

    cal = ForceCalibration(np.zeros((1, 3)), np.zeros(3), np.ones(3))
    ps = ProbeSensing(SensingConfig(), devices=SensingDevices(Frames(), Board(), cal))
    try:
        for k in range(3):
            m = ps.measure(float(k))
            assert m.T_world_probe is None and m.force_stale  # no board reading ever
        stats = ps.device_stats()
    finally:
        ps.close()
    assert stats["no_camera_pose"] == 3 and stats["frames"] == 0
    assert stats["camera"]["dropped"] == {} and unmeasured_frames(stats, 0)["no_pose"] == 3


def test_the_daemon_tells_the_headset_page_and_the_log_as_devices_stall_and_return(
    caplog, tmp_path
):
    import numpy as np

    from humantele.follower.daemon import FollowerConfig, FollowerDaemon
    from humantele.follower.sensing import Measurement, TrackerImage
    from humantele.tracking.status import TrackingStatus

    def measured(t: float, stalled: bool, stale: bool) -> None:
        """The daemon takes a measurement of a stalled stream and/or a stale force."""
        m = Measurement(TrackingStatus.LOST, None, np.zeros(3), False, None, None, None,
                        stale, stalled)  # fmt: skip
        d.take_measurement(TrackerImage(t, None, None, None), m)

    d = FollowerDaemon(FollowerConfig(state_dir=str(tmp_path), probe_source="truth"))
    published = []
    d.feed.publish = lambda kind, fields: published.append((kind, fields))
    caplog.set_level("INFO", logger="humantele.follower.device_watch")
    measured(0.0, False, False)
    assert published == []  # nothing changed
    measured(0.1, True, False)
    measured(0.2, True, False)  # once per change
    measured(0.3, False, True)
    assert published == [
        ("devices", {"headset_stream_stalled": True, "force_stale": False}),
        ("devices", {"headset_stream_stalled": False, "force_stale": True}),
    ]
    text = caplog.text
    assert text.count("headset stream stalled") == 1 and "headset stream back" in text
    assert "force board stale" in text

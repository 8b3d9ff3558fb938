"""The follower's sensing in a child process: frames measured there, answers on the loop,
a killed child restarted, a refused config reported, nothing left running."""

import asyncio
import multiprocessing as mp
import os
import signal

import numpy as np
import pytest

from humantele.follower.daemon import FollowerConfig, FollowerDaemon
from humantele.follower.sensing_process import RESTART_FIRST_S, SensingProcess
from humantele.follower.sensing_worker import SensingWorker
from humantele.follower.sim_human import probe_down_quat
from humantele.follower.sim_world import SimWorld
from humantele.geometry import Pose
from humantele.wire import TrackingStatus
from waits import until

pytestmark = pytest.mark.e2e  # each test starts the sensing child process (not in the fast lane)

WAIT_S = 120.0  # upper bound for a spawned child to import and calibrate on a loaded machine


def _held_probe_world() -> SimWorld:
    w = SimWorld()
    w.human.hand = Pose([0.35, 1.0, -0.15], probe_down_quat([0.0, 1.0, 0.0]))
    w.step(0.0, None)
    return w


async def test_the_child_measures_frames_restarts_when_killed_and_stops_cleanly():
    results = []
    proc = SensingProcess(FollowerConfig(), None, lambda *r: results.append(r))
    proc.start()
    world = _held_probe_world()
    try:
        await until(lambda: proc.ready, WAIT_S)
        first_pid = proc.pid
        assert first_pid != os.getpid()
        truth = world.truth(0.1)
        assert proc.submit(1, (0.1, truth))
        assert not proc.submit(2, (0.1, truth))  # one frame in flight at most
        await until(lambda: results, WAIT_S)
        job, m, seconds = results[0]
        assert job == 1 and seconds > 0
        assert m.status == TrackingStatus.TRACKED
        dp, _ = m.T_world_tip.distance_to(truth.T_world_tip)
        assert dp < 3e-3  # measured through the pipeline in the child, not the truth copied
        assert dp > 0.0
        t_kill = asyncio.get_running_loop().time()
        os.kill(first_pid, signal.SIGKILL)
        await until(lambda: proc.restarter.due_at is not None, WAIT_S)  # its back-off
        assert proc.running and not proc.ready and not proc.submit(3, None)  # being replaced
        assert _state_of(proc) == "restarting (1)"  # as the status line shows it
        await until(lambda: proc.restarts == 1 and proc.ready, WAIT_S)
        assert _state_of(proc) == "running"
        assert asyncio.get_running_loop().time() - t_kill >= RESTART_FIRST_S
        assert proc.pid != first_pid and not proc.failed
        assert proc.submit(3, (0.2, world.truth(0.2)))
        await until(lambda: len(results) == 2, WAIT_S)
        assert results[1][0] == 3 and results[1][1].status == TrackingStatus.TRACKED
    finally:
        pid = proc.pid
        proc.close()
    assert not proc.running
    try:
        os.kill(pid, 0)
        alive = True
    except ProcessLookupError:
        alive = False
    assert not alive


async def test_a_child_that_dies_too_often_is_given_up_and_the_daemon_measures_in_a_thread():
    """With ``max_restarts=0`` the first death is one too many: failed (the daemon measures in
    a thread), no replacement started."""
    proc = SensingProcess(FollowerConfig(), None, lambda *r: None, max_restarts=0)
    proc.start()
    try:
        await until(lambda: proc.ready, WAIT_S)
        os.kill(proc.pid, signal.SIGKILL)
        await until(lambda: proc.failed, WAIT_S)
        await asyncio.sleep(2 * RESTART_FIRST_S)  # past a back-off: nothing started
        assert proc.restarts == 0 and not proc.running and not _sensing_children()
        assert not proc.submit(1, None)
    finally:
        proc.close()


async def _killed_into_its_back_off(proc: SensingProcess) -> None:
    """Start ``proc``, SIGKILL its child once it is ready; back once the replacement is timed."""
    proc.start()
    await until(lambda: proc.ready, WAIT_S)
    os.kill(proc.pid, signal.SIGKILL)
    await until(lambda: proc.restarter.due_at is not None, WAIT_S)


async def test_a_close_during_the_back_off_starts_no_replacement():
    proc = SensingProcess(FollowerConfig(), None, lambda *r: None)
    try:
        await _killed_into_its_back_off(proc)
    finally:
        proc.close()
    await asyncio.sleep(2 * RESTART_FIRST_S)  # past the replacement's due time
    assert proc.restarts == 0 and not proc.running and not _sensing_children()


async def test_a_replacement_that_cannot_start_is_tried_again_after_a_longer_wait(
    monkeypatch, caplog
):
    """The first replacement's spawn fails (the system refused a process): said, and tried
    again after the doubled back-off, which starts it."""
    import humantele.follower.sensing_process as sp

    monkeypatch.setattr(sp, "RESTART_FIRST_S", 0.05)
    spawns, real_spawn = [], sp.spawn

    def spawn_refused_once(*args, **kwargs):
        spawns.append(asyncio.get_running_loop().time())
        if len(spawns) == 2:  # the first replacement
            raise OSError(11, "Resource temporarily unavailable")
        return real_spawn(*args, **kwargs)

    proc = SensingProcess(FollowerConfig(), None, lambda *r: None)
    monkeypatch.setattr(sp, "spawn", spawn_refused_once)
    proc.start()
    try:
        await until(lambda: proc.ready, WAIT_S)
        t_kill = asyncio.get_running_loop().time()
        os.kill(proc.pid, signal.SIGKILL)
        await until(lambda: proc.restarts == 1 and proc.ready, WAIT_S)
        assert len(spawns) == 3 and not proc.failed
        assert spawns[2] - spawns[1] >= 2 * 0.05 and spawns[1] - t_kill >= 0.05
        assert "Resource temporarily unavailable" in caplog.text
    finally:
        proc.close()


async def test_a_back_off_timer_that_fires_early_still_starts_the_replacement(monkeypatch):
    """asyncio may run a timer up to its clock's resolution early; the due time is then taken
    as reached (here the timer is run 5 s early, by hand)."""
    import humantele.follower.sensing_process as sp

    monkeypatch.setattr(sp, "RESTART_FIRST_S", 5.0)
    proc = SensingProcess(FollowerConfig(), None, lambda *r: None)
    try:
        await _killed_into_its_back_off(proc)
        proc._restart_at.cancel()  # noqa: SLF001 - the loop's timer, run early instead
        proc._restart_due()  # noqa: SLF001
        await until(lambda: proc.restarts == 1, 4.0)
    finally:
        proc.close()


def _state_of(proc: SensingProcess) -> str:
    """The follower's sensing state (its stats' ``sensing_state``) with ``proc`` measuring."""
    worker = SensingWorker(FollowerConfig(), None, lambda *a: None, lambda r: None)
    worker.proc = proc
    return worker.state()


def _sensing_children() -> list:
    return [c for c in mp.active_children() if c.name == "humantele-sensing"]


async def test_a_config_the_child_refuses_is_reported_once_and_not_restarted():
    errors = []
    proc = SensingProcess(FollowerConfig(tool="no_such_tool"), None, lambda *r: None, errors.append)
    proc.start()
    try:
        await until(lambda: errors, WAIT_S)
    finally:
        proc.close()
    assert proc.failed and proc.restarts == 0 and not proc.running
    assert "no_such_tool" in errors[0]
    assert not proc.submit(1, None)


class _Link:
    connected, state = True, "connected"
    counters = type("C", (), {"connections": 1, "sent": {}, "dropped": {}})()

    def send_state(self, msg):
        return True

    def send_control(self, msg):
        return True

    def age_of(self, t):
        return 0.01


async def test_the_daemon_streams_what_the_child_measured(tmp_path):
    d = FollowerDaemon(FollowerConfig(state_dir=str(tmp_path), sensing_worker="process"))
    d.link = _Link()
    d.clinic.world.human.hand = Pose([0.35, 1.0, -0.15], probe_down_quat([0.0, 1.0, 0.0]))
    d.worker.proc = SensingProcess(
        d.config, None, d.worker._measured_in_process, d.worker._cannot_start
    )
    d.worker.proc.start()
    try:
        await until(lambda: d.worker.proc.ready, WAIT_S)
        t = 0.0
        while d.measurements < 10:
            d.tick(t)
            t += 0.01
            await asyncio.sleep(0.005)
            assert t < 600.0
    finally:
        d.worker.proc.close()
    assert d.sensing.pipeline is None  # the daemon never built its own: the child measured
    assert d.measurement.T_world_tip is not None and d.tick_errors == 0
    s = d.stats()
    assert s["sensing_restarts"] == 0 and s["sensing_p50_ms"] is not None
    assert np.isfinite(d.last_force_n)

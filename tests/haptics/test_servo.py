"""The servo loop: force pipeline (ramp, swap, faults, limits, registration) and the process."""

import math
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from servo_helpers import pressing_config

from fuzz_examples import examples
from humantele.config import ConfigError, validate_config
from humantele.geometry import Pose, quat_from_axis_angle
from humantele.haptics.demo_patient import demo_model
from humantele.haptics.devices import DeviceState
from humantele.haptics.devices.sim import SimFault
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.haptics.renderer import (
    FAULT_BAD_DATA,
    FAULT_DEVICE,
    FAULT_STALE,
    ForceRenderer,
    auto_registration,
)
from humantele.haptics.servo import ServoProcess
from humantele.haptics.servo_config import ServoConfig
from humantele.haptics.servo_layout import ServoError
from waits import wait_for

MODEL = demo_model()
INSIDE = (0.0, -0.035, 0.0)  # device frame: 5 mm into the model with the auto registration


def state(t, p=INSIDE, **kw) -> DeviceState:
    return DeviceState(t, p, **kw)


def ticks(r: ForceRenderer, t0: float, t1: float, p=INSIDE, dt=1e-3):
    out = []
    for k in range(int(round((t1 - t0) / dt))):
        t = t0 + k * dt
        out.append(r.tick(state(t, p), t))
    return out


def test_auto_registration_puts_the_device_above_the_xiphoid():
    T = auto_registration(MODEL, 0.03)
    top = MODEL.center + [0.0, MODEL.semi_axes[1], 0.0]
    assert np.allclose(T.position, top + [0, 0.03, 0])
    assert MODEL.penetration(T.apply([0.0, -0.035, 0.0]))[0] == pytest.approx(0.005, abs=1e-6)


def test_force_ramps_in_without_a_kick_then_holds_kp_depth():
    r = ForceRenderer(ServoConfig())
    r.set_model(MODEL, 0.0)
    f = np.array(ticks(r, 0.0, 0.4))
    fy = f[:, 1]
    assert fy[0] == pytest.approx(0.0, abs=1e-9)
    assert fy[100] == pytest.approx(0.5 * 1.5, rel=0.02)  # halfway through the 0.2 s ramp
    assert np.all(np.diff(fy[:200]) <= 1.5 / 200 * 1.01)  # no step larger than the ramp
    assert fy[-1] == pytest.approx(300 * 0.005, rel=1e-3)  # kp * depth, up (+y)
    assert r.sample[5] == pytest.approx(0.005, abs=1e-6)


def test_model_swap_crossfades_and_none_is_free_space():
    r = ForceRenderer(ServoConfig())
    r.set_model(MODEL, 0.0)
    ticks(r, 0.0, 0.3)
    higher = Ellipsoid(MODEL.center + [0, 0.005, 0], MODEL.semi_axes, MODEL.heading)
    r.set_model(higher, 0.3)  # auto registration moves with it: same depth, same force
    f = np.array(ticks(r, 0.3, 0.6))
    assert np.all(np.abs(np.diff(f[:, 1])) < 0.02)
    r.set_model(None, 0.6)
    f = np.array(ticks(r, 0.6, 1.0))
    assert f[0, 1] > 1.4 and np.all(np.diff(f[:, 1]) <= 1e-12)  # fades out, never kicks
    assert np.all(f[250:] == 0.0)


def test_registration_rotates_force_back_into_the_device_frame():
    cfg = ServoConfig()
    r = ForceRenderer(cfg)
    r.set_model(MODEL, 0.0)
    top = MODEL.center + [0.0, MODEL.semi_axes[1], 0.0]
    # Device rotated 90 deg about world z: device +x points world +y (up).
    q = quat_from_axis_angle([0, 0, 1], math.pi / 2)
    r.set_registration(Pose(top + [0, 0.005, 0], q), 1.0, 0.0)
    f = ticks(r, 0.0, 0.5, p=(-0.01, 0.0, 0.0))  # 5 mm below the top in the world
    assert f[-1] == pytest.approx((300 * 0.005, 0.0, 0.0), abs=1e-6)
    pw = r.sample[0]
    assert pw == pytest.approx(tuple(top - [0, 0.005, 0]), abs=1e-9)


def test_motion_scaling_maps_device_motion_into_larger_world_motion():
    with pytest.raises(ValueError, match="not passive"):
        ServoConfig(motion_scale=2.0)  # the device feels 2 kp: the default gains no longer pass
    r = ForceRenderer(ServoConfig(motion_scale=2.0, kp=150.0, kd=0.05))
    r.set_model(MODEL, 0.0)
    f = ticks(r, 0.0, 0.3, p=(0.0, -0.0175, 0.0))
    assert r.sample[5] == pytest.approx(0.005, abs=1e-6)  # 2 x 17.5 mm - 30 mm clearance
    assert f[-1][1] == pytest.approx(150 * 0.005, rel=1e-3)


def test_stale_data_zeroes_force_and_recovers_with_a_ramp():
    r = ForceRenderer(ServoConfig())
    r.set_model(MODEL, 0.0)
    ticks(r, 0.0, 0.3)
    f = r.tick(state(0.29), 0.3)  # 10 ms old
    assert f == (0.0, 0.0, 0.0) and r.sample[7] & FAULT_STALE
    assert r.counts["stale"] == 1 and r.counts["episodes"] == 1
    f = np.array(ticks(r, 0.301, 0.7))
    assert np.all(f[:49] == 0.0)  # held off for fault_hold_s
    assert 0.0 < f[60, 1] < 1.0  # ramping in again
    assert f[-1, 1] == pytest.approx(1.5, rel=1e-3) and r.sample[7] == 0


def test_bad_data_and_device_errors_give_zero_force():
    r = ForceRenderer(ServoConfig())
    r.set_model(MODEL, 0.0)
    ticks(r, 0.0, 0.3)
    assert r.tick(state(0.3, (math.nan, 0.0, 0.0)), 0.3) == (0.0, 0.0, 0.0)
    assert r.sample[7] & FAULT_BAD_DATA
    assert r.tick(None, 0.301) == (0.0, 0.0, 0.0)
    assert r.sample[7] & FAULT_DEVICE
    r.tick(state(0.302, quaternion=(0.0, 0.0, 0.0, 0.0)), 0.302)  # not a rotation
    assert r.sample[7] & FAULT_BAD_DATA and r.counts["bad_data"] == 2
    Pose(r.sample[0], r.sample[1])  # the published sample stays a valid pose


finite = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=examples(300), deadline=None)
@given(p=st.tuples(finite, finite, finite), v=st.tuples(finite, finite, finite), dt=st.floats(0, 1))
def test_never_nan_never_over_limit(p, v, dt):
    r = ForceRenderer(ServoConfig(force_limit_n=2.0))
    r.set_model(MODEL, -1.0)
    r.tick(state(0.0), 0.0)
    f = r.tick(DeviceState(dt, p, velocity=v), dt)
    assert all(math.isfinite(c) for c in f)
    assert math.sqrt(sum(c * c for c in f)) <= 2.0 + 1e-9


def test_config_errors_name_the_field():
    with pytest.raises(ConfigError, match="force_limit_n"):
        validate_config(ServoConfig, {"force_limit_n": 20})
    with pytest.raises(ConfigError, match=r"device\.backend: unknown backend 'nope'"):
        validate_config(ServoConfig, {"device": {"backend": "nope"}})
    with pytest.raises(ConfigError, match=r"device\.backend: .*'kind' is now called 'backend'"):
        validate_config(ServoConfig, {"device": {"kind": "hid"}})
    cfg = validate_config(ServoConfig, {"device": {"backend": "hid"}, "kp": 4000})
    assert cfg.device.backend == "hid"  # no force output: the gains cannot destabilise it


# ------------------------------------------------------------------ the servo process


@pytest.mark.e2e  # starts the servo process (the fast lane leaves it out)
def test_process_runs_swaps_model_and_stops_cleanly():
    sp = ServoProcess(pressing_config(), MODEL)
    sp.start()
    try:
        s = wait_for(lambda: (x := sp.latest()) and x.tick > 300 and x.ramp == 1.0 and x)
        assert s.force[1] > 0.5 and s.depth > 0 and s.fault == ""
        assert s.force[1] == pytest.approx(300 * s.depth, rel=0.1)
        assert (
            isinstance(s.T_patient_stylus, Pose)
            and isinstance(s.T_device_stylus, Pose)
            and s.t <= time.monotonic()
        )
        sp.set_model(None)
        wait_for(lambda: (x := sp.latest()) and x.force == (0.0, 0.0, 0.0))
        st_ = wait_for(lambda: (x := sp.stats()) and x.ticks > 0 and x)
        assert st_.rate_hz > 0 and st_.period_p50_us > 0 and st_.period_max_us >= st_.period_p50_us
        assert st_.nonfinite_forces == 0
    finally:
        sp.stop()
    assert not sp.alive
    assert sp.stats().ticks > 300


@pytest.mark.e2e  # starts the servo process (the fast lane leaves it out)
def test_process_stale_fault_zeroes_force_then_recovers():
    # 2 s of stale readings: a test process descheduled for a while (a busy machine) still
    # sees them (0.4 s was missed once with the suite's other worker busy)
    cfg = pressing_config(faults=[SimFault(kind="stale", start_s=0.6, duration_s=2.0)])
    with ServoProcess(cfg, MODEL) as sp:
        wait_for(lambda: (x := sp.latest()) and x.force[1] > 1.0)
        s = wait_for(lambda: (x := sp.latest()) and "stale" in x.fault and x)
        assert s.force == (0.0, 0.0, 0.0) and s.force_device == (0.0, 0.0, 0.0)
        wait_for(lambda: (x := sp.latest()) and x.fault == "" and x.force[1] > 1.0)
        assert sp.stats().fault_episodes >= 1
        assert sp.stats().stale_ticks > 0


@pytest.mark.e2e  # starts the servo process (the fast lane leaves it out)
def test_process_reports_device_errors_at_start():
    cfg = ServoConfig(device={"backend": "touchx", "library": "/nonexistent/libHD.so"})
    with pytest.raises(ServoError, match="libHD"):
        ServoProcess(cfg).start()


@pytest.mark.e2e  # starts the servo process (the fast lane leaves it out)
def test_sigterm_stops_the_servo_with_force_zeroed():
    sp = ServoProcess(pressing_config(), MODEL)
    sp.start()
    try:
        wait_for(lambda: (x := sp.latest()) and x.force[1] > 1.0)
        os.kill(sp.pid, signal.SIGTERM)
        wait_for(lambda: not sp.alive, 5.0)
        assert sp._proc.exitcode == 0
        assert sp.latest().force == (0.0, 0.0, 0.0)
    finally:
        sp.stop()


@pytest.mark.slow
def test_parent_death_stops_the_servo(tmp_path):
    script = textwrap.dedent(
        """
        import time
        from humantele.haptics.servo_config import ServoConfig
        from humantele.haptics.servo import ServoProcess
        from humantele.haptics.demo_patient import demo_model
        if __name__ == "__main__":
            sp = ServoProcess(ServoConfig(realtime_priority=0), demo_model())
            sp.start()
            print(sp.pid, flush=True)
            time.sleep(60)
        """
    )
    f = tmp_path / "parent.py"
    f.write_text(script)
    parent = subprocess.Popen([sys.executable, str(f)], stdout=subprocess.PIPE, text=True)
    try:
        child = int(parent.stdout.readline())
        os.kill(child, 0)  # running
        parent.kill()
        parent.wait()

        def gone():
            try:
                os.kill(child, 0)
            except ProcessLookupError:
                return True
            # A zombie until reaped by init counts as gone.
            with open(f"/proc/{child}/stat") as fh:
                return fh.read().split()[2] == "Z"

        wait_for(gone, 5.0)
    finally:
        parent.kill()


def _seqlock_writer(name: str, n: int, stop) -> None:
    """Child process: write np.full(n, k) for k = 1, 2, ... until told to stop."""
    from humantele.haptics.shm import SeqlockArray

    w = SeqlockArray(n, name)
    k = 0.0
    while not stop.is_set():
        k += 1.0
        w.write(np.full(n, k))
    w.close()


@pytest.mark.e2e  # forks a writer process (the fast lane leaves it out)
def test_seqlock_readers_never_see_a_torn_write():
    """Writer and reader in two processes over shared memory, as the servo and daemon are."""
    import multiprocessing

    from humantele.haptics.shm import SeqlockArray

    n = 512  # wide enough that an unguarded copy overlapping a write tears
    owner = SeqlockArray(n)
    r = SeqlockArray(n, owner.name)
    ctx = multiprocessing.get_context("fork")
    stop = ctx.Event()
    child = ctx.Process(target=_seqlock_writer, args=(owner.name, n, stop), daemon=True)
    child.start()
    try:
        seen: set[float] = set()
        deadline = time.monotonic() + 60.0  # a hang guard only: the count below decides
        while len(seen) < 200 and time.monotonic() < deadline:
            a = r.read(timeout_s=5.0)
            assert np.all(a == a[0]), "a read mixed two writes"
            seen.add(float(a[0]))
        assert len(seen) >= 200  # the writer really was writing while we read
    finally:
        stop.set()
        child.join(10.0)
        r.close()
        owner.close()
        owner.unlink()


def test_seqlock_try_read_never_waits_on_a_write_in_progress():
    from humantele.haptics.shm import SeqlockArray

    w = SeqlockArray(4)
    r = SeqlockArray(4, w.name)
    try:
        w.write([1.0, 2.0, 3.0, 4.0])
        np.testing.assert_array_equal(r.try_read(), [1.0, 2.0, 3.0, 4.0])
        w._a[0] += 1.0  # the writer was preempted half-way through a write
        retries = r.retries
        assert r.try_read() is None
        assert r.retries - retries == 3  # three attempts and gives up: no wait, unlike read()
        with pytest.raises(TimeoutError):
            r.read(timeout_s=0.01)
        w._a[0] += 1.0  # the write completes
        assert r.try_read() is not None
    finally:
        r.close()
        w.close()
        w.unlink()


@pytest.mark.e2e  # starts the servo process (the fast lane leaves it out)
def test_servo_survives_a_daemon_preempted_mid_write():
    """A normal-priority daemon can be preempted inside a command write; the SCHED_FIFO servo
    keeps its last command (it used to spin 10 ms, then die with TimeoutError)."""
    sp = ServoProcess(pressing_config(), MODEL)
    sp.start()
    try:
        wait_for(lambda: (x := sp.latest()) and x.tick > 100 and x.force[1] > 0.0)
        sp._cmd._a[0] += 1.0  # odd: a write "in progress" for much longer than 10 ms
        tick0 = sp.latest().tick
        # Still rendering (a late tick on a loaded machine may zero one sample: wait for one).
        wait_for(lambda: (x := sp.latest()) and x.tick > tick0 + 100 and x.force[1] > 0.0)
        assert sp.alive
        sp._cmd._a[0] += 1.0  # the write completes; new commands take effect again
        sp.set_model(None)
        wait_for(lambda: (x := sp.latest()) and x.force == (0.0, 0.0, 0.0))
    finally:
        sp.stop()
    assert not sp.alive


@pytest.mark.e2e  # starts the servo process (the fast lane leaves it out)
def test_daemon_side_reads_survive_a_servo_killed_mid_write():
    sp = ServoProcess(pressing_config(), MODEL)
    sp.start()
    try:
        s0 = wait_for(lambda: (x := sp.latest()) and x.tick > 50 and x)
        st0 = wait_for(lambda: (x := sp.stats()) and x.ticks > 0 and x)
        os.kill(sp.pid, signal.SIGKILL)
        wait_for(lambda: not sp.alive)
        sp._out._a[0] += 1.0 if int(sp._out._a[0]) % 2 == 0 else 0.0  # left odd by the death
        sp._st._a[0] += 1.0 if int(sp._st._a[0]) % 2 == 0 else 0.0
        s1, st1 = sp.latest(), sp.stats()  # no TimeoutError into the daemon
        assert s1 is not None and s1.tick >= s0.tick and s1.t <= time.monotonic()
        assert st1.ticks >= st0.ticks
    finally:
        sp.stop()


def test_the_servo_read_while_another_thread_frees_it_is_the_last_sample():
    """The expert's loop reads the servo's sample while a restart frees the dead process's
    shared memory in an executor thread (a Ctrl-C during a servo restart: the loop met a
    closed block, TypeError, traceback, exit 1): a closed block reads as nothing new."""
    from humantele.haptics.shm import SeqlockArray

    block = SeqlockArray(4)
    block.write([1.0, 2.0, 3.0, 4.0])
    assert list(block.read()) == [1.0, 2.0, 3.0, 4.0]
    block.close()
    block.unlink()
    with pytest.raises(TimeoutError):
        block.read()
    block.write([5.0])  # a command to a servo that is gone: nowhere, no error

    servo = ServoProcess(ServoConfig())
    from humantele.haptics.servo_layout import CMD_LEN, SAMPLE_LEN, STATS_LEN

    servo._cmd, servo._out = SeqlockArray(CMD_LEN), SeqlockArray(SAMPLE_LEN)
    servo._st = SeqlockArray(STATS_LEN)
    servo._blocks = [servo._cmd, servo._out, servo._st]
    servo._out.close()  # freed by the other thread between the loop's check and its read
    assert servo.latest() is None  # nothing read yet: none (later: the last sample read)
    servo.stop()  # frees the rest, the list first
    assert servo._blocks == [] and servo.latest() is None

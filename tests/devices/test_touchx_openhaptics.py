"""The touchx backend run on a fake OpenHaptics libHD (tests/devices/fake_libhd.c).

The fake exports the HD functions the backend binds, with the same signatures, and runs the
scheduled callbacks either in its own 1 kHz thread (as the real servo thread) or tick by tick
from the test (``fake_tick``), so these tests do not depend on the machine's speed.
"""

import ctypes
import logging
import math
import os
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from humantele.haptics.demo_patient import demo_model
from humantele.haptics.devices import DeviceError, TouchX, TouchXConfig
from humantele.haptics.devices.touchx import describe_hd_error
from humantele.haptics.devices.touchx_reset import main as touchx_main
from humantele.haptics.devices.touchx_reset import reset_encoders
from humantele.haptics.renderer import ForceRenderer
from humantele.haptics.servo_config import ServoConfig
from waits import wait_for

TICKS, FRAMES, WRITES, FRAME_VIOL, THREAD_VIOL, RATE, PRIO, STATE, UPD_STYLE, CAL = range(10)
WARM_EVENTS, EXCEEDED, WATCHDOG, ENC_RESET_RUNNING, UPDATES, SAFETY_CAPS, WARM = range(10, 17)
INITS, CALLBACKS = 17, 18
OK, NEEDS_UPDATE, NEEDS_MANUAL = 0x5000, 0x5001, 0x5002
ENCODER_RESET, AUTO, INKWELL = 1, 2, 4


def set_pose(fake, R, t_mm):
    m = np.eye(4)
    m[:3, :3] = R
    m[:3, 3] = t_mm
    arr = (ctypes.c_double * 16)(*m.T.reshape(-1))  # column-major, as HD
    fake.fake_set_transform(arr)


def forces(fake):
    return [fake.fake_force(i) for i in range(3)]


def test_open_schedules_one_max_priority_callback_at_1khz(fake_hd):
    path, fake = fake_hd
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    assert fake.fake_counter(STATE) == 111  # force output enabled, scheduler running, inited
    assert fake.fake_counter(RATE) == 1000
    assert fake.fake_counter(PRIO) == 0xFFFF  # HD_MAX_SCHEDULER_PRIORITY
    assert fake.fake_counter(SAFETY_CAPS) == 11  # HD_MAX_FORCE_CLAMPING and HD_FORCE_RAMPING
    assert (dev.model, dev.serial) == ("Touch X (fake)", "00000-fake")
    with pytest.raises(DeviceError, match="no servo tick yet"):
        dev.read()
    fake.fake_tick(5)
    assert dev.ticks == 5 and fake.fake_counter(FRAMES) == 5 and fake.fake_counter(WRITES) == 5
    dev.close()
    assert fake.fake_counter(STATE) == 0  # scheduler stopped, device disabled
    dev.close()  # twice is fine


def test_pose_mm_to_m_and_force_in_device_frame_and_newtons(fake_hd):
    path, fake = fake_hd
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    Rz90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    set_pose(fake, Rz90, [10.0, 20.0, -30.0])
    fake.fake_set_velocity(100.0, 0.0, -50.0)
    fake.fake_set_buttons(2)
    fake.fake_tick(1)
    s = dev.read()
    assert s.position == pytest.approx((0.010, 0.020, -0.030))
    assert s.velocity == pytest.approx((0.1, 0.0, -0.05))
    assert s.quaternion == pytest.approx((0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)))
    assert s.buttons == 2
    dev.command_force((1.0, -2.0, 0.5))
    assert forces(fake) == [0.0, 0.0, 0.0]  # written by the next servo tick, not by the caller
    fake.fake_tick(1)
    assert forces(fake) == [1.0, -2.0, 0.5]
    assert fake.fake_counter(FRAME_VIOL) == 0
    dev.close()
    assert forces(fake) == [0.0, 0.0, 0.0] or fake.fake_counter(STATE) == 0


def test_force_is_clamped_at_the_device_limit_and_never_nan(fake_hd):
    path, fake = fake_hd
    fake.fake_set_nominal_max_force(3.3)  # the device says less than the spec's 7.9 N
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    assert dev.force_limit_n == pytest.approx(3.3)
    rng = np.random.default_rng(3)
    for _ in range(200):
        f = rng.normal(0.0, 20.0, 3)
        if rng.random() < 0.1:
            f[rng.integers(3)] = rng.choice([math.nan, math.inf, -math.inf])
        dev.command_force(tuple(f))
        fake.fake_tick(1)
        out = forces(fake)
        assert all(math.isfinite(x) for x in out)
        if all(math.isfinite(x) for x in f) and np.linalg.norm(f) > 3.3:  # direction kept
            assert np.allclose(np.array(out) / np.linalg.norm(out), f / np.linalg.norm(f))
    assert math.sqrt(fake.fake_max_force_seen()) == pytest.approx(3.3)
    dev.close()


def test_ellipsoid_force_arrives_in_the_device_frame(fake_hd):
    """The servo's force renderer on the stylus read through libHD: pushing down into a plane-
    like patient under the stylus gives an upward (+y device) force at the fake device."""
    path, fake = fake_hd
    cfg = ServoConfig()
    r = ForceRenderer(cfg)
    r.set_model(demo_model(), 0.0)  # automatic registration: origin 30 mm above the xiphoid
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    set_pose(fake, np.eye(3), [0.0, -35.0, 0.0])  # 5 mm into the top of the patient
    t = 0.0
    for _ in range(600):  # past the start ramp
        fake.fake_tick(1)
        t += 1e-3
        dev.command_force(r.tick(dev.read(), t))
    fake.fake_tick(1)
    f = forces(fake)
    assert f[1] > 1.0 and abs(f[0]) < 0.2 * f[1] and abs(f[2]) < 0.2 * f[1]
    assert math.sqrt(sum(x * x for x in f)) <= dev.force_limit_n + 1e-9
    dev.close()


def pos_mm(dev):
    return np.array(dev.read().position) * 1e3


def ramp_up(fake, ticks):
    """The force magnitude (N) written by each of ``ticks`` ticks."""
    out = []
    for _ in range(ticks):
        fake.fake_tick(1)
        out.append(float(np.linalg.norm(forces(fake))))
    return np.array(out)


def test_auto_calibration_is_preferred_and_takes_time_then_force_ramps_back(fake_hd, caplog):
    """A device supporting encoder reset and auto calibration is updated with AUTO (OpenHaptics'
    Calibration example), never with an encoder reset by itself; the update takes time, the
    position jumps when it completes, and the force ramps back instead of stepping to full."""
    path, fake = fake_hd
    fake.fake_set_calibration(NEEDS_UPDATE, ENCODER_RESET | AUTO)
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    assert dev.calibration_style == AUTO
    with caplog.at_level(logging.WARNING):
        dev.command_force((1.0, 0.0, 0.0))
        fake.fake_tick(1)
        assert dev.calibration == "needs_update" and forces(fake) == [0.0, 0.0, 0.0]
        assert fake.fake_counter(UPD_STYLE) == AUTO  # hdUpdateCalibration(HD_CALIBRATION_AUTO)
        before = pos_mm(dev)
        fake.fake_tick(30)
        assert dev.calibration == "needs_update" and forces(fake) == [0.0, 0.0, 0.0]
        fake.fake_tick(30)
    assert dev.calibration == "ok"
    assert np.linalg.norm(pos_mm(dev) - before) > 5.0  # the position jumped
    assert "force off" in caplog.text and "ramps back" in caplog.text
    f = ramp_up(fake, 1100)
    assert 0.0 < f[0] < 0.05  # no full-force step on the first calibrated tick
    assert np.all(np.diff(f) >= -1e-12) and np.all(np.diff(f) <= 1.0 / 900)
    assert f[-1] == pytest.approx(1.0)
    assert fake.fake_counter(ENC_RESET_RUNNING) == 0
    assert fake.fake_counter(UPDATES) < 10  # not every tick: at most every 0.1 s
    dev.close()


def test_inkwell_calibration_asks_for_the_inkwell_then_updates_it(fake_hd, caplog):
    """A Touch X/Omni-style device: manual input (the inkwell) first; once the stylus is in
    it, hdUpdateCalibration(HD_CALIBRATION_INKWELL), never an encoder reset wherever the arm
    is; the force ramps back when calibration is ok."""
    path, fake = fake_hd
    fake.fake_set_calibration(NEEDS_MANUAL, INKWELL | ENCODER_RESET)
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    assert dev.calibration_style == INKWELL
    with caplog.at_level(logging.WARNING):
        dev.command_force((0.0, 1.0, 0.0))
        fake.fake_tick(300)
        dev.read()  # the pose is still readable; the servo thread's messages are logged
    assert dev.calibration == "needs_manual_input" and forces(fake) == [0.0, 0.0, 0.0]
    assert "put the stylus in the inkwell" in caplog.text
    assert fake.fake_counter(UPDATES) == 0  # nothing to update without the inkwell
    fake.fake_set_inkwell(1)  # the user docks the stylus
    fake.fake_tick(2)
    assert dev.calibration == "needs_update" and fake.fake_counter(UPD_STYLE) == INKWELL
    fake.fake_tick(60)
    assert dev.calibration == "ok"
    assert [fake.fake_offset(i) for i in range(3)] == [0.0, 0.0, 0.0]  # true pose
    assert fake.fake_counter(ENC_RESET_RUNNING) == 0
    f = ramp_up(fake, 1100)
    assert f[0] < 0.05 and f[-1] == pytest.approx(1.0) and np.all(np.diff(f) >= -1e-12)
    dev.close()


def test_encoder_reset_devices_wait_for_the_prompted_reset(fake_hd, caplog):
    """A device with only an encoder reset: the servo never resets it (force stays off and the
    log says how); reset_encoders asks the user first and resets before the scheduler runs."""
    path, fake = fake_hd
    fake.fake_set_calibration(NEEDS_UPDATE, ENCODER_RESET)
    cfg = TouchXConfig(library=path)
    dev = TouchX(cfg)
    dev.open()
    with caplog.at_level(logging.WARNING):
        dev.command_force((0.0, 1.0, 0.0))
        fake.fake_tick(500)
        dev.read()
    assert dev.calibration == "needs_update" and forces(fake) == [0.0, 0.0, 0.0]
    assert fake.fake_counter(UPDATES) == 0 and "touchx_reset" in caplog.text
    dev.close()
    asked = []
    with pytest.raises(DeviceError, match="cancelled"):
        reset_encoders(cfg, lambda prompt: asked.append(prompt) or False)
    assert "reset pose" in asked[0] and fake.fake_counter(UPDATES) == 0
    fake.fake_set_at_reset_pose(1)
    assert "calibration ok" in reset_encoders(cfg, lambda prompt: True)
    assert fake.fake_counter(UPD_STYLE) == ENCODER_RESET
    assert fake.fake_counter(ENC_RESET_RUNNING) == 0  # before the scheduler, as the example
    assert [fake.fake_offset(i) for i in range(3)] == [0.0, 0.0, 0.0]
    fake.fake_set_calibration(NEEDS_MANUAL, INKWELL)
    with pytest.raises(DeviceError, match="no encoder reset.*inkwell"):
        reset_encoders(cfg, lambda prompt: True)


def test_reset_encoders_command_line(fake_hd, monkeypatch, capsys):
    path, fake = fake_hd
    fake.fake_set_calibration(NEEDS_UPDATE, ENCODER_RESET)
    fake.fake_set_at_reset_pose(1)
    monkeypatch.setattr("builtins.input", lambda prompt: "y")
    assert touchx_main(["--library", path]) == 0
    assert "encoders reset; calibration ok" in capsys.readouterr().out
    monkeypatch.setattr("builtins.input", lambda prompt: "")
    assert touchx_main(["--library", path]) == 1


@pytest.mark.parametrize(
    ("code", "words"),
    [
        (0x0201, "HD_EXCEEDED_MAX_FORCE"),
        (0x0300, "HD_DEVICE_FAULT.*power-cycle"),
    ],
)
def test_hd_errors_become_clear_device_errors_and_zero_the_force(fake_hd, code, words):
    """Errors that are not scheduler errors (hduIsSchedulerError): reported once, force
    dropped, the callback goes on (scheduler errors: the test after this one)."""
    path, fake = fake_hd
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    fake.fake_fail_at_tick(3, code)
    dev.command_force((0.0, 0.0, 1.5))
    fake.fake_tick(3)
    assert forces(fake) == [0.0, 0.0, 1.5]
    fake.fake_tick(1)  # the error is raised inside this tick
    with pytest.raises(DeviceError, match=words):
        dev.read()
    assert dev.errors == 1
    fake.fake_tick(1)
    assert forces(fake) == [0.0, 0.0, 0.0]  # dropped until the loop commands again
    dev.read()  # reported once; the device keeps running
    dev.command_force((0.0, 0.0, 1.0))
    fake.fake_tick(1)
    assert forces(fake) == [0.0, 0.0, 1.0]
    dev.close()


class Clock:
    """A clock the test moves (s)."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.mark.parametrize(
    ("code", "words"),
    [(0x0302, "HD_COMM_ERROR.*USB cable"), (0x0304, "HD_TIMER_ERROR.*time slice")],
)
def test_a_scheduler_error_stops_the_callback_and_the_device_is_reinitialised(
    fake_hd, code, words, caplog
):
    """A scheduler error (HD_COMM_ERROR, HD_TIMER_ERROR: OpenHaptics' hduIsSchedulerError):
    that tick writes zero force and the callback stops (HD_CALLBACK_DONE, as
    HelloHapticDevice.c); the loop's next read releases the device and says it is lost; after
    the back-off it is initialised again and the force ramps back."""
    path, fake = fake_hd
    clock = Clock()
    dev = TouchX(TouchXConfig(library=path, reopen_first_s=0.5, ramp_s=0.005))
    dev._clock = clock
    dev.open()
    dev.command_force((0.0, 0.0, 1.5))
    fake.fake_tick(3)
    assert forces(fake) == [0.0, 0.0, 1.5]
    fake.fake_fail_at_tick(3, code)
    fake.fake_tick(1)
    assert forces(fake) == [0.0, 0.0, 0.0]  # the tick that saw it wrote zero
    assert fake.fake_counter(CALLBACKS) == 0  # and stopped the callback
    with caplog.at_level(logging.WARNING):
        with pytest.raises(DeviceError, match=words + ".*re-initialising: attempt 0, next in 0.5"):
            dev.read()
        assert fake.fake_counter(STATE) == 0  # released: scheduler stopped, device disabled
        assert dev.lost is not None
        with pytest.raises(DeviceError, match="lost"):
            dev.command_force((0.0, 0.0, 1.0))
        assert dev.wait_tick(dev.ticks, 0.01) == dev.ticks  # waits, never spins the loop
        clock.t += 0.4
        with pytest.raises(DeviceError, match="next in 0.1"):
            dev.read()  # not yet
        assert fake.fake_counter(INITS) == 1
        clock.t += 0.1
        reopen = dev.open

        def open_and_tick():  # the new scheduler ticks before the loop hears it is back
            reopen()
            fake.fake_tick(1)

        dev.open = open_and_tick
        dev.read()  # re-initialised; that tick's state
        dev.open = reopen
    assert fake.fake_counter(INITS) == 2 and fake.fake_counter(STATE) == 111
    assert dev.lost is None and dev.reinits == 1 and fake.fake_counter(CALLBACKS) == 1
    assert "device lost" in caplog.text and "re-initialised" in caplog.text
    dev.command_force((0.0, 0.0, 1.5))
    f = ramp_up(fake, 10)
    assert f[0] < 0.75 and f[-1] == pytest.approx(1.5)  # ramps back over ramp_s (5 ticks)
    assert np.all(np.diff(f) >= -1e-12)
    dev.read()
    dev.close()


def test_an_unplugged_device_is_reinitialised_with_backoff_once_replugged(fake_hd, caplog):
    """Unplugged: every tick raises HD_COMM_ERROR and hdInitDevice fails while it is out; the
    backend waits 0.5, 1, 2, 2 s between attempts (reopen_max_s 2), and the replugged device,
    which only a new hdInitDevice brings back, is re-initialised at the next attempt."""
    path, fake = fake_hd
    clock = Clock()
    dev = TouchX(TouchXConfig(library=path, reopen_first_s=0.5, reopen_max_s=2.0))
    dev._clock = clock
    dev.open()
    dev.command_force((0.0, 1.0, 0.0))
    fake.fake_tick(2)
    fake.fake_unplug()
    fake.fake_tick(1)
    assert forces(fake) == [0.0, 0.0, 0.0] and fake.fake_counter(CALLBACKS) == 0
    fake.fake_tick(5)  # the scheduler ticks on until released: its errors pile up unread
    with caplog.at_level(logging.WARNING):
        with pytest.raises(DeviceError, match="HD_COMM_ERROR.*next in 0.5"):
            dev.read()
        for wait, attempt, next_s in ((0.5, 1, 1.0), (1.0, 2, 2.0), (2.0, 3, 2.0)):
            clock.t += wait
            with pytest.raises(DeviceError, match=f"attempt {attempt}, next in {next_s}"):
                dev.read()
        assert "re-initialising failed (attempt 1)" in caplog.text
        fake.fake_replug()
        clock.t += 1.0
        with pytest.raises(DeviceError, match="attempt 3, next in 1.0"):
            dev.read()  # back-off not over: no attempt
        clock.t += 1.0
        with pytest.raises(DeviceError, match="no servo tick yet"):
            dev.read()
    assert dev.reinits == 1 and dev.lost is None and fake.fake_counter(INITS) == 2
    fake.fake_tick(1)
    dev.read()
    fake.fake_unplug()  # and again: lost again, found again
    fake.fake_tick(1)
    with pytest.raises(DeviceError, match="lost"):
        dev.read()
    fake.fake_replug()
    clock.t += 0.5  # the back-off starts over at reopen_first_s
    with pytest.raises(DeviceError, match="no servo tick yet"):
        dev.read()
    assert dev.reinits == 2
    dev.close()
    assert dev.lost is None and fake.fake_counter(STATE) == 0


@pytest.mark.parametrize(
    ("code", "words"),
    [(0x0301, "another program holds the device"), (0x0600, "license"),
     (0x0303, "Touch_Setup")],
)  # fmt: skip
def test_init_failures_say_what_to_do(fake_hd, code, words):
    path, fake = fake_hd
    fake.fake_fail_init(code)
    dev = TouchX(TouchXConfig(library=path, device_name="Left Touch"))
    with pytest.raises(DeviceError, match=words) as exc:
        dev.open()
    assert "'Left Touch'" in str(exc.value)
    with pytest.raises(DeviceError, match="not open"):
        dev.read()


def test_describe_unknown_error():
    assert "0x0abc" in describe_hd_error(0x0ABC, 5) and "internal 5" in describe_hd_error(0xABC, 5)


def test_missing_library_and_wrong_library_are_clear(tmp_path):
    with pytest.raises(DeviceError, match="OpenHaptics HD library"):
        TouchX(TouchXConfig(library=str(tmp_path / "nope.so"))).open()
    libc = ctypes.util.find_library("c")
    if libc:
        with pytest.raises(DeviceError, match="lacks hdInitDevice"):
            TouchX(TouchXConfig(library=libc)).open()


def test_a_missing_dependency_of_libhd_is_named_not_libhd(fake_hd_missing_phantomio):
    """libHD is there but the Touch driver's libPhantomIOLib42.so it links against is not: the
    message names that library and the driver, not "libHD.so is not installed"."""
    with pytest.raises(DeviceError) as exc:
        TouchX(TouchXConfig(library=fake_hd_missing_phantomio)).open()
    msg = str(exc.value)
    assert "needs is missing: libPhantomIOLib42.so" in msg and "Touch device driver" in msg
    assert "not installed or not found" not in msg


def test_gtdd_home_unset_or_unconfigured_is_named(fake_hd, monkeypatch, tmp_path, capfd):
    path, fake = fake_hd
    monkeypatch.delenv("GTDD_HOME")
    with pytest.raises(DeviceError, match=r"HD_COMM_ERROR.*GTDD_HOME is not set.*Touch_Setup"):
        TouchX(TouchXConfig(library=path)).open()
    assert "Config directory not set correctly" in capfd.readouterr().err  # the driver's own
    fake.fake_require_gtdd_home(0)
    fake.fake_fail_init(0x0302)
    monkeypatch.setenv("GTDD_HOME", str(tmp_path / "nowhere"))
    with pytest.raises(DeviceError, match=r"nowhere/config does not exist: run Touch_Setup"):
        TouchX(TouchXConfig(library=path)).open()


def test_real_scheduler_thread_runs_the_callback_and_io_stays_in_it(fake_hd):
    """With the fake's own servo thread (as OpenHaptics): ticks arrive without the caller's help,
    every HD frame and force write happens in that thread, and close stops it."""
    path, fake = fake_hd
    fake.fake_reset(0)  # threaded scheduler (the fixture turned the watchdog off)
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    deadline = time.monotonic() + 30.0
    while dev.ticks < 200 and time.monotonic() < deadline:
        dev.command_force((0.5, 0.0, 0.0))
        time.sleep(0.005)
    assert dev.ticks >= 200, "the fake HD servo thread did not tick"
    dev.read()
    dev.close()
    n = fake.fake_counter(TICKS)
    time.sleep(0.05)
    assert fake.fake_counter(TICKS) == n  # stopped
    assert fake.fake_counter(THREAD_VIOL) == 0 and fake.fake_counter(FRAME_VIOL) == 0
    assert fake.fake_counter(FRAMES) == n == dev.ticks
    assert fake.fake_counter(RATE) == 1000
    t = dev.timing.summary()  # the callback's own period and duration were measured
    assert t["callbacks"] == n and t["period_p50_us"] > 0 and t["duration_p50_us"] > 0


def _fifo_allowed() -> bool:
    """Whether this machine lets a thread take SCHED_FIFO (tried in a throwaway thread)."""
    ok = []

    def attempt():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except OSError:
            return
        ok.append(True)

    t = threading.Thread(target=attempt)
    t.start()
    t.join(30.0)
    return bool(ok)


def _open_from_fifo_thread(dev, prio):
    """``dev.open()`` called from a thread at SCHED_FIFO ``prio`` where allowed (as the servo
    process's main thread is when it opens the device)."""
    errors = []

    def run():
        try:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
            except OSError:
                pass
            dev.open()
        except BaseException as exc:  # noqa: BLE001 - re-raised below
            errors.append(exc)

    t = threading.Thread(target=run)
    t.start()
    t.join(30.0)
    if errors:
        raise errors[0]


def _wait_ticks(dev, n):
    deadline = time.monotonic() + 30.0
    while dev.ticks < n and time.monotonic() < deadline:
        time.sleep(0.005)
    assert dev.ticks >= n, "the fake HD servo thread did not tick"


def test_hd_servo_thread_starts_normal_and_its_callback_makes_it_fifo(fake_hd):
    """The fake's scheduler thread starts at normal priority even when the thread that starts
    it is SCHED_FIFO (as OpenHaptics' may: the driver makes it); the backend's first callback
    gives it SCHED_FIFO at ``thread_priority``, read back from the thread itself. Where the
    machine refuses SCHED_FIFO the thread stays normal and the backend says so."""
    path, fake = fake_hd
    fifo = _fifo_allowed()
    fake.fake_reset(0)  # threaded scheduler
    dev = TouchX(TouchXConfig(library=path))  # thread_priority 0: the thread is left alone
    _open_from_fifo_thread(dev, 3)
    _wait_ticks(dev, 5)
    assert fake.fake_thread_policy() == 0  # SCHED_OTHER: not inherited from the FIFO opener
    assert dev.thread_fifo == 0 and dev.thread_policy == "normal priority"
    dev.close()
    assert fake.fake_thread_policy() == -1

    fake.fake_reset(0)
    dev = TouchX(TouchXConfig(library=path))
    dev.thread_priority = 7
    _open_from_fifo_thread(dev, 3)
    _wait_ticks(dev, 5)
    if fifo:
        assert fake.fake_thread_policy() == 1007  # SCHED_FIFO 7, asked from inside the thread
        assert dev.thread_fifo == 7 and dev.thread_policy == "SCHED_FIFO 7"
    else:
        assert fake.fake_thread_policy() == 0
        assert dev.thread_fifo == 0 and "SCHED_FIFO 7 refused" in dev.thread_policy
    dev.close()


def test_continuous_force_is_queried_and_sustained_force_settles_at_it(fake_hd):
    """A brief peak passes; a sustained press is brought down to the device's continuous rating
    (queried: HD_NOMINAL_MAX_CONTINUOUS_FORCE) smoothly, so the motors never warm up."""
    path, fake = fake_hd
    fake.fake_set_nominal_continuous_force(1.5)
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    assert dev.continuous_force_n == pytest.approx(1.5) and dev.force_limit_n == pytest.approx(7.9)
    dev.command_force((0.0, 6.0, 0.0))
    fake.fake_tick(2)
    assert forces(fake)[1] == pytest.approx(6.0)  # a peak, from cold, is allowed
    dev.command_force((0.0, 3.0, 0.0))
    f = ramp_up(fake, 12000)  # 12 s pressing at 3 N
    assert f[0] == pytest.approx(3.0, rel=1e-3)
    assert np.all(np.abs(np.diff(f)) < 0.01)  # no step
    assert f[-1] <= 1.5 + 1e-6 and f[-1] > 1.45
    assert fake.fake_counter(WARM_EVENTS) == 0 and fake.fake_temperature() < 0.7
    assert fake.fake_counter(EXCEEDED) == 0
    dev.command_force((0.0, 0.0, 0.0))
    fake.fake_tick(8000)  # rested: the peak is available again
    dev.command_force((0.0, 6.0, 0.0))
    fake.fake_tick(2)
    assert forces(fake)[1] > 5.5
    dev.close()


def test_motor_temperature_limits_force_toward_continuous_as_prevent_warm_motors(fake_hd):
    """The device's own motor model (HD_MOTOR_TEMPERATURE) above 0.7: the limit decays by 0.1 %
    a tick toward the continuous rating (OpenHaptics' PreventWarmMotors); below 0.5 it
    recovers."""
    path, fake = fake_hd
    fake.fake_set_thermal(1e9, 0.8)  # warm, and held there
    dev = TouchX(TouchXConfig(library=path, thermal_time_constant_s=600.0))
    dev.open()
    dev.command_force((0.0, 3.0, 0.0))
    f = ramp_up(fake, 3000)
    assert dev.temperature == pytest.approx(0.8)
    assert f[0] == pytest.approx(3.0, rel=2e-3) and f[-1] == pytest.approx(1.75, abs=1e-6)
    assert np.all(np.diff(f) <= 1e-12) and np.all(np.diff(f) > -0.01)
    fake.fake_set_thermal(1e9, 0.4)
    f = ramp_up(fake, 2000)
    assert np.all(np.diff(f) >= -1e-12) and f[-1] == pytest.approx(3.0)
    assert fake.fake_counter(WARM_EVENTS) == 0
    dev.close()


def test_warm_motors_ramp_the_force_down_and_back_not_a_drop_to_zero(fake_hd, caplog):
    """HD_WARM_MOTORS mid-contact: no fault and no step; the force ramps to zero, stays off
    until the motors cool, then ramps back; the log says so."""
    path, fake = fake_hd
    dev = TouchX(TouchXConfig(library=path, warm_ramp_s=0.5, ramp_s=0.5))
    dev.open()
    dev.command_force((0.0, 1.5, 0.0))
    fake.fake_tick(5)
    assert forces(fake)[1] == pytest.approx(1.5)
    with caplog.at_level(logging.WARNING):
        fake.fake_set_thermal(1e9, 1.05)  # the device's model says: overheating
        f = ramp_up(fake, 3000)
        assert dev.warm_motors and fake.fake_counter(WARM_EVENTS) == 1
        dev.read()  # not an error: the loop keeps running
        assert f[0] > 1.49 and np.all(np.diff(f) <= 1e-12)
        assert np.all(np.diff(f) > -1.5 / 500 - 1e-9)  # at most the ramp's step per tick
        assert f[-1] == 0.0 and f[700] == 0.0
        fake.fake_set_thermal(1e9, 0.3)  # cooled
        f = ramp_up(fake, 2000)
        dev.read()
    assert not dev.warm_motors
    assert f[0] == 0.0 and f[-1] == pytest.approx(1.5) and np.all(np.diff(f) >= -1e-12)
    assert "HD_WARM_MOTORS" in caplog.text and "cooled" in caplog.text
    dev.close()


def test_a_callback_that_runs_long_trips_the_scheduler_watchdog(fake_hd):
    """The real servo loop cuts the force when its time slice is missed: the fake's watchdog
    faults a tick whose callback runs over its limit (HD_TIMER_ERROR); the backend reports it and
    keeps the force zero until the loop commands again."""
    path, fake = fake_hd
    fake.fake_set_watchdog_us(20_000)  # 20 ms here: a busy test machine stalls for less
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    dev.command_force((0.0, 1.0, 0.0))
    fake.fake_tick(3)
    assert fake.fake_counter(WATCHDOG) == 0 and forces(fake)[1] == pytest.approx(1.0)
    slow = dev._make_state

    def late(t):
        time.sleep(0.04)
        return slow(t)

    dev._make_state = late
    fake.fake_tick(1)
    dev._make_state = slow
    assert fake.fake_counter(WATCHDOG) == 1 and forces(fake) == [0.0, 0.0, 0.0]
    fake.fake_tick(1)
    with pytest.raises(DeviceError, match="HD_TIMER_ERROR"):
        dev.read()
    assert forces(fake) == [0.0, 0.0, 0.0]
    assert dev.timing.max_duration_us > 40_000  # hdGetSchedulerTimeStamp saw it
    dev.close()


def test_wait_tick_blocks_until_the_next_device_tick(fake_hd):
    path, fake = fake_hd
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    fake.fake_tick(2)
    assert dev.wait_tick(0, 5.0) == 2  # already newer: at once
    assert dev.wait_tick(2, 0.01) == 2  # none: after the timeout
    got = []
    t = threading.Thread(target=lambda: got.append(dev.wait_tick(2, 30.0)))
    t.start()
    time.sleep(0.01)
    fake.fake_tick(1)
    t.join(30.0)
    assert got == [3]
    dev.close()


def test_servo_loop_follows_the_device_ticks_and_never_spins(fake_hd, monkeypatch):
    """The servo process's loop with a Touch X waits in wait_tick (GIL free) for each device
    tick instead of sleeping and spinning on its own clock (which holds the GIL the device's
    callback needs): each sample is the newest device tick's pose."""
    from humantele.haptics import servo_child
    from humantele.haptics.servo_layout import CMD_LEN, S_PD, S_TICK, SAMPLE_LEN, STATS_LEN
    from humantele.haptics.shm import SeqlockArray

    path, fake = fake_hd

    def no_sleep(s):
        raise AssertionError("the device-driven loop slept on its own clock")

    monkeypatch.setattr(servo_child, "time", SimpleNamespace(monotonic=time.monotonic,
                                                             sleep=no_sleep))  # fmt: skip
    cfg = ServoConfig(device=TouchXConfig(library=path), realtime_priority=0,
                      stale_after_s=1.0)  # fmt: skip
    dev = TouchX(cfg.device)
    dev.open()
    blocks = [SeqlockArray(CMD_LEN), SeqlockArray(SAMPLE_LEN), SeqlockArray(STATS_LEN)]
    cmd, out, st = blocks
    stop = {"flag": False}
    errors = []

    def run():
        try:
            servo_child._run(cfg, dev, cmd, out, st, stop, servo_child.os.getppid(), False)
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    loop = threading.Thread(target=run)
    loop.start()
    try:
        for k in range(1, 21):
            set_pose(fake, np.eye(3), [float(k), 0.0, 0.0])
            fake.fake_tick(1)
            deadline = time.monotonic() + 30.0
            while time.monotonic() < deadline and not errors:
                a = out.read()
                if a[S_TICK] >= k and a[S_PD] == pytest.approx(k * 1e-3):
                    break
                time.sleep(0.0005)
            assert not errors, errors
            assert a[S_PD] == pytest.approx(k * 1e-3), (k, a[S_PD])
    finally:
        stop["flag"] = True
        fake.fake_tick(1)
        loop.join(30.0)
        dev.close()
        for b in blocks:
            b.close()
            b.unlink()
    assert not errors and not loop.is_alive()


@pytest.mark.e2e  # starts the servo process (the fast lane leaves it out)
def test_servo_process_runs_on_the_touchx_backend(fake_hd_path, tmp_path, monkeypatch):
    """The whole servo process on the fake libHD in its own 1 kHz thread: the loop follows the
    device's ticks, publishes the stylus pose and stops with the device released."""
    from humantele.haptics.servo import ServoProcess

    (tmp_path / "3DSystems" / "config").mkdir(parents=True)
    monkeypatch.setenv("GTDD_HOME", str(tmp_path / "3DSystems"))
    monkeypatch.setenv("FAKE_HD_WATCHDOG_US", "0")  # a busy test machine's stall is no defect
    # SCHED_FIFO 1 where allowed: the device's HD servo thread must end up there too
    cfg = ServoConfig(device=TouchXConfig(library=fake_hd_path), realtime_priority=1)
    fifo = _fifo_allowed()
    with ServoProcess(cfg) as sp:
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            s = sp.latest()
            if s is not None and s.tick > 300:
                break
            time.sleep(0.01)
        assert s is not None and s.tick > 300
        assert np.allclose(s.T_device_stylus.position, 0.0)  # the fake's stylus at the origin
        deadline = time.monotonic() + 30.0  # the statistics are written 4 times a second
        while sp.stats().ticks < 300 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert sp.realtime == fifo
        assert sp.stats().device_thread_fifo == (1 if fifo else 0)
    assert sp.returncode == 0 and sp.stats().ticks > 300  # the final statistics


@pytest.mark.e2e  # starts the servo process (the fast lane leaves it out)
def test_the_servo_says_the_device_is_lost_and_runs_again_after_a_replug(
    fake_hd_path, tmp_path, monkeypatch
):
    """The whole servo process on the fake libHD, unplugged and replugged from this process
    (the fake watches a file): the servo's state says the device is lost and being
    re-initialised, no force reaches it, and once replugged it is initialised again in the same
    process (no restart) and runs."""
    from humantele.haptics.supervisor import SupervisedServo

    (tmp_path / "3DSystems" / "config").mkdir(parents=True)
    monkeypatch.setenv("GTDD_HOME", str(tmp_path / "3DSystems"))
    monkeypatch.setenv("FAKE_HD_WATCHDOG_US", "0")
    unplugged = tmp_path / "unplugged"
    monkeypatch.setenv("FAKE_HD_UNPLUG_FILE", str(unplugged))
    device = TouchXConfig(library=fake_hd_path, reopen_first_s=0.05, reopen_max_s=0.2)
    # stale only after 0.5 s: a busy test machine's late tick is no fault here
    sup = SupervisedServo(ServoConfig(device=device, realtime_priority=0, stale_after_s=0.5))
    sup.start()
    try:
        wait_for(lambda: (x := sup.latest()) and x.tick > 100, 30.0)
        assert "device" not in sup.state(sup.latest()) and sup.stats().device_lost == 0
        unplugged.touch()
        state = wait_for(lambda: "device lost" in (st := sup.state(sup.latest())) and st, 30.0)
        assert state.startswith("fault: ") and "re-initialising" in state
        assert sup.latest().force_device == (0.0, 0.0, 0.0)
        assert wait_for(lambda: sup.stats().device_lost == 1, 30.0)
        unplugged.unlink()
        wait_for(lambda: (st := sup.stats()).device_reinits >= 1 and not st.device_lost, 30.0)
        # running again: the device ticks (no stale fault) and the callback was not stopped by
        # the error of the session before
        wait_for(lambda: (x := sup.latest()) and sup.state(x) == "running", 30.0)
        assert sup.alive and sup.restarts == 0  # the same process, never restarted
    finally:
        sup.stop_now()


def test_a_failing_tick_closes_its_frame_with_zero_force(fake_hd):
    path, fake = fake_hd
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    dev.command_force((0.0, 1.0, 0.0))
    fake.fake_tick(2)
    assert forces(fake)[1] == pytest.approx(1.0)
    good = dev._limited

    def broken(*args):
        raise ValueError("boom")

    dev._limited = broken
    fake.fake_tick(1)
    dev._limited = good
    assert forces(fake) == [0.0, 0.0, 0.0] and fake.fake_counter(FRAMES) == 3
    with pytest.raises(DeviceError, match="servo callback failed.*boom"):
        dev.read()
    fake.fake_tick(1)  # the next frame opens cleanly (no HD_ILLEGAL_BEGIN)
    dev.read()
    dev.close()

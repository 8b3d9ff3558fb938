"""The touchx backend run on a fake OpenHaptics libHD (tests/devices/fake_libhd.c).

The fake exports the HD functions the backend binds, with the same signatures, and runs the
scheduled callbacks either in its own 1 kHz thread (as the real servo thread) or tick by tick
from the test (``fake_tick``), so these tests do not depend on the machine's speed.
"""

import ctypes
import logging
import math
import time

import numpy as np
import pytest

from humantele.haptics.demo_patient import demo_model
from humantele.haptics.devices import DeviceError, TouchX, TouchXConfig
from humantele.haptics.devices.touchx import describe_hd_error
from humantele.haptics.renderer import ForceRenderer
from humantele.haptics.servo_config import ServoConfig

TICKS, FRAMES, WRITES, FRAME_VIOL, THREAD_VIOL, RATE, PRIO, STATE, UPD_STYLE, CAL = range(10)


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


def test_calibration_needs_update_is_fixed_with_a_supported_style(fake_hd, caplog):
    path, fake = fake_hd
    fake.fake_set_calibration(0x5001, 1 << 1)  # needs update; auto supported
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    with caplog.at_level(logging.WARNING):
        dev.command_force((1.0, 0.0, 0.0))
        fake.fake_tick(1)
    assert dev.calibration == "needs_update" and forces(fake) == [0.0, 0.0, 0.0]
    assert fake.fake_counter(UPD_STYLE) == 1 << 1  # hdUpdateCalibration(HD_CALIBRATION_AUTO)
    fake.fake_tick(1)
    assert dev.calibration == "ok" and forces(fake) == [1.0, 0.0, 0.0]
    assert "force off" in caplog.text
    dev.close()


def test_inkwell_calibration_keeps_force_off_until_the_stylus_is_docked(fake_hd, caplog):
    path, fake = fake_hd
    fake.fake_set_calibration(0x5002, 1 << 2)  # needs manual input; inkwell only
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    with caplog.at_level(logging.WARNING):
        dev.command_force((0.0, 2.0, 0.0))
        fake.fake_tick(50)
    assert dev.calibration == "needs_manual_input" and forces(fake) == [0.0, 0.0, 0.0]
    assert "inkwell" in caplog.text
    assert fake.fake_counter(UPD_STYLE) == 0  # no update attempted without the inkwell
    dev.read()  # the pose is still readable
    fake.fake_set_calibration(0x5000, 1 << 2)  # stylus put in the inkwell
    fake.fake_tick(1)
    assert dev.calibration == "ok" and forces(fake) == [0.0, 2.0, 0.0]
    dev.close()


@pytest.mark.parametrize(
    ("code", "words"),
    [
        (0x0302, "HD_COMM_ERROR.*USB cable"),
        (0x0200, "HD_WARM_MOTORS.*cool"),
        (0x0201, "HD_EXCEEDED_MAX_FORCE"),
        (0x0300, "HD_DEVICE_FAULT.*power-cycle"),
    ],
)
def test_hd_errors_become_clear_device_errors_and_zero_the_force(fake_hd, code, words):
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


def test_real_scheduler_thread_runs_the_callback_and_io_stays_in_it(fake_hd):
    """With the fake's own servo thread (as OpenHaptics): ticks arrive without the caller's help,
    every HD frame and force write happens in that thread, and close stops it."""
    path, fake = fake_hd
    fake.fake_reset(0)  # threaded scheduler
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

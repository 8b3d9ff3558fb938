"""Haptic device backends: factory, the simulated Touch X's dynamics and faults, touchx errors."""

import math

import numpy as np
import pytest

from humantele.config import ConfigError
from humantele.haptics.devices import (
    DeviceError,
    ManualClock,
    SimDeviceConfig,
    SimTouchX,
    TouchX,
    TouchXConfig,
    device_config,
    make_device,
    safe_force,
)
from humantele.haptics.devices.sim import SimFault, SimHandConfig, scan_target


def _run(dev: SimTouchX, clock: ManualClock, seconds: float, force=(0.0, 0.0, 0.0), dt=1e-3):
    states = []
    for _ in range(int(round(seconds / dt))):
        clock.t += dt
        states.append(dev.read())
        dev.command_force(force)
    return states


def _sim(**hand) -> tuple[SimTouchX, ManualClock]:
    clock = ManualClock()
    cfg = SimDeviceConfig(hand=SimHandConfig(**hand)) if hand else SimDeviceConfig()
    dev = SimTouchX(cfg, clock=clock)
    dev.open()
    return dev, clock


def test_factory_unknown_backend_names_the_field_and_lists_the_choices():
    with pytest.raises(
        ConfigError, match=r"device: backend: unknown backend 'phantom'.*'sim', 'touchx', 'hid'"
    ):
        make_device({"backend": "phantom"})
    with pytest.raises(ConfigError, match="'sim', 'touchx', 'hid'"):
        device_config({"backend": 3})
    with pytest.raises(ConfigError, match=r"device: backend: missing"):
        device_config({"seed": 3})


def test_old_kind_field_is_refused_with_the_new_name():
    with pytest.raises(
        ConfigError, match=r"device: backend: .*'kind' is now called 'backend'.*'sim'"
    ):
        make_device({"kind": "sim", "seed": 3})


def test_factory_builds_each_backend_and_names_bad_fields():
    assert isinstance(make_device(None), SimTouchX)
    assert isinstance(make_device({"backend": "sim", "seed": 3}), SimTouchX)
    assert isinstance(make_device({"backend": "touchx"}), TouchX)  # not opened: no library needed
    assert make_device({"backend": "hid"}).has_force is False
    assert isinstance(make_device(TouchXConfig()), TouchX)
    with pytest.raises(ConfigError, match=r"sim_rate_hz"):
        make_device({"backend": "sim", "sim_rate_hz": 100})
    with pytest.raises(ConfigError, match=r"bogus"):
        make_device({"backend": "sim", "bogus": 1})
    with pytest.raises(TypeError, match="not a haptic device configuration"):
        make_device(42)  # type: ignore[arg-type]


def test_free_hand_follows_the_held_target():
    dev, clock = _sim(path="hold", hold_target_m=(0.02, -0.01, 0.015), tremor_n=0.0)
    states = _run(dev, clock, 1.5)
    p = np.array(states[-1].position)
    assert np.allclose(p, [0.02, -0.01, 0.015], atol=2e-4)  # friction 0.04 N / 150 N/m


def test_scan_path_is_tracked_with_hand_lag_only():
    dev, clock = _sim()
    states = _run(dev, clock, 6.0)
    errs = [
        np.linalg.norm(np.subtract(s.position, scan_target(dev.config.hand, s.t - 0.0)[0]))
        for s in states[1000:]
    ]
    assert max(errs) < 0.01  # a compliant hand lags a moving target by millimetres
    ys = [s.position[1] for s in states]
    assert min(ys) < -0.04 and max(ys) > -0.02  # it did press down and hover


def test_contact_force_acts_back_on_the_motion():
    """A constant 1.5 N upward command displaces the held stylus by F / k_hand."""
    dev, clock = _sim(path="hold", tremor_n=0.0)
    _run(dev, clock, 1.0)
    y0 = dev.true_position[1]
    _run(dev, clock, 1.5, force=(0.0, 1.5, 0.0))
    dy = dev.true_position[1] - y0
    assert dy == pytest.approx(1.5 / 150.0, rel=0.05)


def test_force_is_clamped_to_peak_and_nan_is_zeroed():
    dev, _ = _sim()
    dev.command_force((100.0, 0.0, 0.0))
    assert math.hypot(*dev.applied_force) == pytest.approx(7.9)
    dev.command_force((math.nan, 1.0, 0.0))
    assert dev.applied_force == (0.0, 0.0, 0.0)
    assert safe_force((3.0, 4.0, 0.0), 1.0) == pytest.approx((0.6, 0.8, 0.0))
    assert safe_force((math.inf, 0.0, 0.0), 5.0) == (0.0, 0.0, 0.0)


def test_readings_are_quantized_to_encoder_resolution():
    dev, clock = _sim()
    states = _run(dev, clock, 0.5)
    q = dev.spec.resolution_m
    for s in states[-10:]:
        for c in s.position:
            assert abs(c / q - round(c / q)) < 1e-6


def test_deterministic_by_seed_and_seed_matters():
    def trace(seed):
        clock = ManualClock()
        dev = SimTouchX(SimDeviceConfig(seed=seed), clock=clock)
        dev.open()
        return [s.position for s in _run(dev, clock, 0.5)]

    assert trace(1) == trace(1)
    assert trace(1) != trace(2)


def test_injected_faults():
    clock = ManualClock()
    faults = [
        SimFault(kind="stale", start_s=0.1, duration_s=0.05),
        SimFault(kind="disconnect", start_s=0.2, duration_s=0.05),
        SimFault(kind="nan", start_s=0.3, duration_s=0.05),
    ]
    dev = SimTouchX(SimDeviceConfig(faults=faults), clock=clock)
    dev.open()
    _run(dev, clock, 0.11)
    t_stale = dev.read().t
    clock.t += 0.02
    assert dev.read().t == t_stale  # same sample again: stale
    clock.t = 0.21
    with pytest.raises(DeviceError, match="disconnected"):
        dev.read()
    clock.t = 0.31
    assert all(math.isnan(c) for c in dev.read().position)
    assert not dev.read().is_finite()
    clock.t = 0.4
    s = dev.read()
    assert s.is_finite() and s.t == pytest.approx(0.4, abs=1e-3)


def test_touchx_without_library_says_how_to_fix(tmp_path):
    dev = TouchX(TouchXConfig(library=str(tmp_path / "libHD.so")))
    with pytest.raises(DeviceError, match=r"libHD\.so.*(not installed|not found).*OpenHaptics"):
        dev.open()
    dev.close()  # closing an unopened device is harmless
    with pytest.raises(DeviceError, match="not open"):
        dev.read()

"""Stability: the passivity check on the gains, and the sim showing what it predicts."""

import numpy as np
import pytest

from humantele.config import ConfigError, validate_config
from humantele.haptics.demo_patient import demo_model
from humantele.haptics.devices import SimDeviceConfig
from humantele.haptics.devices.sim import SimHandConfig
from humantele.haptics.renderer import run_lockstep
from humantele.haptics.servo_config import ServoConfig
from humantele.haptics.stability import DEFAULT_MIN_MARGIN, check_passivity

PRESS_N = 2.0
K_HAND = 150.0


def pressing(kp: float, kd: float, allow: bool = False) -> ServoConfig:
    """A light grip (hand damping 0.2 N s/m) whose target makes it press PRESS_N at rest."""
    depth = PRESS_N / kp
    target = (0.0, -0.03 - depth - PRESS_N / K_HAND, 0.0)  # surface 30 mm below the origin
    hand = SimHandConfig(path="hold", hold_target_m=target, stiffness_n_per_m=K_HAND)
    dev = SimDeviceConfig(hand=hand, start_position_m=(0.0, -0.02, 0.0))
    return ServoConfig(kp=kp, kd=kd, device=dev, allow_unstable_gains=allow)


def test_colgate_and_abbott_okamura_bounds():
    ok = check_passivity(300, 0.1, 1e-3, 0.5)
    assert ok.passive and ok.margin == pytest.approx(0.5 / (0.15 + 0.1))
    assert ok.kp_max == pytest.approx(2 * (0.5 - 0.1) / 1e-3)
    bad = check_passivity(1200, 0.0, 1e-3, 0.5)
    assert not bad.passive and "Colgate" in bad.reason
    assert not check_passivity(300, 0.5, 1e-3, 0.5).passive  # |B| alone uses up b
    # Quantization (Abbott and Okamura): 2 f_c / delta = 2 * 0.01 / 23 um = 870 N/m.
    q = check_passivity(900, 0.0, 1e-4, 0.5, resolution_m=23e-6, coulomb_friction_n=0.01)
    assert not q.passive and "quantization" in q.reason
    assert check_passivity(300, 0.1, 1e-3, 0.5, scale=3.0).passive is False  # device feels 3 kp


def test_default_gains_pass_with_margin():
    chk = ServoConfig().passivity()
    assert chk.passive and chk.margin >= DEFAULT_MIN_MARGIN


def test_non_passive_gains_are_refused_at_configuration_time():
    with pytest.raises(ConfigError, match=r"kp/kd: not passive.*Colgate"):
        validate_config(ServoConfig, {"kp": 4000, "kd": 0.0}, "expert.toml [servo]")
    cfg = pressing(4000, 0.0, allow=True)  # explicit opt-in is possible, with a warning
    assert not cfg.passivity().passive


def test_defaults_settle_at_press_over_kp_without_oscillation():
    cfg = pressing(300.0, 0.1)
    out = run_lockstep(cfg, demo_model(), 3.0)
    last = out["depth"][-1000:]
    assert last.mean() == pytest.approx(PRESS_N / 300.0, rel=0.05)
    assert np.ptp(last) < 0.05e-3  # at rest to encoder resolution
    # No growing oscillation: the motion in each later half second is no larger than before.
    spread = [np.ptp(out["depth"][k : k + 500]) for k in range(500, 3000, 500)]
    assert all(b <= a + 1e-9 for a, b in zip(spread, spread[1:], strict=False))
    assert np.abs(out["force"]).max() <= cfg.force_limit_n + 1e-9


def test_non_passive_gains_oscillate_in_the_sim():
    cfg = pressing(4000.0, 0.0, allow=True)
    out = run_lockstep(cfg, demo_model(), 3.0)
    last = out["depth"][-1000:]
    assert np.ptp(last) > 0.5e-3  # a sustained limit cycle of about a millimetre
    fy = out["force"][-1000:, 1]
    assert fy.max() > 2.5 and fy.min() == 0.0  # bouncing on and off the surface
    # Same scene with the defaults but the stiff gains made passive by the rule: calm.
    kp_ok = check_passivity(1, 0.0, 1e-3, 0.5).kp_max / DEFAULT_MIN_MARGIN
    calm = run_lockstep(pressing(kp_ok, 0.0), demo_model(), 3.0)
    assert np.ptp(calm["depth"][-1000:]) < 0.05e-3

"""Sampled-data stability of the rendered spring-damper: the passivity check on the gains.

A virtual wall ``K`` (N/m) with virtual damping ``B`` (N s/m) rendered at period ``T`` (s) on a
device with physical damping ``b`` (N s/m) is passive when (Colgate and Schenkel 1997)

    b > K T / 2 + |B|

and with encoder quantization ``delta`` (m) and Coulomb friction ``f_c`` (N) (Abbott and
Okamura 2005) also ``K <= 2 f_c / delta``. Motion scaling ``s`` (device metres to world metres)
multiplies the stiffness and damping felt at the device by ``s``. Passivity is sufficient, not
necessary: gains beyond it may still look stable with a firm grip, but a light grip (the sim's
default hand) lets them oscillate, which ``tests/haptics/test_stability.py`` shows.
"""

from __future__ import annotations

from dataclasses import dataclass

DEFAULT_MIN_MARGIN = 1.5  # the defaults must pass with at least this factor


@dataclass(frozen=True)
class PassivityCheck:
    """Result of :func:`check_passivity`. ``margin`` > 1 means passive (b over what is needed)."""

    passive: bool
    margin: float
    kp_max: float  # N/m, the largest passive stiffness for this kd (world units)
    reason: str


def check_passivity(
    kp: float,
    kd: float,
    period_s: float,
    device_damping: float,
    resolution_m: float | None = None,
    coulomb_friction_n: float | None = None,
    scale: float = 1.0,
) -> PassivityCheck:
    """Check gains ``kp`` (N/m), ``kd`` (N s/m), world frame, against the passivity bounds."""
    k_dev = kp * scale
    b_dev = abs(kd) * scale
    need = k_dev * period_s / 2.0 + b_dev
    margin = device_damping / need if need > 0 else float("inf")
    k_colgate = max(0.0, 2.0 * (device_damping - b_dev) / period_s)
    k_quant = float("inf")
    if resolution_m and coulomb_friction_n is not None:
        k_quant = 2.0 * coulomb_friction_n / resolution_m
        margin = min(margin, k_quant / k_dev if k_dev > 0 else float("inf"))
    kp_max = min(k_colgate, k_quant) / scale
    problems = []
    if device_damping <= need:
        problems.append(
            f"b = {device_damping:g} N s/m <= K T/2 + |B| = {need:.3g} N s/m (Colgate and "
            f"Schenkel; kp <= {k_colgate / scale:.0f} N/m at kd = {kd:g} N s/m, "
            f"T = {period_s * 1e3:g} ms)"
        )
    if k_dev > k_quant:
        problems.append(
            f"K = {k_dev:g} N/m > 2 f_c / delta = {k_quant:.0f} N/m (quantization, Abbott and "
            "Okamura)"
        )
    if problems:
        reason = "not passive: " + "; ".join(problems)
    else:
        reason = f"passive: margin {margin:.2f} (kp <= {kp_max:.0f} N/m at kd = {kd:g} N s/m)"
    return PassivityCheck(not problems, margin, kp_max, reason)

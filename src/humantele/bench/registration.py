"""``humantele bench registration``: how long registering the headset takes (number of
touched targets) against how accurate ``T_world_xr`` comes out, with noisy touches.

Monte Carlo on the solver the follower uses (:func:`humantele.follower.registration.fit_rigid`
and :func:`~humantele.follower.registration.refusal`): the page's targets (XR space, in
front of the technician at table height), an XR space placed in the world at a random
heading and offset, each touch = the target's world point + the hand's error + the
tracker's error (independent, Gaussian, per axis). Errors of the fit are measured where the
guide is drawn: the largest over the work area (a 50 x 20 x 40 cm box centred on the
targets, the abdomen: its corners and centre), and the rotation's angle. Time = the
technician's set-up plus seconds per target (assumed: ``--seconds-per-point``;
docs/registration.md says why).
Deterministic by seed; writes the "registration" section of docs/benchmarks.md and
docs/img/registration_speed_accuracy.png.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from humantele.bench import pyplot, save_chart
from humantele.follower.registration import (
    DegenerateRegistration,
    RegistrationConfig,
    fit_from_trajectories,
    fit_rigid,
    refusal,
    solve_trajectories,
)
from humantele.geometry import Pose, quat_from_axis_angle
from humantele.report import DOCS_DIR, machine_line, markdown_table, write_section

# Targets relative to their centre (m: right, up, ahead), as registration.js lays them out:
# the corners of a W x D rectangle first, then the middles of its edges, then the centre.
LAYOUTS = {
    "24 x 14 cm": (0.24, 0.14),
    "36 x 20 cm (the page's)": (0.36, 0.20),
    "50 x 30 cm": (0.50, 0.30),
}
POINTS = (3, 4, 5, 6, 8)
WORK_BOX = (0.5, 0.2, 0.4)  # m: right, up (centred on the targets), ahead: the abdomen
CONFIG = RegistrationConfig()  # the follower's defaults: its refusals


def targets(n: int, width: float, depth: float) -> NDArray[np.float64]:
    """``n`` targets (XR space, m) at table height in front of a viewer at the origin."""
    w, d = width / 2, depth / 2
    order = [(-w, -d), (w, -d), (w, d), (-w, d), (0, -d), (0, d), (-w, 0), (w, 0)]
    if n == 5:
        order = [*order[:4], (0.0, 0.0)]
    pts = np.array([[r, 0.0, -0.45 - a] for r, a in order[:n]])
    pts[:, 1] = 1.0  # table height in local-floor (m)
    return pts


def work_points(centre: NDArray[np.float64]) -> NDArray[np.float64]:
    """The work area's corners and centre (XR space): where the guide is drawn."""
    wx, wy, wz = WORK_BOX
    corners = [[sx * wx / 2, sy * wy / 2, sz * wz / 2] for sx in (-1, 1) for sy in (-1, 1)
               for sz in (-1, 1)]  # fmt: skip
    return centre + np.array([*corners, [0.0, 0.0, 0.0]])


def trial(
    rng: np.random.Generator, pts: NDArray[np.float64], hand_mm: float, tracker_mm: float
) -> tuple[float, float, float, float]:
    """One registration: (worst work-area error mm, angle error deg, residual RMS mm,
    1.0 if the follower would refuse it); NaNs when degenerate."""
    yaw = rng.uniform(-math.pi, math.pi)
    T = Pose(rng.uniform(-2, 2, 3), quat_from_axis_angle([0, 1, 0], yaw))
    sigma = math.hypot(hand_mm, tracker_mm) / 1000.0
    touched = T.apply(pts) + rng.normal(0.0, sigma, pts.shape)
    try:
        fit = fit_rigid(pts, touched)
    except DegenerateRegistration:
        return math.nan, math.nan, math.nan, 1.0
    work = work_points(pts.mean(axis=0))
    gap = np.linalg.norm(fit.T_world_xr.apply(work) - T.apply(work), axis=1).max()
    _, ang = fit.T_world_xr.distance_to(T)
    refused = refusal(fit, CONFIG) is not None
    return float(gap * 1000.0), math.degrees(ang), fit.rms_m * 1000.0, float(refused)


def run_case(n: int, layout: tuple[float, float], trials: int, hand_mm: float,
             tracker_mm: float, seed: int) -> dict:  # fmt: skip
    """Median and p95 of the errors over ``trials``, and how many fits are refused."""
    rng = np.random.default_rng(seed)
    pts = targets(n, *layout)
    res = np.array([trial(rng, pts, hand_mm, tracker_mm) for _ in range(trials)])
    refused = float(np.mean(res[:, 3])) * 100.0
    return {
        "n": n,
        "mm_p50": float(np.median(res[:, 0])),
        "mm_p95": float(np.percentile(res[:, 0], 95)),
        "deg_p50": float(np.median(res[:, 1])),
        "deg_p95": float(np.percentile(res[:, 1], 95)),
        "residual_p50": float(np.median(res[:, 2])),
        "refused_pct": refused,
    }


# The trajectory method, for comparison: 10 s of the technician's head looking around the
# work (30 pose pairs), the rig pose taken LAG later than the viewer pose it is paired with
# (two streams, no common clock), each pose off by the device's own jitter.
T_VIEWER_RIG = Pose([0.0, -0.03, 0.09], quat_from_axis_angle([1, 0, 0], math.radians(8)))
HEAD_S, HEAD_POSES = 10.0, 30
LAGS_MS = (0.0, 20.0, 50.0)


def head(t: float, phase: NDArray[np.float64]) -> Pose:
    """The viewer in XR space at ``t`` (s): looking down at the work, turning +-30 degrees
    left and right and +-15 up and down (peak ~20 degrees/s), swaying a few cm."""
    yaw = 0.5 * math.sin(0.6 * t + phase[0])
    pitch = -0.6 + 0.25 * math.sin(0.9 * t + phase[1])
    roll = 0.08 * math.sin(1.3 * t + phase[2])
    q = quat_from_axis_angle([0, 1, 0], yaw)
    for axis, ang in (([1, 0, 0], pitch), ([0, 0, 1], roll)):
        q = (Pose([0, 0, 0], q) @ Pose([0, 0, 0], quat_from_axis_angle(axis, ang))).quaternion
    pos = [0.05 * math.sin(0.7 * t + phase[0]), 1.6 + 0.03 * math.sin(1.1 * t),
           0.05 * math.sin(0.5 * t + phase[1])]  # fmt: skip
    return Pose(pos, q)


def _jitter(rng: np.random.Generator, T: Pose, mm: float, deg: float) -> Pose:
    d = quat_from_axis_angle(rng.normal(size=3), math.radians(deg) * abs(rng.normal()))
    return Pose(T.position + rng.normal(0, mm / 1000.0, 3), (Pose([0, 0, 0], d) @ T).quaternion)


def trajectory_case(trials: int, lag_s: float, known_offset: bool, seed: int,
                    jitter_mm: float = 1.0, jitter_deg: float = 0.2) -> dict:  # fmt: skip
    """The trajectory method's errors over the work area (as :func:`run_case`)."""
    rng = np.random.default_rng(seed)
    work = work_points(targets(4, 0.36, 0.20).mean(axis=0))
    out = []
    for _ in range(trials):
        T = Pose(rng.uniform(-2, 2, 3), quat_from_axis_angle([0, 1, 0], rng.uniform(-3, 3)))
        phase = rng.uniform(0, 2 * math.pi, 3)
        ts = np.linspace(0.0, HEAD_S, HEAD_POSES)
        viewers = [_jitter(rng, head(t, phase), jitter_mm, jitter_deg) for t in ts]
        rigs = [_jitter(rng, T @ head(t + lag_s, phase) @ T_VIEWER_RIG, jitter_mm, jitter_deg)
                for t in ts]  # fmt: skip
        if known_offset:
            est = fit_from_trajectories(viewers, rigs, T_VIEWER_RIG)
        else:
            est, _ = solve_trajectories(viewers, rigs)
        gap = np.linalg.norm(est.apply(work) - T.apply(work), axis=1).max() * 1000.0
        out.append((gap, math.degrees(est.distance_to(T)[1])))
    res = np.array(out)
    return {
        "mm_p50": float(np.median(res[:, 0])),
        "mm_p95": float(np.percentile(res[:, 0], 95)),
        "deg_p50": float(np.median(res[:, 1])),
        "deg_p95": float(np.percentile(res[:, 1], 95)),
    }


def chart(series: dict[str, list[dict]], setup_s: float, per_point_s: float, noise: str,
          trajectories: list[tuple[str, float, dict]]) -> Path:  # fmt: skip
    plt = pyplot()

    fig, axes = plt.subplots(1, 2, figsize=(10, 5.0), dpi=110)
    for (name, rows), colour in zip(series.items(), ("C1", "C0", "C2"), strict=False):
        t = [setup_s + per_point_s * r["n"] for r in rows]
        for ax, key in zip(axes, ("mm", "deg"), strict=True):
            ax.plot(t, [r[f"{key}_p50"] for r in rows], "-o", color=colour,
                    label=f"{name}, median")  # fmt: skip
            ax.plot(t, [r[f"{key}_p95"] for r in rows], "--", marker="s", color=colour,
                    mfc="none", label=f"{name}, p95")  # fmt: skip
            for x, r in zip(t, rows, strict=True):
                ax.annotate(f"{r['n']}", (x, r[f"{key}_p95"]), fontsize=7, xytext=(0, 5),
                            textcoords="offset points", ha="center")  # fmt: skip
    # The trajectory method (no touching, 10 s of head motion; no offset known: B = Z A X),
    # at three time mismatches between the streams: median, and p95 as the bar's top.
    for k, (label, lag_ms, r) in enumerate(trajectories):
        x = setup_s + HEAD_S + 0.6 * (k - 1)
        for ax, key in zip(axes, ("mm", "deg"), strict=True):
            y, top = r[f"{key}_p50"], r[f"{key}_p95"]
            ax.errorbar([x], [y], yerr=[[0], [top - y]], fmt="kx", ms=7, capsize=3,
                        label=label if k == 0 else None)  # fmt: skip
            ax.annotate(f"{lag_ms:g} ms", (x, top), fontsize=7, xytext=(0, 4),
                        textcoords="offset points", ha="center")  # fmt: skip
    for ax in axes:
        ax.axvline(30.0, color="r", lw=0.8, ls=":")
        ax.text(30.3, ax.get_ylim()[1] * 0.95, "30 s", color="r", fontsize=8, va="top")
        ax.set_xlabel(f"registration time, s ({setup_s:g} s + {per_point_s:g} s per target)")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("position error over the work area (worst), mm")
    axes[1].set_ylabel("rotation error, deg")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle(f"Headset registration: time against accuracy (numbers: targets; {noise})",
                 fontsize=10)  # fmt: skip
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    return save_chart(fig, DOCS_DIR / "img" / "registration_speed_accuracy.png")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--trials", type=int, default=2000, help="Monte-Carlo trials per case")
    parser.add_argument("--hand-mm", type=float, default=2.0, help="hand's error per axis, mm")
    parser.add_argument(
        "--tracker-mm", type=float, default=0.5, help="tracker's error per axis, mm"
    )
    parser.add_argument("--setup-s", type=float, default=6.0, help="press Register, pick up")
    parser.add_argument(
        "--seconds-per-point", type=float, default=4.0, help="reach a target, hold it 1 s"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-write", action="store_true", help="print only")


def run(args: argparse.Namespace) -> int:
    load0 = os.getloadavg()[0]
    series: dict[str, list[dict]] = {}
    rows = []
    for name, layout in LAYOUTS.items():
        series[name] = []
        for n in POINTS:
            r = run_case(n, layout, args.trials, args.hand_mm, args.tracker_mm, args.seed + n)
            series[name].append(r)
            t = args.setup_s + args.seconds_per_point * n
            row = [name, n, f"{t:.0f}", f"{r['mm_p50']:.2f}", f"{r['mm_p95']:.2f}",
                   f"{r['deg_p50']:.2f}", f"{r['deg_p95']:.2f}", f"{r['residual_p50']:.2f}",
                   f"{r['refused_pct']:.1f}"]  # fmt: skip
            rows.append(row)
            print(" | ".join(str(c) for c in row), flush=True)
    noise = f"hand {args.hand_mm:g} mm + tracker {args.tracker_mm:g} mm per axis"
    trajectories, traj_rows = [], []
    label = "trajectories (10 s of head motion), no offset known, by stream mismatch"
    for lag_ms in LAGS_MS:
        for known in (False, True):
            r = trajectory_case(max(1, args.trials // 4), lag_ms / 1000.0, known, args.seed)
            name = "offset known exactly" if known else "no offset known (B = Z A X)"
            if not known:
                trajectories.append((label, lag_ms, r))
            row = [name, f"{lag_ms:g}", f"{args.setup_s + HEAD_S:.0f}", f"{r['mm_p50']:.2f}",
                   f"{r['mm_p95']:.2f}", f"{r['deg_p50']:.2f}", f"{r['deg_p95']:.2f}"]  # fmt: skip
            traj_rows.append(row)
            print(" | ".join(row), flush=True)
    if args.no_write:
        return 0
    path = chart(series, args.setup_s, args.seconds_per_point, noise, trajectories)
    table = markdown_table(
        [
            "targets",
            "points",
            "time s",
            "work area mm p50",
            "p95",
            "angle deg p50",
            "p95",
            "residual mm p50",
            "refused %",
        ],  # fmt: skip
        rows,
    )
    traj_table = markdown_table(
        [
            "trajectories",
            "mismatch ms",
            "time s",
            "work area mm p50",
            "p95",
            "angle deg p50",
            "p95",
        ],  # fmt: skip
        traj_rows,
    )
    md = f"""## Headset registration: time against accuracy

`humantele bench registration` ({args.trials} Monte-Carlo trials per case, seed {args.seed};
{machine_line()} Load average {load0:.2f} at start, a shared machine; the figures do not
depend on it). Each touch is the target's world point plus the hand's error and the
tracker's ({noise}, Gaussian); the fit is the follower's (`fit_rigid`), the position error
the largest over the work area (a 50 x 20 x 40 cm box centred on the targets), the refusal the
follower's (`max_residual_mm` {CONFIG.max_residual_mm:g}). Time assumes
{args.setup_s:g} s to start and {args.seconds_per_point:g} s per target (reach it, hold
still 1 s); docs/registration.md discusses the figures and the choice of 4 targets.

![registration time against accuracy](img/{path.name})

{table}

For comparison, the trajectory method (no touching: {HEAD_S:g} s of the technician's head
looking around the work, {HEAD_POSES} pose pairs, each pose off by 1 mm and 0.2 degrees,
the rig pose paired with a viewer pose taken "mismatch" earlier; {max(1, args.trials // 4)}
trials each):

{traj_table}
"""
    print(f"wrote {write_section('registration', md)} and {path}")
    return 0

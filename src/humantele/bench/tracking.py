"""``humantele bench tracking``: IR marker tracking, time per frame against pose error.

Sweeps pipeline variants (centroid method, depth handling, refinement, filter) and noise
levels on simulated AHAT frames, then where the default fails (occlusion, clutter, distance,
a camera blur the sphere model does not expect, before and after calibrating it), the
filter's lag, and the force sensor's RMS error. OpenCV runs on one thread (one core).
Writes docs/img/tracking_speed_accuracy.png and the "tracking" section of docs/benchmarks.md.
Deterministic by ``--seed``.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from humantele.bench import publish, pyplot, save_chart
from humantele.geometry import Pose, quat_from_axis_angle, quat_multiply
from humantele.report import DOCS_DIR, machine_line, markdown_table
from humantele.tracking.filter import FilterConfig
from humantele.tracking.pipeline import PipelineConfig, Tracker
from humantele.tracking.psf import estimate_psf_sigma
from humantele.tracking.sim import SimFrameConfig, SimFrameSource, default_sim_pose

WRONG_M, WRONG_RAD = 0.005, np.radians(5.0)
BEFORE = "before: core median + 0.47 R depth"
FILTER = {"enabled": True, "alpha": 0.4, "beta": 0.05}
CHART = DOCS_DIR / "img" / "tracking_speed_accuracy.png"
# the matcher before the missing-marker checks (issue 9): any 3-marker fit within tolerance
NO_CHECKS = {"verify_missing": False, "max_rms_partial_mm": 1.5}

# sphere-shaped strays (same size as the markers, within 7 cm of the probe) and a second tool
STRAY_SCENES: dict[str, dict] = {
    "3 sphere strays": {"stray_spheres": 3},
    "one marker hidden + 1 sphere stray": {"occluded_markers": [1], "stray_spheres": 1},
    "two markers hidden + 1 sphere stray": {"occluded_markers": [0, 2], "stray_spheres": 1},
    "two markers hidden + 3 sphere strays": {"occluded_markers": [0, 2], "stray_spheres": 3},
    "second tool in view": {"second_tool": "reference_frame"},
    "second tool, one marker hidden": {"second_tool": "reference_frame", "occluded_markers": [3]},
    "second tool, two markers hidden": {
        "second_tool": "reference_frame",
        "occluded_markers": [1, 3],
    },
}

VARIANTS: dict[str, tuple[dict, dict]] = {
    "default (weighted, sphere model depth, refine)": ({}, {}),
    "before: core median + 0.47 R depth": ({"depth": "sphere", "iterations": 3}, {}),
    "no refinement (Kabsch only)": ({"refine": False}, {}),
    "binary centroid": ({"centroid": "binary"}, {}),
    "peak pixel centroid": ({"centroid": "peak"}, {}),
    "mean depth, no surface offset": ({"depth": "mean"}, {}),
    "depth of brightest pixel + R": ({"depth": "peak"}, {}),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frames", type=int, default=150, help="frames per configuration")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print a JSON summary as the last line")
    p.add_argument("--no-write", action="store_true", help="do not write docs/")


def random_poses(n: int, seed: int, dist: tuple[float, float] = (0.35, 0.5)) -> list[Pose]:
    """Poses of the probe in the camera frame: handle towards the camera, tilted <= 30 deg."""
    rng = np.random.default_rng(seed)
    base = default_sim_pose().quaternion
    out = []
    for _ in range(n):
        tilt = quat_from_axis_angle(rng.normal(size=3), np.radians(rng.uniform(0, 30)))
        pos = [rng.uniform(-0.08, 0.08), rng.uniform(-0.08, 0.08), rng.uniform(*dist)]
        out.append(Pose(pos, quat_multiply(tilt, base)))
    return out


def run_case(sim: SimFrameConfig, poses: list[Pose], pipe: dict, filt: dict) -> dict:
    """Track ``poses``; time per frame (pipeline only), errors, status counts."""
    src = SimFrameSource(sim)
    tracker = Tracker(src.tool, PipelineConfig(**pipe), FilterConfig(**filt))
    times, errs, tip_errs = [], [], []
    n_tracked = n_wrong = 0
    for i, pose in enumerate(poses):
        frame = src.render(pose, t=i / 45.0)
        t0 = time.perf_counter()
        res = tracker.process(frame)
        times.append(time.perf_counter() - t0)
        if res.T_camera_probe is None:
            continue
        n_tracked += 1
        dp, dr = pose.distance_to(res.T_camera_probe)
        if dp > WRONG_M or dr > WRONG_RAD:
            n_wrong += 1
        errs.append((dp, dr))
        tip = src.tool.tip
        tip_errs.append(np.linalg.norm(pose.apply(tip) - res.T_camera_probe.apply(tip)))
    e = np.array(errs).reshape(-1, 2)

    def rms(x):
        return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")

    return {
        "ms_per_frame": float(np.median(times) * 1e3),
        "pos_rmse_mm": rms(e[:, 0]) * 1e3,
        "rot_rmse_deg": float(np.degrees(rms(e[:, 1]))),
        "tip_rmse_mm": rms(tip_errs) * 1e3,
        "tracked_pct": 100.0 * n_tracked / len(poses),
        "wrong": n_wrong,
    }


def filter_lag(frames: int, seed: int, filt: dict) -> dict:
    """Lag (ms) and jitter (mm) of the output on a 0.1 m/s ramp: the along-track error / speed."""
    base = default_sim_pose()
    speed = 0.1
    poses = [
        Pose(base.position + [speed * i / 45.0 - 0.06, 0.0, 0.0], base.quaternion)
        for i in range(frames)
    ]
    src = SimFrameSource(SimFrameConfig(seed=seed))
    tr = Tracker(src.tool, PipelineConfig(), FilterConfig(**filt))
    along, across = [], []
    for i, p in enumerate(poses):
        r = tr.process(src.render(p, t=i / 45.0))
        if r.T_camera_probe is not None and i > 20:
            d = p.position - r.T_camera_probe.position
            along.append(d[0])
            across.append(np.linalg.norm(d[1:]))
    return {
        "lag_ms": float(np.mean(along) / speed * 1e3),
        "jitter_mm": float(np.std(along) * 1e3),
    }


def force_rms(seed: int) -> dict:
    from humantele.forcesense.calibration import calibrate_sim, calibration_loads
    from humantele.forcesense.sim import SimForceConfig, SimForceSensor

    cal = calibrate_sim(SimForceSensor(SimForceConfig(seed=seed)), seed=seed)
    out = {}
    cases = {
        "default": SimForceConfig(seed=seed),
        "drift": SimForceConfig(seed=seed, temp_swing_c=10, temp_period_s=5, outside_field_mt=0.5),
    }
    for name, cfg in cases.items():
        s = SimForceSensor(cfg)
        loads = calibration_loads(2000, seed=seed + 5)
        rd = []
        for i, f in enumerate(loads):
            s.set_force(f)
            rd.append(s.read(i / 100.0))
        err = cal.force(rd) - loads
        out[name] = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    return out


def chart(points: list[tuple[str, float, float]], noise: list[tuple[float, float, float]]) -> None:
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(7.5, 4.8), dpi=110)
    for name, ms, err in points:
        ax.scatter(ms, err, s=30)
        ax.annotate(name, (ms, err), fontsize=7, xytext=(4, 3), textcoords="offset points")
    if noise:
        xs, ys = [n[1] for n in noise], [n[2] for n in noise]
        ax.plot(xs, ys, "k--", lw=0.8, marker="x")
        for s, x, y in noise:
            ax.annotate(
                f"noise x{s:g}", (x, y), fontsize=7, xytext=(4, -9), textcoords="offset points"
            )
    ax.axhline(0.5, color="r", lw=0.8, ls=":")
    ax.axvline(2.0, color="r", lw=0.8, ls=":")
    ax.set_yscale("log")
    ax.set_xlabel("median time per 512x512 frame, ms (one core)")
    ax.set_ylabel("position RMSE, mm (log)")
    ax.set_title("IR marker tracking on simulated AHAT frames: speed against accuracy")
    fig.tight_layout()
    save_chart(fig, CHART)


def calibrated_psf(sim: SimFrameConfig, seed: int) -> float:
    """PSF sigma (px) estimated from 10 frames of other poses (no ground truth used)."""
    src = SimFrameSource(sim.model_copy(update={"seed": seed + 101}))
    frames = [src.render(p) for p in random_poses(10, seed + 102)]
    return estimate_psf_sigma(frames, src.tool.sphere_radius)


def run(args: argparse.Namespace) -> int:
    import cv2

    cv2.setNumThreads(1)
    n, seed = args.frames, args.seed
    load0 = os.getloadavg()[0]
    poses = random_poses(n, seed + 1)
    rows, points, summary = [], [], {"variants": {}, "scenarios": {}}

    def fmt(r):
        return [
            f"{r['ms_per_frame']:.2f}",
            f"{r['pos_rmse_mm']:.2f}",
            f"{r['rot_rmse_deg']:.2f}",
            f"{r['tip_rmse_mm']:.2f}",
            f"{r['tracked_pct']:.0f}",
            r["wrong"],
        ]

    for name, (pipe, filt) in VARIANTS.items():
        r = run_case(SimFrameConfig(seed=seed), poses, pipe, filt)
        summary["variants"][name] = r
        rows.append([name, "1", *fmt(r)])
        points.append((name, r["ms_per_frame"], r["pos_rmse_mm"]))
        print(f"{name:45s} {fmt(r)}", flush=True)
    noise_pts = []
    for scale in (0.5, 2.0, 4.0):
        r = run_case(SimFrameConfig(seed=seed, noise_scale=scale), poses, {}, {})
        summary["variants"][f"default, noise x{scale:g}"] = r
        rows.append(["default", f"{scale:g}", *fmt(r)])
        noise_pts.append((scale, r["ms_per_frame"], r["pos_rmse_mm"]))
        print(f"default noise x{scale:<32g} {fmt(r)}", flush=True)
    d = summary["variants"][next(iter(VARIANTS))]
    noise_pts.insert(1, (1.0, d["ms_per_frame"], d["pos_rmse_mm"]))
    scen_rows = []
    blur_sharp = SimFrameConfig(seed=seed, psf_sigma_px=0.5)
    blur_wide = SimFrameConfig(seed=seed, psf_sigma_px=1.0)
    psf_sharp, psf_wide = calibrated_psf(blur_sharp, seed), calibrated_psf(blur_wide, seed)
    finger = SimFrameConfig(seed=seed, partial_occlusion_prob=0.3)
    scenarios: dict[str, tuple[SimFrameConfig, dict]] = {
        "one marker hidden": (SimFrameConfig(seed=seed, occluded_markers=[1]), {}),
        "two markers hidden": (SimFrameConfig(seed=seed, occluded_markers=[0, 2]), {}),
        "finger over a sphere, 30 %": (finger, {}),
        "finger over a sphere, 30 %, before": (finger, VARIANTS[BEFORE][0]),
        "heavy clutter (8 glints, 10 bars)": (
            SimFrameConfig(seed=seed, spurious_rate=8.0, clutter_patches=10),
            {},
        ),
        "camera blur 0.5 px, model expects 0.7": (blur_sharp, {}),
        f"camera blur 0.5 px, calibrated ({psf_sharp:.2f})": (
            blur_sharp,
            {"psf_sigma_px": psf_sharp},
        ),
        "camera blur 1.0 px, model expects 0.7": (blur_wide, {}),
        f"camera blur 1.0 px, calibrated ({psf_wide:.2f})": (blur_wide, {"psf_sigma_px": psf_wide}),
        "noise x4": (SimFrameConfig(seed=seed, noise_scale=4.0), {}),
    }
    for name, kw in STRAY_SCENES.items():
        scenarios[name] = (SimFrameConfig(seed=seed, **kw), {})

    def before(cfg: SimFrameConfig, pipe: dict) -> list:
        r0 = run_case(cfg, poses, {**pipe, **NO_CHECKS}, {})
        return [f"{r0['tracked_pct']:.0f}", r0["wrong"]]

    for name, (cfg, pipe) in scenarios.items():
        r = run_case(cfg, poses, pipe, {})
        summary["scenarios"][name] = r
        b = before(cfg, pipe)
        r["before_checks"] = {"tracked_pct": float(b[0]), "wrong": b[1]}
        scen_rows.append([name, *fmt(r), *b])
        print(f"{name:45s} {fmt(r)} before {b}", flush=True)
    for dist in (0.3, 0.45, 0.6, 0.7, 0.9, 1.1):
        cfg = SimFrameConfig(seed=seed, background_depth_m=dist + 0.15)
        r = run_case(cfg, random_poses(max(n // 2, 10), seed + 2, (dist, dist)), {}, {})
        name = f"at {dist:.2f} m" + (" (depth wraps)" if dist + 0.0055 > 1.0 else "")
        summary["scenarios"][name] = r
        scen_rows.append([name, *fmt(r), "", ""])
        print(f"{name:45s} {fmt(r)}", flush=True)
    lag_off = filter_lag(max(n, 90), seed, {})
    lag_on = filter_lag(max(n, 90), seed, FILTER)
    force = force_rms(seed)
    src = SimFrameSource(SimFrameConfig(seed=seed))
    t_render = []
    for p in poses[:60]:
        t0 = time.perf_counter()
        src.render(p)
        t_render.append(time.perf_counter() - t0)
    render_ms = float(np.median(t_render) * 1e3)
    summary.update(
        filter_off=lag_off,
        filter_on=lag_on,
        force_rms_n=force,
        sim_render_ms=render_ms,
        frames=n,
        seed=seed,
    )
    print(f"lag off {lag_off}  on {lag_on}  force {force}  render {render_ms:.2f} ms")
    if not args.no_write:
        chart(points, noise_pts)
    head = [
        "variant",
        "noise",
        "ms/frame",
        "pos RMSE mm",
        "rot RMSE deg",
        "tip RMSE mm",
        "tracked %",
        "wrong",
    ]
    md = "\n\n".join(
        [
            "## Tracking (IR markers, simulated AHAT frames)",
            machine_line() + f" {n} frames per row, seed {seed}, `humantele bench tracking`;"
            f" load average {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end "
            "(times grow with it; the tracked and wrong columns do not).",
            "Time is the pipeline only (blobs, depth, matching, fit), median, one core; "
            f"rendering a sim frame takes {render_ms:.2f} ms more. Poses: 0.35-0.5 m, tilted "
            "<= 30 deg. *Wrong* counts tracked frames off by > 5 mm or 5 deg. Targets: "
            "<= 2 ms, <= 0.5 mm, <= 0.5 deg (STTAR 0.09 mm lateral / 0.42 mm depth / 0.80 deg;"
            " Polaris 0.25 mm RMS).",
            markdown_table(head, rows),
            "Depth: the default fits each marker's ToF image with a model of the sphere "
            "(blurred disc coverage, depth of the visible cap, amplitude-weighted mixing with "
            "the background ring; `humantele.tracking.sphere`): each pixel votes for the "
            "centre's range along the IR centroid's ray, robustly weighted. *Before* is the "
            "previous default (median range of the bright core + 0.47 R, fitted on the sim: "
            "biased by -1 mm at 0.5 m and +0.4 mm at 0.35 m). A blob whose IR image misfits "
            "the model (a finger over the sphere, a merged glint) is refused, so the pose "
            "comes from the other markers or is lost, never wrong. The model's one sensor "
            "parameter, the camera blur, is calibrated from IR frames alone "
            "(`humantele.tracking.psf.estimate_psf_sigma`, 10 frames).",
            "Where the default pipeline fails (hidden markers have a finger in front; sphere "
            "strays are drawn by the sim's marker renderer, never intersecting a marker; the "
            "second tool is `src/humantele/defaults/tools/reference_frame.toml` 7-14 cm "
            "from the probe). "
            "*Before checks*: the same scene with the matcher as it was before issue 9 "
            "(any three-marker fit within the distance tolerances).",
            markdown_table(
                ["scenario", *head[2:], "tracked % before checks", "wrong before checks"],
                scen_rows,
            ),
            "Lost, never wrong: a fit that leaves a marker unmatched (three of four) is kept "
            "only if (1) its RMS residual is <= 0.6 mm (1.5 mm for four), (2) no candidate "
            "point lies on that marker's ray or within the tool's marker spacing of its "
            "fitted place (it was seen and did not fit), and (3) the depth image shows a "
            "reason not to see it: at its fitted place the depth reads no farther than its "
            "front surface + 10 mm (a finger in front, or its own refused image). If the ray "
            "is clear, the background visible through where the marker would be, the fit is "
            "refuted (`humantele.tracking.evidence`). Without depth, or outside the image, "
            "only four-marker fits are trusted. A fit that puts its missing marker straight "
            "behind one of its own matched markers (the tool turned edge-on) is kept only "
            "when no other candidate is in view: with one, a stray may stand in for the "
            "hidden marker. Refusing those fits always cost the demo's side landmark press "
            "most of its frames (84 % tracked before, 17 % with the rule always applied, "
            "70 % now; `tests/tracking/test_tracking_markers.py`). "
            "The cost is the drop in tracked % in the rows above. The same scenes "
            "with 400 frames and seed 7 gave no wrong pose but one at noise x4 (2.5 mm, "
            "8 deg: three noisy markers whose fourth was not detected at all), beyond the "
            "sensor's spec; before the checks, every tracked frame with two markers hidden "
            "was wrong.",
            f"Alpha-beta filter (alpha {FILTER['alpha']}, beta {FILTER['beta']}) on a 0.1 m/s "
            f"ramp: it adds {lag_on['lag_ms'] - lag_off['lag_ms']:.1f} ms of lag and takes "
            f"the along-track jitter from {lag_off['jitter_mm']:.2f} to "
            f"{lag_on['jitter_mm']:.2f} mm.",
            f"Force sensor (sim, +-20 N presses, after least-squares calibration): "
            f"{force['default']:.3f} N RMS (vector); with 10 K temperature swings and a 0.5 mT "
            f"outside field: {force['drift']:.3f} N RMS (anchor: 0.45 N RMS).",
            f"![speed against accuracy](img/{CHART.name})",
        ]
    )
    publish("tracking", md, summary, args)
    return 0

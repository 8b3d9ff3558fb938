"""The study's table from its recordings: per scan and per condition, in the paper's shape.

Per scan (complete scans 1..N of each run; :mod:`humantele.analysis` does the alignment):

- the paper's four alignment figures (Table II): position and orientation RMSE, centered;
- the effective lag (s): the shift of the virtual track that best explains the follower's
  probe (least position RMSE, 0-2 s in 10 ms steps) - the follower's own lag plus the pose's
  one-way age - and the centered position RMSE with that lag removed;
- the mean error along the patient's y (mm, normal to the bed: the haptic model against the
  real surface shows there);
- video at the expert, per track (``/expert/video_frame`` received): latency capture to decoded
  p50/p95 (ms), frames per second, freezes per minute and the share of the scan frozen. A
  freeze is WebRTC's (webrtc-stats ``freezeCount``): a gap between two decoded frames longer
  than max(3 x the typical frame interval, that interval + 150 ms); a scan with no frame at
  all is frozen throughout; a track whose typical interval is ``OFF_INTERVAL_S`` or longer
  was off (the POV off sends a frame every 5 s), not live: its frozen share is none, said
  ``off``;
- the pose stream at the follower: median one-way age (``/follower/latency`` pose_one_way)
  and the share of the scan the virtual probe was stale (pose_stale_s);
- the sim ultrasound's known-answer image quality (0-1);
- the US picture at the expert: the share of the scan it was live (not frozen) and its SSIM
  against the frame the follower captured (:mod:`humantele.study.quality`).
- the time without tracker measurements (``sensing_gap_s``: a killed sensing process); such
  scans are marked ``*`` in the per-scan table.

Per run: set-up time (s, expert clock): the first calibration landmark taken to the patient
model at the expert (scan 1's start less ``start_after_model_s``) - the registration task the
follower does, with the model's trip over the link; the servo's rate and overruns.

Per condition: mean and SD over its scans (all seeds), and whether the follower can still
follow (:func:`verdict`): alignment within the study's bound (its worst scan, Table II:
position RMSE 51.8 mm, centered 18.5 mm) and the virtual probe stale less than half the time,
with the cause named from the recordings when not.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from humantele.report import markdown_table

# The 750 km study (the seed paper, Table II): mean and SD over 11 scans; the bound is its
# worst scan (scan 8: 51.8 mm; scan 5: 18.5 mm centered).
STUDY = {
    "position_rmse_mm": (31.9, 10.2),
    "centered_position_rmse_mm": (10.1, 3.7),
    "orientation_rmse_deg": (11.4, 3.55),
    "centered_orientation_rmse_deg": (5.81, 3.33),
}
BOUND = {"position_rmse_mm": 51.8, "centered_position_rmse_mm": 18.5}
# 754 km of fibre at 4.9 us/km: the propagation floor of the study's one-way delay (ms).
STUDY_ONE_WAY_MS = 754 * 4.9e-3
STALE_BREAK_PCT = 50.0  # the virtual probe stale this share of a scan: it cannot be followed
OFF_INTERVAL_S = 1.0  # frames this far apart (typically) are a track turned off, not video
FROZEN_BREAK_PCT = 50.0  # the expert's picture frozen this share of a scan
BASELINE_FROZEN_PCT = 10.0  # an unimpaired link's picture frozen more: the machine is busy
START_AFTER_MODEL_S = 2.0  # as humantele.study.session
EXTRA_TOPICS = ("/expert/video_frame", "/follower/latency", "/follower/calibration")
QUALITY_TOPICS = ("/expert/us_video", "/follower/us_image")  # the US picture's SSIM
LAG_MAX_S, LAG_STEP_S = 2.0, 0.01

ALIGN = (
    ("position_rmse_mm", "pos RMSE mm"),
    ("centered_position_rmse_mm", "centered pos mm"),
    ("orientation_rmse_deg", "orient RMSE deg"),
    ("centered_orientation_rmse_deg", "centered orient deg"),
)


def freezes(t: np.ndarray, start: float, stop: float) -> dict[str, float | int | None]:
    """Frames decoded at times ``t`` (s) in [start, stop]: fps, freezes (webrtc-stats
    definition, see the module docstring) per minute and the share of the span frozen (%);
    ``off``: the typical interval was :data:`OFF_INTERVAL_S` or more (the track was turned
    off, not frozen nor live: no freeze figures)."""
    span = stop - start
    t = np.sort(t[(t >= start) & (t <= stop)])
    if span <= 0:
        return {"fps": None, "freezes_per_min": None, "frozen_pct": None, "frames": 0}
    if t.size < 2:
        return {"fps": t.size / span, "freezes_per_min": 0.0, "frozen_pct": 100.0,
                "frames": int(t.size)}  # fmt: skip
    gaps = np.diff(np.concatenate([[start], t, [stop]]))
    typical = float(np.median(np.diff(t)))
    if typical >= OFF_INTERVAL_S:
        return {"fps": t.size / span, "freezes_per_min": None, "frozen_pct": None,
                "frames": int(t.size), "off": True}  # fmt: skip
    frozen = gaps > max(3.0 * typical, typical + 0.150)
    return {
        "fps": t.size / span,
        "freezes_per_min": float(frozen.sum()) / span * 60.0,
        "frozen_pct": 100.0 * float(gaps[frozen].sum()) / span,
        "frames": int(t.size),
        "off": False,
    }


def effective_lag(session: Any, start: float, stop: float) -> tuple[float | None, float | None]:
    """(lag s, centered position RMSE mm with it removed) of one scan: the shift of the virtual
    track that best explains the tracked probe (positions only)."""
    v, r = session.virtual, session.real
    sel = (r.t >= start) & (r.t <= stop)
    if sel.sum() < 10 or len(v) < 2:
        return None, None
    tr, pr = r.t[sel], r.position[sel]
    best = (math.inf, None, None)
    for lag in np.arange(0.0, LAG_MAX_S + 1e-9, LAG_STEP_S):
        tq = tr - lag
        ok = (tq >= v.t[0]) & (tq <= v.t[-1])
        if ok.sum() < 0.8 * len(tq):
            continue
        pv = np.column_stack([np.interp(tq[ok], v.t, v.position[:, k]) for k in range(3)])
        e = pr[ok] - pv
        rmse = float(np.sqrt(np.mean(np.sum(e * e, axis=1))))
        if rmse < best[0]:
            c = e - e.mean(axis=0)
            best = (rmse, float(lag), float(np.sqrt(np.mean(np.sum(c * c, axis=1)))) * 1e3)
    return best[1], best[2]


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) * 1e3 if values else None


def run_scans(run_dir: Path, summary: dict) -> list[dict[str, Any]]:
    """One row per complete scan 1..N of a recorded run (see the module docstring)."""
    from humantele.analysis.sessions import analyze_scans, load_sessions
    from humantele.recording import read_recording

    spec = summary["spec"]
    files = sorted(run_dir.glob("session*.mcap"))  # the expert's and the follower's
    sessions = load_sessions(files)
    extra: dict[str, list[dict]] = {k: [] for k in EXTRA_TOPICS}
    for f in files:
        rec = read_recording(f, EXTRA_TOPICS)
        for k in EXTRA_TOPICS:
            extra[k] += rec.samples(k)
    demo = summary.get("demo") or {}
    quality: list[tuple[float, int, float]] = []
    if spec.get("video"):
        from humantele.study.quality import us_ssim

        q: dict[str, list[dict]] = {k: [] for k in QUALITY_TOPICS}
        for f in files:
            rec = read_recording(f, QUALITY_TOPICS)
            for k in QUALITY_TOPICS:
                q[k] += rec.samples(k)
        quality = us_ssim(q[QUALITY_TOPICS[0]], q[QUALITY_TOPICS[1]])
    rows = []
    for session in sessions:
        to_e = session.clock.to_expert
        frames = {
            name: np.array(
                [s["t"] for s in extra["/expert/video_frame"]
                 if s.get("event") == "received" and s.get("stream") == name], dtype=float)
            for name in ("us", "pov")
        }  # fmt: skip
        ages = {
            name: [(s["t"], s["age_s"]) for s in extra["/expert/video_frame"]
                   if s.get("event") == "received" and s.get("stream") == name
                   and isinstance(s.get("age_s"), int | float) and math.isfinite(s["age_s"])]
            for name in ("us", "pov")
        }  # fmt: skip
        lat = [(float(to_e(s["t"])), s["name"], s["value_s"]) for s in extra["/follower/latency"]]
        points = [s["t"] for s in extra["/follower/calibration"] if s.get("event") == "point"]
        results = analyze_scans(session)
        starts = sorted(r.interval.start for r in results if r.interval.complete)
        setup = None
        if points and starts:
            setup = starts[0] - START_AFTER_MODEL_S - float(to_e(min(points)))
        for res in results:
            iv = res.interval
            if not iv.complete or not 1 <= iv.scan <= spec["scans"]:
                continue
            d = res.as_dict()
            row: dict[str, Any] = {
                "run": run_dir.name,
                "condition": spec["condition"]["name"],
                "seed": spec["seed"],
                **{
                    k: spec["condition"][k]
                    for k in ("delay_ms", "jitter_ms", "loss_pct", "bandwidth_kbps")
                },  # fmt: skip
                "scan": iv.scan,
                "duration_s": d["duration_s"],
                **{k: d[k] for k, _ in ALIGN},
                "mean_error_y_mm": d["mean_position_error_mm"][1],
                "sim_image_quality": d["sim_image_quality"],
                "sensing_gap_s": d["sensing_gap_s"],  # without tracker measurements (0: none)
            }
            lag, lag_c = effective_lag(session, iv.start, iv.stop)
            row["effective_lag_s"] = lag
            row["lag_removed_centered_mm"] = lag_c
            for name in ("us", "pov"):
                fz = freezes(frames[name], iv.start, iv.stop) if summary["spec"]["video"] else {}
                a = [age for t, age in ages[name] if iv.start <= t <= iv.stop]
                row[f"{name}_age_p50_ms"] = _pct(a, 50)
                row[f"{name}_age_p95_ms"] = _pct(a, 95)
                row[f"{name}_fps"] = fz.get("fps")
                row[f"{name}_freezes_per_min"] = fz.get("freezes_per_min")
                row[f"{name}_frozen_pct"] = fz.get("frozen_pct")
                row[f"{name}_off"] = bool(fz.get("off"))
            qs = [v for t, _, v in quality if iv.start <= t <= iv.stop]
            row["us_ssim"] = float(np.mean(qs)) if qs else None
            us_frozen = row.get("us_frozen_pct")
            row["us_live_pct"] = None if us_frozen is None else 100.0 - us_frozen
            # each report covers the ~1 s before it
            stale = [v for t, n, v in lat if n == "pose_stale_s" and iv.start < t <= iv.stop + 1]
            one_way = [v for t, n, v in lat if n == "pose_one_way" and iv.start <= t <= iv.stop]
            span = iv.stop - iv.start
            row["stale_pct"] = min(100.0, 100.0 * sum(stale) / span) if stale and span else None
            row["pose_age_p50_ms"] = float(np.median(one_way)) * 1e3 if one_way else None
            row["setup_s"] = setup
            row["load_1min"] = (summary.get("load_at_start") or [None])[0]
            conns = demo.get("link_connections")
            row["link_drops"] = None if conns is None else max(0, int(conns) - 1)
            row["servo_rate_hz"] = demo.get("servo_rate_hz")
            row["servo_overruns"] = demo.get("servo_overruns")
            rows.append(row)
    return rows


def _mean_sd(values: list[Any]) -> tuple[float | None, float | None]:
    v = [float(x) for x in values if isinstance(x, int | float) and math.isfinite(x)]
    if not v:
        return None, None
    return float(np.mean(v)), (float(np.std(v, ddof=1)) if len(v) > 1 else None)


SUMMARY_KEYS = (
    *(k for k, _ in ALIGN), "effective_lag_s", "lag_removed_centered_mm", "mean_error_y_mm",
    "us_age_p50_ms", "us_age_p95_ms", "pov_age_p50_ms", "pov_age_p95_ms", "us_fps", "pov_fps",
    "us_freezes_per_min", "us_frozen_pct", "pov_freezes_per_min", "pov_frozen_pct",
    "stale_pct", "pose_age_p50_ms", "setup_s", "sim_image_quality", "load_1min", "link_drops",
    "us_ssim", "us_live_pct",
)  # fmt: skip


def summarize(rows: list[dict], conditions: list[dict]) -> list[dict[str, Any]]:
    """Per condition (file order): the settings, scan count, mean and SD of each figure, and
    the verdict."""
    out = []
    for c in conditions:
        mine = [r for r in rows if r["condition"] == c["name"]]
        s: dict[str, Any] = {**c, "scans": len(mine), "runs": len({r["run"] for r in mine})}
        for k in SUMMARY_KEYS:
            s[k], s[f"{k}_sd"] = _mean_sd([r.get(k) for r in mine])
        for name in ("us", "pov"):  # scans the track was off in (no freeze figures)
            s[f"{name}_off_scans"] = sum(1 for r in mine if r.get(f"{name}_off"))
        s.update(verdict(s) if mine else {"follows": None, "cause": "no complete scan"})
        out.append(s)
    return out


def verdict(s: dict[str, Any]) -> dict[str, Any]:
    """Can the follower still follow on this condition, and if not, why (from the figures the
    recordings gave)."""
    causes = []
    pos, cen = s.get("position_rmse_mm"), s.get("centered_position_rmse_mm")
    over = (pos is not None and pos > BOUND["position_rmse_mm"]) or (
        cen is not None and cen > BOUND["centered_position_rmse_mm"]
    )
    stale = s.get("stale_pct")
    drops = s.get("link_drops")
    if stale is not None and stale > STALE_BREAK_PCT:
        causes.append(f"pose staleness: the virtual probe stale {stale:.0f} % of the scan")
    if drops and stale:  # the link fell and came back (a reconnection): said whatever the bound
        causes.append(
            f"the link dropped and reconnected ({drops:g} time(s) per run): the virtual probe "
            f"stale {stale:.0f} % of the scan"
        )
    if over:
        lag, lag_c = s.get("effective_lag_s"), s.get("lag_removed_centered_mm")
        y = s.get("mean_error_y_mm")
        if lag_c is not None and lag_c <= BOUND["centered_position_rmse_mm"]:
            causes.append(
                f"pose age: the follower follows poses {s['delay_ms']:g} ms old on top of its "
                f"own lag (effective lag {lag:.2f} s; with it removed, centered "
                f"{lag_c:.1f} mm)"
            )
        elif y is not None and pos and abs(y) > 0.5 * pos:
            causes.append(
                f"the haptic model against the real surface: mean error {y:.1f} mm normal "
                "to the bed"
            )
        else:
            causes.append("alignment over the study's bound (no single cause in the recordings)")
    frozen = [s.get(f"{n}_frozen_pct") for n in ("us", "pov")]
    if any(f is not None and f > FROZEN_BREAK_PCT for f in frozen):
        causes.append(
            "video freezes: the expert's picture frozen "
            + " / ".join("-" if f is None else f"{f:.0f}" for f in frozen)
            + " % of the scan (US / POV)"
        )
    follows = not (over or (stale is not None and stale > STALE_BREAK_PCT))
    return {"follows": follows, "cause": "; ".join(causes)}


def _f(v: Any, digits: int = 1) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _ms(v: Any, sd: Any, digits: int = 1) -> str:
    return _f(v, digits) + ("" if sd is None else f" ± {_f(sd, digits)}")


SCAN_HEADER = [
    "condition", "seed", "scan", *(h for _, h in ALIGN), "lag s", "US p50/p95 ms",
    "POV p50/p95 ms", "US / POV freezes /min", "US / POV frozen %", "stale %",
    "pose age ms", "set-up s",
]  # fmt: skip
COND_HEADER = [
    "condition", "one way ms", "loss %", "kbit/s", "scans", *(h for _, h in ALIGN), "lag s",
    "US p95 ms", "POV p95 ms", "US / POV frozen %", "US SSIM", "stale %", "link drops",
    "set-up s", "load", "follows",
]  # fmt: skip


def _frozen(r: dict, name: str) -> str:
    """A track's frozen share in a table: ``off`` for a scan it was off in (a condition's
    mean over the other scans, and ``off n/m``)."""
    if r.get(f"{name}_off"):
        return "off"
    n, scans = r.get(f"{name}_off_scans") or 0, r.get("scans") or 0
    if n and n >= scans:
        return "off"
    return _f(r.get(f"{name}_frozen_pct")) + (f" (off {n}/{scans})" if n else "")


def scan_table(rows: list[dict]) -> str:
    out = []
    for r in rows:
        out.append([
            r["condition"], str(r["seed"]), f"{r['scan']}{'*' if r.get('sensing_gap_s') else ''}",
            *(_f(r[k], 1 if "position" in k else 2) for k, _ in ALIGN),
            _f(r["effective_lag_s"], 2),
            f"{_f(r['us_age_p50_ms'], 0)} / {_f(r['us_age_p95_ms'], 0)}",
            f"{_f(r['pov_age_p50_ms'], 0)} / {_f(r['pov_age_p95_ms'], 0)}",
            f"{_f(r['us_freezes_per_min'])} / {_f(r['pov_freezes_per_min'])}",
            f"{_frozen(r, 'us')} / {_frozen(r, 'pov')}",
            _f(r["stale_pct"]), _f(r["pose_age_p50_ms"], 0), _f(r["setup_s"]),
        ])  # fmt: skip
    return markdown_table(SCAN_HEADER, out)


def condition_table(summary: list[dict]) -> str:
    out = []
    for s in summary:
        delay = f"{s['delay_ms']:g}" + (f" ± {s['jitter_ms']:g}" if s["jitter_ms"] else "")
        follows = {True: "yes", False: "**no**", None: "-"}[s.get("follows")]
        out.append([
            s["name"], delay, f"{s['loss_pct']:g}", f"{s['bandwidth_kbps']:g}" if
            s["bandwidth_kbps"] else "-", str(s["scans"]),
            *(_ms(s[k], s[f"{k}_sd"], 1 if "position" in k else 2) for k, _ in ALIGN),
            _f(s["effective_lag_s"], 2), _f(s["us_age_p95_ms"], 0), _f(s["pov_age_p95_ms"], 0),
            f"{_frozen(s, 'us')} / {_frozen(s, 'pov')}", _f(s.get("us_ssim"), 3),
            _f(s["stale_pct"]), _f(s["link_drops"], 0), _f(s["setup_s"]), _f(s["load_1min"]),
            follows,
        ])  # fmt: skip
    return markdown_table(COND_HEADER, out)


def study_line() -> str:
    """The 750 km study's row, for comparison (Table II, mean ± SD over 11 scans)."""
    return (
        "The 750 km study (Table II, 11 scans, human followers): "
        + ", ".join(
            f"{h} {m:g} ± {sd:g}" for (k, h), (m, sd) in zip(ALIGN, STUDY.values(), strict=True)
        )  # fmt: skip
        + f"; one-way propagation >= {STUDY_ONE_WAY_MS:.1f} ms (754 km of fibre)."
    )


AXES: dict[str, tuple[str, ...]] = {
    "delay": ("delay_ms", "jitter_ms"),
    "loss": ("loss_pct",),
    "bandwidth": ("bandwidth_kbps",),
}  # the impairments a condition sets; delay and its jitter are one axis


def axes_set(s: dict[str, Any]) -> set[str]:
    """The axes a condition impairs (a value other than 0)."""
    return {a for a, keys in AXES.items() if any(s.get(k) for k in keys)}


def _harsher(axis: str, s: dict[str, Any], than: dict[str, Any]) -> bool:
    """Whether ``s`` impairs ``axis`` more than ``than`` does (a thinner cap is harsher)."""
    if axis == "bandwidth":
        b, t = s.get("bandwidth_kbps") or math.inf, than.get("bandwidth_kbps") or math.inf
        return b < t
    return any((s.get(k) or 0.0) > (than.get(k) or 0.0) for k in AXES[axis])


def _harmless(summary: list[dict]) -> dict[str, list[dict]]:
    """Per axis, the conditions impairing that axis alone with which the follower followed."""
    return {a: [s for s in summary if axes_set(s) == {a} and s.get("follows")] for a in AXES}


def counts_for(axis: str, s: dict[str, Any], harmless: dict[str, list[dict]]) -> bool:
    """A condition tells about ``axis`` when it impairs it and each other impairment it sets
    is no harsher than one the follower followed with on its own (so a loss series at the
    750 km delay counts for loss; a satellite link of 300 ms, 1 % loss and 2000 kbit/s counts
    for no axis unless 300 ms alone was shown harmless)."""
    if axis not in axes_set(s):
        return False
    for other in axes_set(s) - {axis}:
        if not any(not _harsher(other, s, ok) for ok in harmless[other]):
            return False
    return True


def breaking_points(summary: list[dict]) -> dict[str, Any]:
    """Where the follower stops following, per axis, drawn only from conditions that tell
    about that axis (:func:`counts_for`): the first delay, loss and bandwidth cap at which it
    does not (None: not within those conditions), the harshest of each it still followed at,
    the delay at which a straight line through the centered RMSE against delay crosses the
    bound (delay-only conditions; None without a rising trend), and the conditions that
    changed several things at once and tell about no axis (``combined``)."""
    ran = [s for s in summary if s.get("follows") is not None]
    harmless = _harmless(ran)
    order = {
        "delay": lambda s: (s["delay_ms"], s.get("jitter_ms") or 0.0),
        "loss": lambda s: (s["loss_pct"], s["delay_ms"]),
        "bandwidth": lambda s: (-(s["bandwidth_kbps"] or math.inf), s["delay_ms"]),
    }
    per = {a: sorted((s for s in ran if counts_for(a, s, harmless)), key=order[a]) for a in AXES}
    first = {a: next((s for s in per[a] if not s["follows"]), None) for a in AXES}
    crossing = None
    clean = sorted((s for s in ran if axes_set(s) <= {"delay"}), key=order["delay"])
    pts = [(s["delay_ms"], s["centered_position_rmse_mm"]) for s in clean
           if s.get("centered_position_rmse_mm") is not None]  # fmt: skip
    if len({x for x, _ in pts}) >= 3:
        slope, icpt = np.polyfit([x for x, _ in pts], [y for _, y in pts], 1)
        if slope > 0:
            crossing = float((BOUND["centered_position_rmse_mm"] - icpt) / slope)
    told = {id(s) for a in AXES for s in per[a]}
    combined = [s for s in ran if len(axes_set(s)) > 1 and id(s) not in told]
    ok = {a: [s for s in per[a] if s["follows"]] for a in AXES}
    return {
        "delay": first["delay"], "loss": first["loss"], "bandwidth": first["bandwidth"],
        "delay_crossing_ms": crossing,
        "largest_delay_ms": ok["delay"][-1]["delay_ms"] if ok["delay"] else None,
        "largest_loss_pct": ok["loss"][-1]["loss_pct"] if ok["loss"] else None,
        "thinnest_kbps": ok["bandwidth"][-1]["bandwidth_kbps"] if ok["bandwidth"] else None,
        "combined": combined,
    }  # fmt: skip


def _label(s: dict[str, Any]) -> str:
    """``300 ms ± 30, 1 % loss, 2000 kbit/s``: what a condition sets."""
    parts = [f"{s['delay_ms']:g} ms" + (f" ± {s['jitter_ms']:g}" if s.get("jitter_ms") else "")]
    if s.get("loss_pct"):
        parts.append(f"{s['loss_pct']:g} % loss")
    if s.get("bandwidth_kbps"):
        parts.append(f"{s['bandwidth_kbps']:g} kbit/s")
    return ", ".join(parts)


def breaking_text(b: dict[str, Any]) -> str:
    """The breaking points in words: per axis from the conditions that tell about it, then each
    condition that changed several things at once, by name, with its measured cause."""
    lines = []
    if b["delay"] is not None:
        s = b["delay"]
        lines.append(f"- delay: the follower stops following at {s['delay_ms']:g} ms one way "
                     f"({s['name']}): {s['cause']}")  # fmt: skip
    elif b["largest_delay_ms"] is not None:
        lines.append(f"- delay: it still follows at the largest delay run, "
                     f"{b['largest_delay_ms']:g} ms one way")  # fmt: skip
    if b["delay_crossing_ms"] is not None:
        lines.append(
            f"- a straight line through the centered position RMSE against delay crosses the "
            f"study's bound ({BOUND['centered_position_rmse_mm']:g} mm) at "
            f"{b['delay_crossing_ms']:.0f} ms one way"
        )
    if b["loss"] is not None:
        s = b["loss"]
        lines.append(f"- loss: the follower stops following at {s['loss_pct']:g} % "
                     f"({s['name']}, {s['delay_ms']:g} ms): {s['cause']}")  # fmt: skip
    elif b["largest_loss_pct"] is not None:
        lines.append(f"- loss: it still follows at the largest loss run, "
                     f"{b['largest_loss_pct']:g} % each way")  # fmt: skip
    if b.get("bandwidth") is not None:
        s = b["bandwidth"]
        lines.append(f"- bandwidth: the follower stops following at {s['bandwidth_kbps']:g} "
                     f"kbit/s ({s['name']}): {s['cause']}")  # fmt: skip
    elif b.get("thinnest_kbps") is not None:
        lines.append(f"- bandwidth: it still follows at the thinnest link run, "
                     f"{b['thinnest_kbps']:g} kbit/s each way")  # fmt: skip
    for s in b.get("combined", []):
        what = " and ".join(sorted(axes_set(s)))
        if s["follows"]:
            verdict_text = "still follows" + (f" ({s['cause']})" if s.get("cause") else "")
        else:
            verdict_text = f"does not follow: {s['cause'] or 'cause not measured'}"
        lines.append(
            f"- {s['name']} ({_label(s)}) changes {what} at once, beyond what each was run "
            f"alone: it {verdict_text}. It sets no single axis's break point."
        )
    return "\n".join(lines)


def markdown(rows: list[dict], summary: list[dict], header: str = "") -> str:
    """The whole table as markdown: per condition, the causes, then per scan."""
    parts = [header] if header else []
    parts += ["### Per condition (mean ± SD over its scans)", condition_table(summary),
              study_line()]  # fmt: skip
    where = breaking_text(breaking_points(summary))
    if where:
        parts += ["### Where it breaks", where]
    base = [s for s in summary if s.get("scans") and not (s["delay_ms"] or s["jitter_ms"]
            or s["loss_pct"] or s["bandwidth_kbps"])]  # fmt: skip
    for s in base:
        fz = [s.get(f"{n}_frozen_pct") for n in ("us", "pov")]
        if any(f is not None and f > BASELINE_FROZEN_PCT for f in fz):
            parts.append(
                f"Note: on the unimpaired link ({s['name']}) the picture is itself frozen "
                + " / ".join(_f(f, 0) for f in fz)
                + f" % of the scan (US / POV), at a load average of {_f(s.get('load_1min'))}: "
                "that much of the video figures is the machine's (or the video pipeline's), not "
                "the link's."
            )
    broken = [s for s in summary if s.get("cause")]
    if broken:
        parts.append("\n".join(f"- **{s['name']}**: {s['cause']}" for s in broken))
    parts += ["### Per scan", scan_table(rows)]
    gaps = [r for r in rows if r.get("sensing_gap_s")]
    if gaps:
        parts.append(
            "\\* a sensing gap in the scan (the tracker gave no measurement for 1 s or more: "
            + "; ".join(
                f"{r['condition']} seed {r['seed']} scan {r['scan']}: {r['sensing_gap_s']:.1f} s"
                for r in gaps
            )  # fmt: skip
            + "); its figures stand on the rest of the scan"
        )
    return "\n\n".join(parts) + "\n"


def write_json(path: Path, rows: list[dict], summary: list[dict], meta: dict) -> None:
    path.write_text(json.dumps({"meta": meta, "conditions": summary, "scans": rows}, indent=1))

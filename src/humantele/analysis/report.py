"""The report of ``humantele analyze``: the paper's results (Table II, image quality against
alignment error, NASA-TLX and usability) from recorded sessions, as a dict, as text tables or
as JSON. The command line is :mod:`humantele.analysis.cli`; the rating sheet's
(:mod:`humantele.analysis.rating`) uses the same report."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from humantele.analysis.sessions import (
    SENSING_GAP_S,
    ScanResult,
    Session,
    analyze_scans,
    load_sessions,
)
from humantele.report import markdown_table

METRICS = (
    ("position_rmse_mm", "Position RMSE (mm)"),
    ("centered_position_rmse_mm", "Centered Position RMSE (mm)"),
    ("orientation_rmse_deg", "Orientation RMSE (deg)"),
    ("centered_orientation_rmse_deg", "Centered Orientation RMSE (deg)"),
)


def _mean_sd(values: list[float | None]) -> dict[str, float | int | None]:
    v = np.array([x for x in values if x is not None and math.isfinite(x)], dtype=float)
    return {
        "mean": float(v.mean()) if len(v) else None,
        "sd": float(v.std(ddof=1)) if len(v) > 1 else None,
        "n": int(len(v)),
    }


def analyze(
    recordings: list[Path],
    scores: Path | None = None,
    tlx: Path | None = None,
    usability: Path | None = None,
    exclude_scans: tuple[int, ...] = (),
    max_gap_s: float = 0.05,
) -> tuple[dict[str, Any], list[tuple[Session, ScanResult]]]:
    """The whole report as one JSON-able dict, and each scan with its session (for plots)."""
    sessions = load_sessions(recordings) if recordings else []
    pairs: list[tuple[Session, ScanResult]] = []
    for s in sessions:
        pairs += [(s, r) for r in analyze_scans(s, max_gap_s)]
    every = [r.as_dict() for _, r in pairs]
    scans = [s for s in every if s["complete"]]  # what the tables and summaries use
    report: dict[str, Any] = {
        "scans": every,
        "summary": {key: _mean_sd([s[key] for s in scans]) for key, _ in METRICS},
        "incomplete_scans": [
            {"session": s["session"], "scan": s["scan"], "reason": s["incomplete_reason"]}
            for s in every
            if not s["complete"]
        ],
        "sensing_gaps": [  # scans with stretches without tracker measurements
            {
                "session": s["session"],
                "scan": s["scan"],
                "gaps": s["sensing_gaps"],
                "total_s": s["sensing_gap_s"],
            }
            for s in every
            if s["sensing_gaps"]
        ],  # fmt: skip
        "sessions": [
            {
                "session": s.session_id,
                "files": [str(f) for f in s.files],
                "clock": {
                    "source": s.clock.source,
                    "offset_s": s.clock.offset_s,
                    "drift_ppm": s.clock.drift * 1e6,
                    "estimates": s.clock.n_estimates,
                },
            }
            for s in sessions
        ],
        "warnings": [w for s in sessions for w in s.warnings],
    }
    if scores is not None:
        from humantele.analysis.quality import read_scores, spearman, summarize_quality

        rows = read_scores(scores)
        quality = summarize_quality(rows)
        if exclude_scans:
            quality["without_excluded"] = summarize_quality(rows, exclude_scans)
        by_scan: dict[int, list[dict]] = {}
        for s in scans:
            by_scan.setdefault(s["scan"], []).append(s)
        dup = sorted(k for k, v in by_scan.items() if len(v) > 1)
        if dup:
            report["warnings"].append(
                f"scan numbers {dup} occur in several sessions: not correlated"
            )
        common = [k for k in sorted(by_scan) if str(k) in quality["scan_quality"] and k not in dup]
        missing = sorted(set(map(int, quality["scan_quality"])) - set(by_scan))
        if missing:
            report["warnings"].append(f"scores for scans {missing} have no recording")
        quality["spearman"] = {
            key: spearman(
                [quality["scan_quality"][str(k)] for k in common if by_scan[k][0][key] is not None],
                [by_scan[k][0][key] for k in common if by_scan[k][0][key] is not None],
            )
            for key, _ in METRICS
        }
        quality["source"] = "raters"
        report["quality"] = quality
    elif any(s.get("sim_image_quality") is not None for s in scans):
        report["quality"] = sim_quality_report(scans)
    if tlx is not None:
        from humantele.analysis.questionnaires import read_tlx, summarize_tlx

        report["tlx"] = summarize_tlx(read_tlx(tlx))
    if usability is not None:
        from humantele.analysis.questionnaires import read_usability, summarize_usability

        report["usability"] = summarize_usability(read_usability(usability))
    return report, pairs


SIM_QUALITY_NOTE = (
    "per-scan image quality from the recorded sim ultrasound (known answer, 0-1: the share of "
    "the target's largest section in view, coupled and out of shadow, mean over the scan's "
    "frames), used in place of rater scores"
)


def sim_quality_report(scans: list[dict[str, Any]]) -> dict[str, Any]:
    """Image quality per scan from the sim US known answer, and its Spearman correlation with
    each alignment metric (as for rater scores)."""
    from humantele.analysis.quality import spearman

    with_q = [s for s in scans if s.get("sim_image_quality") is not None]
    counts: dict[int, int] = {}
    for s in with_q:
        counts[s["scan"]] = counts.get(s["scan"], 0) + 1
    unique = [s for s in with_q if counts[s["scan"]] == 1]
    return {
        "source": "sim",
        "note": SIM_QUALITY_NOTE,
        "scan_quality": {str(s["scan"]): s["sim_image_quality"] for s in unique},
        "mean": float(np.mean([s["sim_image_quality"] for s in with_q])),
        "spearman": {
            key: spearman(
                [s["sim_image_quality"] for s in unique if s[key] is not None],
                [s[key] for s in unique if s[key] is not None],
            )
            for key, _ in METRICS
        },
    }


def _scan_label(s: dict[str, Any]) -> str:
    """A scan's number, with ``*`` when it has a sensing gap."""
    return f"{s['scan']}*" if s.get("sensing_gaps") else str(s["scan"])


def _f(v: float | None, digits: int) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _spearman_lines(q: dict[str, Any], what: str) -> list[str]:
    """A line per alignment metric: the Spearman correlation of ``what`` (the quality) with it."""
    lines = []
    for key, head in METRICS:
        sp = q["spearman"][key]
        lines.append(
            f"Spearman {what} vs {head}: rho {_f(sp['rho'], 2)} (p = {_f(sp['p'], 2)}, "
            f"n = {sp['n']})"
        )
    return lines


def format_report(report: dict[str, Any]) -> str:
    """The report as text: the paper's Table II layout (complete scans only), then the other
    results."""
    out = []
    complete = [s for s in report["scans"] if s.get("complete", True)]
    if report["scans"] and not complete:
        out += ["Alignment error per scan: no complete scan (see below)", ""]
    if complete:
        digits = {"position_rmse_mm": 1, "centered_position_rmse_mm": 1}
        rows = [
            [_scan_label(s)] + [_f(s[k], digits.get(k, 2)) for k, _ in METRICS] for s in complete
        ]
        summ = report["summary"]
        rows.append(
            ["Mean ± SD"]
            + [
                f"{_f(summ[k]['mean'], digits.get(k, 2))} ± {_f(summ[k]['sd'], digits.get(k, 2))}"
                for k, _ in METRICS
            ]
        )
        out += [
            "Alignment error per scan",
            "",
            markdown_table(["Scan"] + [h for _, h in METRICS], rows),
            "",
        ]
    if report.get("sensing_gaps"):
        out += [
            f"Scans with sensing gaps (*: no tracker measurement for {SENSING_GAP_S:g} s or more; "
            "their figures stand on the rest of the scan):"
        ]
        out += [
            f"- scan {g['scan']} of session {g['session']}: "
            + ", ".join(
                f"{x['duration_s']:.1f} s without measurements from {x['at_s']:.1f} s"
                for x in g["gaps"]
            )  # fmt: skip
            for g in report["sensing_gaps"]
        ]
        out.append("")
    if report.get("incomplete_scans"):
        out += ["Incomplete scans, left out of the tables and the mean ± SD:"]
        out += [
            f"- scan {s['scan']} of session {s['session']}: {s['reason']}"
            for s in report["incomplete_scans"]
        ]
        out.append("")
    if report["scans"]:
        for s in report["sessions"]:
            c = s["clock"]
            out.append(
                f"session {s['session']}: follower clock -> expert clock: {c['source']} "
                f"({c['estimates']} estimates), offset {c['offset_s']:.4f} s, "
                f"drift {c['drift_ppm']:.1f} ppm"
            )
        out.append("")
    q = report.get("quality")
    if q and q.get("source") == "sim":
        out += ["Image quality (sim ultrasound, 0-1)", "", f"Image quality: {q['note']}."]
        out.append(
            "per scan: "
            + ", ".join(f"scan {k}: {v:.2f}" for k, v in q["scan_quality"].items())
            + f"; mean {q['mean']:.2f}"
        )
        out += [*_spearman_lines(q, "sim quality"), ""]
    elif q:
        out += ["Image quality (0-5)", ""]
        for label, qq in (("all scans", q), ("without excluded scans", q.get("without_excluded"))):
            if not qq:
                continue
            share3 = qq["share_ge3_all_raters"]
            share5 = qq["share_5_all_raters"]
            out.append(
                f"{label}: {qq['images']} images, {qq['images_missing']} missing (0 from a "
                f"rater); captured: mean {_f(qq['mean_captured'], 2)} "
                f"± {_f(qq['sd_captured'], 2)}, "
                f">= 3 by all raters {_f(None if share3 is None else 100 * share3, 1)} %, "
                f"5 by all raters {_f(None if share5 is None else 100 * share5, 1)} %"
            )
        out += [*_spearman_lines(q, "quality"), ""]
    t = report.get("tlx")
    if t:
        rows = [
            [v["label"], _f(v["mean"], 1), _f(v["sd"], 1), _f(v["median"], 1)]
            for v in t["subscales"].values()
        ]
        rows.append(
            [
                "Raw TLX",
                _f(t["raw_tlx"]["mean"], 1),
                _f(t["raw_tlx"]["sd"], 1),
                _f(t["raw_tlx"]["median"], 1),
            ]
        )
        out += [
            f"NASA-TLX (n = {t['n']}, 0-100, lower is better)",
            "",
            markdown_table(["Subscale", "Mean", "SD", "Median"], rows),
            "",
        ]
    u = report.get("usability")
    if u:
        rows = [
            [
                v["prompt"] + (" (lower is better)" if v["lower_is_better"] else ""),
                f"{_f(v['mean'], 2)} ± {_f(v['sd'], 2)}",
            ]
            for v in u["items"].values()
        ]
        out += [
            f"Usability (n = {u['n']}, 0 strongly disagree .. 4 strongly agree)",
            "",
            markdown_table(["Prompt", "Mean ± SD"], rows),
            "",
        ]
    if report["warnings"]:
        out += ["Warnings:"] + [f"- {w}" for w in report["warnings"]]
    return "\n".join(out).rstrip() + "\n"


def print_report(report: dict, as_json: bool) -> None:
    """The report on stdout: JSON, or the tables as text."""
    if as_json:
        print(json.dumps(report, indent=2))
    else:
        sys.stdout.write(format_report(report))

"""Image-quality scores (the paper's 0-5 scale) and their relation to alignment error.

Scores CSV, one of two layouts (a header row is required):

- long: ``scan,target,rater,score`` - one row per score;
- wide: ``scan,target,<rater>,<rater>...`` - one row per image, one column per rater.

``score`` is an integer 0-5 (0 = target not obtained, 5 = good quality; Table I of the paper).
Summary as in the paper's Results: an image is *captured* when no rater gave it 0; over captured
images, the mean +- SD (sample SD) of all raters' scores, the share scored >= 3 by every rater
and the share scored 5 by every rater. A scan's quality (for the Spearman rank correlation with
its RMSE) is the mean score of its captured images.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from humantele.analysis.csvfile import csv_rows, number_cell
from humantele.config import ConfigError

SCORES = range(0, 6)


@dataclass(frozen=True)
class Score:
    scan: int
    target: str
    rater: str
    score: int


def _int_cell(value: str, where: str, column: str, lo: int, hi: int) -> int:
    return int(number_cell(value, where, column, lo, hi, integer=True))


def read_scores(path: str | Path) -> list[Score]:
    """Scores from a CSV (long or wide layout); ConfigError naming the row and column."""
    path = Path(path)
    header, rows = csv_rows(path, "scores")
    if "scan" not in header or "target" not in header:
        raise ConfigError(f"{path}: the header needs columns 'scan' and 'target', got {header}")
    long = set(header) == {"scan", "target", "rater", "score"}
    raters = [h for h in header if h not in ("scan", "target")]
    if not long and not raters:
        raise ConfigError(f"{path}: no rater columns (or use scan,target,rater,score)")
    out: list[Score] = []
    seen: set[tuple[int, str, str]] = set()
    for _row_no, where, row in rows:
        scan = _int_cell(row["scan"], where, "scan", 0, 10**6)
        target = (row["target"] or "").strip()
        if not target:
            raise ConfigError(f"{where}: column 'target': empty")
        if long:
            rater = (row["rater"] or "").strip()
            if not rater:
                raise ConfigError(f"{where}: column 'rater': empty")
            pairs = [(rater, _int_cell(row["score"], where, "score", 0, 5))]
        else:
            pairs = [(r, _int_cell(row[r], where, r, 0, 5)) for r in raters]
        for rater, score in pairs:
            key = (scan, target, rater)
            if key in seen:
                raise ConfigError(f"{where}: scan {scan} target {target!r} rater {rater!r} twice")
            seen.add(key)
            out.append(Score(scan, target, rater, score))
    if not out:
        raise ConfigError(f"{path}: no scores")
    return out


def _images(scores: list[Score]) -> dict[tuple[int, str], dict[str, int]]:
    images: dict[tuple[int, str], dict[str, int]] = {}
    for s in scores:
        images.setdefault((s.scan, s.target), {})[s.rater] = s.score
    raters = {s.rater for s in scores}
    for (scan, target), by_rater in images.items():
        if set(by_rater) != raters:
            missing = ", ".join(sorted(raters - set(by_rater)))
            raise ConfigError(f"scores: scan {scan} target {target!r} has no score from {missing}")
    return images


def summarize_quality(scores: list[Score], exclude_scans: tuple[int, ...] = ()) -> dict[str, Any]:
    """The paper's image-quality figures (see the module docstring), scans excluded if asked."""
    scores = [s for s in scores if s.scan not in exclude_scans]
    images = _images(scores)
    captured = {k: v for k, v in images.items() if min(v.values()) > 0}
    values = np.array([x for v in captured.values() for x in v.values()], dtype=float)
    counts = {k: 0 for k in SCORES}
    for s in scores:
        counts[s.score] += 1
    n_scores = max(len(scores), 1)
    n_cap = len(captured)
    per_scan: dict[int, list[float]] = {}
    for (scan, _), v in captured.items():
        per_scan.setdefault(scan, []).extend(v.values())
    return {
        "raters": sorted({s.rater for s in scores}),
        "excluded_scans": list(exclude_scans),
        "images": len(images),
        "images_missing": len(images) - n_cap,
        "images_captured": n_cap,
        "mean_captured": float(values.mean()) if len(values) else None,
        "sd_captured": float(values.std(ddof=1)) if len(values) > 1 else None,
        "share_ge3_all_raters": (
            sum(min(v.values()) >= 3 for v in captured.values()) / n_cap if n_cap else None
        ),
        "share_5_all_raters": (
            sum(min(v.values()) == 5 for v in captured.values()) / n_cap if n_cap else None
        ),
        "score_counts": {str(k): c for k, c in counts.items()},
        "score_proportions": {str(k): c / n_scores for k, c in counts.items()},
        "scan_quality": {str(k): float(np.mean(v)) for k, v in sorted(per_scan.items())},
    }


def spearman(x: list[float], y: list[float]) -> dict[str, float | int | None]:
    """Spearman's rank correlation of x and y with its two-sided p-value (None when n < 3 or
    an input is constant)."""
    n = len(x)
    if n < 3 or len(set(x)) < 2 or len(set(y)) < 2:
        return {"rho": None, "p": None, "n": n}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = stats.spearmanr(x, y)
    return {"rho": float(res.statistic), "p": float(res.pvalue), "n": n}

"""NASA-TLX and the paper's modified system usability scale, from CSV responses.

NASA-TLX: raw (unweighted) TLX, as the paper reports subscale means out of 100 with no
weighting. CSV header: optional ``follower`` and ``scan`` columns, then the six subscales
``mental,physical,temporal,performance,effort,frustration`` (0-100; lower is better, even for
performance, as in the paper's Fig. 7).

Usability (Table III of the paper, 0 = strongly disagree .. 4 = strongly agree): optional
``follower``/``scan``, then the eight item columns of :data:`USABILITY_ITEMS` (integers 0-4).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from humantele.analysis.csvfile import csv_rows, number_cell
from humantele.config import ConfigError
from humantele.recording.schemas import check_participant_id

TLX_SUBSCALES: dict[str, str] = {
    "mental": "Mental demand",
    "physical": "Physical demand",
    "temporal": "Temporal demand",
    "performance": "Performance",
    "effort": "Effort",
    "frustration": "Frustration",
}

# key -> (prompt as in the paper's Table III, lower is better)
USABILITY_ITEMS: dict[str, tuple[str, bool]] = {
    "easy_to_use": ("I thought the overall system was easy to use", False),
    "follow_virtual": ("I found it easy to follow the virtual transducer", False),
    "point_fitting": ("I found the point/dot fitting at the beginning easy to do", False),
    "follow_instructions": (
        "I found it easy to follow the sonographer/expert's instructions",
        False,
    ),
    "learn_before": (
        "I needed to learn a lot of things before I could get going with the system",
        True,
    ),
    "learn_quickly": (
        "I would imagine that most people would learn to use this system very quickly",
        False,
    ),
    "cumbersome": ("I found the system very cumbersome to use", True),
    "confident": ("I felt very confident using the system", False),
}

_ID_COLUMNS = ("follower", "scan")


@dataclass(frozen=True)
class Responses:
    """Questionnaire answers: ``values`` (respondents, items) in the order of ``items``."""

    items: tuple[str, ...]
    values: np.ndarray
    respondents: tuple[str, ...]


def _read(
    path: str | Path, items: tuple[str, ...], lo: float, hi: float, integer: bool
) -> Responses:
    path = Path(path)
    header, csv_reader = csv_rows(path, "responses")
    unknown = [h for h in header if h not in items and h not in _ID_COLUMNS]
    missing = [i for i in items if i not in header]
    if unknown or missing:
        raise ConfigError(
            f"{path}: header: "
            + "; ".join(
                part
                for part in (
                    f"unknown column(s) {unknown}" if unknown else "",
                    f"missing column(s) {missing}" if missing else "",
                )
                if part
            )
            + f" (expected optional follower, scan and {', '.join(items)})"
        )
    rows, who = [], []
    for row_no, where, row in csv_reader:
        if "follower" in row:
            try:
                check_participant_id((row["follower"] or "").strip(), "follower")
            except ValueError as exc:
                raise ConfigError(f"{where}: column 'follower': {exc}") from None
        who.append((row.get("follower") or f"#{row_no - 1}").strip())
        rows.append([number_cell(row[item], where, item, lo, hi, integer) for item in items])
    if not rows:
        raise ConfigError(f"{path}: no responses")
    return Responses(items, np.array(rows, dtype=float), tuple(who))


def read_tlx(path: str | Path) -> Responses:
    """NASA-TLX responses (0-100 per subscale); ConfigError naming row and column."""
    return _read(path, tuple(TLX_SUBSCALES), 0.0, 100.0, integer=False)


def read_usability(path: str | Path) -> Responses:
    """Modified usability scale responses (integers 0-4); ConfigError naming row and column."""
    return _read(path, tuple(USABILITY_ITEMS), 0.0, 4.0, integer=True)


def _mean_sd(v: np.ndarray) -> dict[str, float | None]:
    return {
        "mean": float(v.mean()),
        "sd": float(v.std(ddof=1)) if len(v) > 1 else None,
        "median": float(np.median(v)),
    }


def summarize_tlx(r: Responses) -> dict[str, Any]:
    """Per-subscale mean, SD (sample) and median, and the raw TLX (mean of the six)."""
    out: dict[str, Any] = {"n": len(r.respondents), "subscales": {}}
    for k, item in enumerate(r.items):
        out["subscales"][item] = {"label": TLX_SUBSCALES[item], **_mean_sd(r.values[:, k])}
    out["raw_tlx"] = _mean_sd(r.values.mean(axis=1))
    return out


def summarize_usability(r: Responses) -> dict[str, Any]:
    """Per-item mean, SD and median, with the prompt and whether lower is better."""
    out: dict[str, Any] = {"n": len(r.respondents), "items": {}}
    for k, item in enumerate(r.items):
        prompt, lower = USABILITY_ITEMS[item]
        v = r.values[:, k]
        out["items"][item] = {
            "prompt": prompt,
            "lower_is_better": lower,
            **_mean_sd(v),
            "share_agree": float(np.mean(v >= 3)),
        }
    return out

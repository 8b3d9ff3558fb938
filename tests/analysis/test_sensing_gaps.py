"""A scan with a sensing gap inside (a killed sensing process: 10.1 s without measurements,
issue 34 §4) is said per scan by ``analyze`` and marked in the study's per-scan table."""

from __future__ import annotations

import numpy as np
import pytest

from humantele.analysis.report import analyze, format_report
from humantele.analysis.sessions import sensing_gaps
from humantele.recording.synthetic import SyntheticSession, write_synthetic
from humantele.study.table import markdown


def test_gaps_are_found_inside_and_at_the_edges_of_a_scan():
    t = np.concatenate([np.arange(0.0, 5.0, 1 / 45), np.arange(15.1, 20.0, 1 / 45)])
    (gap,) = sensing_gaps(t, 1.0, 19.0)
    assert gap[0] == pytest.approx(4.0, abs=0.03) and gap[1] == pytest.approx(10.1, abs=0.03)
    assert sensing_gaps(t, 1.0, 4.0) == []
    assert sensing_gaps(t, 6.0, 9.0) == [(0.0, 3.0)]  # no frame at all in it
    assert sensing_gaps(t, 13.0, 16.0)[0] == pytest.approx((0.0, 2.1), abs=0.03)  # from start


def test_analyze_says_the_gap_of_the_scan_it_is_in(tmp_path):
    e, f = tmp_path / "e.mcap", tmp_path / "f.mcap"
    # three scans of ~9.7 s (1 s between); the gap: 14.0 to 24.1 s, inside scans 2 and 3
    cfg = SyntheticSession(duration_s=33.0, n_scans=3, offset_mm=(10.0, 0.0, 0.0),
                           sensing_gaps=[(14.0, 10.1)], expert_rate_hz=200.0)  # fmt: skip
    write_synthetic(e, cfg, follower_path=f)
    report, _ = analyze([e, f])
    by_scan = {s["scan"]: s for s in report["scans"]}
    assert by_scan[1]["sensing_gaps"] == [] and by_scan[1]["sensing_gap_s"] == 0
    total = by_scan[2]["sensing_gap_s"] + by_scan[3]["sensing_gap_s"]
    assert total == pytest.approx(10.1 - 1.0, abs=0.1)  # less the 1 s between the scans
    assert [g["scan"] for g in report["sensing_gaps"]] == [2, 3]
    text = format_report(report)
    assert "| 2* |" in text and "| 3* |" in text and "| 1 |" in text
    assert "Scans with sensing gaps" in text and "s without measurements from" in text


def test_the_study_table_marks_a_scan_with_a_gap():
    row = {"condition": "lan", "seed": 1, "scan": 2, "effective_lag_s": 0.3,
           "position_rmse_mm": 10.0, "centered_position_rmse_mm": 5.0,
           "orientation_rmse_deg": 3.0, "centered_orientation_rmse_deg": 2.0,
           "us_age_p50_ms": None, "us_age_p95_ms": None, "pov_age_p50_ms": None,
           "pov_age_p95_ms": None, "us_freezes_per_min": None, "pov_freezes_per_min": None,
           "us_frozen_pct": None, "pov_frozen_pct": None, "stale_pct": 0.0,
           "pose_age_p50_ms": 1.0, "setup_s": 4.0}  # fmt: skip
    clean = markdown([{**row, "sensing_gap_s": 0.0}], [])
    marked = markdown([{**row, "sensing_gap_s": 10.1}], [])
    assert "| 2 |" in clean and "sensing gap" not in clean
    assert "| 2* |" in marked and "lan seed 1 scan 2: 10.1 s" in marked

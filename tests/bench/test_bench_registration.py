"""``humantele bench registration``: the targets it lays out are the page's, and its figures
behave as the geometry says (wider targets and more of them: smaller errors)."""

import argparse

import numpy as np

from humantele.bench import registration as bench


def test_targets_are_the_pages_layout_and_errors_shrink_with_spread_and_points():
    pts = bench.targets(4, 0.36, 0.20)
    assert pts.shape == (4, 3) and np.allclose(pts[:, 1], 1.0)
    assert np.ptp(pts[:, 0]) == 0.36 and np.isclose(np.ptp(pts[:, 2]), 0.20)
    small = bench.run_case(4, (0.24, 0.14), 300, 2.0, 0.5, seed=1)
    wide = bench.run_case(4, (0.50, 0.30), 300, 2.0, 0.5, seed=1)
    many = bench.run_case(8, (0.24, 0.14), 300, 2.0, 0.5, seed=1)
    assert wide["mm_p50"] < small["mm_p50"] and wide["deg_p50"] < small["deg_p50"]
    assert many["deg_p50"] < small["deg_p50"]
    assert small["mm_p50"] <= small["mm_p95"] and small["refused_pct"] < 5.0
    exact = bench.run_case(3, (0.36, 0.20), 20, 0.0, 0.0, seed=1)
    assert exact["mm_p95"] < 1e-6 and exact["deg_p95"] < 1e-6


def test_run_prints_without_writing(capsys):
    args = argparse.Namespace(trials=20, hand_mm=2.0, tracker_mm=0.5, setup_s=6.0,
                              seconds_per_point=4.0, seed=0, no_write=True)  # fmt: skip
    assert bench.run(args) == 0
    assert "36 x 20 cm (the page's) | 4 | 22 |" in capsys.readouterr().out

"""`humantele bench haptics` runs, reports every scene and method, and its figures are sane."""

import argparse
import json

from humantele.bench import haptics as bench


def test_bench_haptics_small_run(monkeypatch, capsys):
    monkeypatch.setattr(bench, "BATCH_POINTS", 500)
    monkeypatch.setattr(bench, "REPEATS", 1)
    monkeypatch.setattr(bench, "SCALAR_POINTS", 20)
    args = argparse.Namespace(points=200, seed=3, json=True, no_write=True)
    assert bench.run(args) == 0
    out = capsys.readouterr().out
    results = json.loads(out.strip().splitlines()[-1])
    assert set(results["scenes"]) == set(bench.SCENES)
    for scene in results["scenes"].values():
        m = scene["methods"]
        assert m["exact"]["depth_err_max_mm"] == 0.0
        assert m["newton"]["depth_err_max_mm"] < 0.05
        assert all(r["scalar_us"] > 0 and r["batch_evals_per_s"] > 0 for r in m.values())
    # the flattened scenes are where the paper's radial method is documented to fail
    assert results["scenes"]["flattened"]["methods"]["radial"]["depth_err_max_mm"] > 1.0
    assert "| torso (paper) | radial |" in out
    # same seed, same points: the accuracy figures repeat exactly
    assert bench.run(args) == 0
    again = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for name, scene in results["scenes"].items():
        for m, r in scene["methods"].items():
            assert again["scenes"][name]["methods"][m]["depth_err_max_mm"] == r["depth_err_max_mm"]

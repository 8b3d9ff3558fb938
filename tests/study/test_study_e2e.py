"""``humantele study configs/study-tiny.toml``: two whole sessions (both daemons, the servo,
video, coturn and the WAN emulator), recorded, analysed, tabled and charted; a second call
records nothing again."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from humantele.study.conditions import load_conditions
from humantele.transport.turnserver import TurnServer

TINY = Path(__file__).resolve().parents[2] / "configs" / "study-tiny.toml"


@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.whole_session  # one at a time across the lanes (tests/session_slot.py)
@pytest.mark.skipif(not TurnServer.available(), reason="no turnserver (system package coturn)")
def test_a_tiny_study_records_tables_and_charts_and_resumes(tmp_path):
    out, img = tmp_path / "out", tmp_path / "img"
    cmd = [sys.executable, "-m", "humantele", "study", str(TINY), "--out", str(out),
           "--charts", str(img), "--json"]  # fmt: skip
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=900, env=env)
    logs = "".join(p.read_text()[-2000:] for p in out.glob("*/session.log"))
    assert first.returncode == 0, first.stderr[-3000:] + logs
    result = json.loads(first.stdout.strip().splitlines()[-1])
    study = load_conditions(TINY)
    # each run: its recordings and summary; the servo kept its budget or the runner said so
    for run in study.runs():
        d = out / run.run_id
        assert (d / "session.expert.mcap").exists() and (d / "session.follower.mcap").exists()
        summary = json.loads((d / "summary.json").read_text())
        assert summary["exit_code"] == 0 and summary["stopped_after_scans"]
        assert summary["demo"]["scans"] == 1 and summary["demo"]["calibrated"]
        assert summary["spec"]["condition"]["name"] == run.condition.name
    wan = json.loads((out / "wan-s1" / "summary.json").read_text())
    relay = wan["relay"]
    # the emulator was on the path: its loss and its delay (100 ms, FIFO jitter adds to it)
    assert relay["up"]["lost"] > 0 and relay["down"]["lost"] > 0
    assert 0.095 <= relay["down"]["held_mean_s"] < 0.3
    clean = json.loads((out / "clean-s1" / "summary.json").read_text())["relay"]
    assert clean["up"]["lost"] == 0 and clean["down"]["forwarded"] > 1000  # relayed, unimpaired
    # the table: one complete scan per run, the figures the recordings give
    rows = {r["condition"]: r for r in result["scans"]}
    assert set(rows) == {"clean", "wan"}
    for r in rows.values():
        assert r["scan"] == 1 and r["position_rmse_mm"] > 0 and r["us_fps"] > 0
        assert r["effective_lag_s"] is not None and r["stale_pct"] is not None
        assert r["setup_s"] is not None and r["setup_s"] > 0
    # the pose reached the follower ~100 ms old on the impaired link, a few ms on the clean
    assert rows["wan"]["pose_age_p50_ms"] > 90.0 > rows["clean"]["pose_age_p50_ms"]
    conds = {c["name"]: c for c in result["conditions"]}
    assert conds["wan"]["scans"] == 1 and conds["wan"]["follows"] is not None
    assert sorted(p.name for p in img.glob("*.png")) == [
        "study_alignment_vs_delay.png", "study_freezes_vs_loss.png",
    ]  # fmt: skip
    assert "### Per condition" in (out / "table.md").read_text()
    # again: everything is recorded, nothing runs, the same table
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "2 runs (2 recorded before)" in again.stderr
    assert json.loads(again.stdout.strip().splitlines()[-1])["scans"] == result["scans"]

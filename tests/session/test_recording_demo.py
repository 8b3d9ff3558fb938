"""``humantele demo --record FILE`` then ``humantele analyze``: the alignment error found in the
recordings is the one the simulated follower was configured with."""

import math

import pytest

from humantele.analysis.report import analyze
from humantele.demo_report import summarize
from humantele.demo_status import status_line
from humantele.follower.sim_human import SimHumanConfig
from humantele.recording import read_recording


@pytest.mark.slow
def test_demo_records_a_scan_that_analyze_measures(demo_run):
    """The shared demo run (session_helpers.demo_run), recorded: stopped once scan 1 has run
    for a few seconds."""
    assert demo_run.returncode == 0, demo_run.err[-3000:]
    summary = demo_run.summary
    expert, follower = demo_run.recordings
    assert f"humantele analyze {expert} {follower}" in demo_run.err
    assert summary["scans"] == 1
    for role in ("expert", "follower"):
        st = summary["recording"][role]
        assert st["error"] is None and st["dropped"] == 0 and st["written"] == st["queued"] > 100
    e, f = read_recording(expert), read_recording(follower)
    assert e.complete and f.complete
    assert e.session["session_id"] == f.session["session_id"]
    assert (f.session["follower_id"], e.session["sonographer_id"]) == ("F0", "S0")

    report, _ = analyze([expert, follower])
    assert report["warnings"] == []
    (scan,) = report["scans"]
    assert scan["complete"] and scan["duration_s"] > 3.0 and scan["samples_used"] > 50
    # The sim follower holds the probe off by a constant offset (plus lag and tremor): the
    # mean error is about that offset, centering removes it, and the RMSE is of its size.
    cfg = SimHumanConfig()
    offset_mm = math.dist(cfg.offset_mm, (0.0, 0.0, 0.0))  # 6.0 mm
    offset_deg = math.dist(cfg.offset_rotation_deg, (0.0, 0.0, 0.0))  # 5.9 deg
    mean_mm = math.dist(scan["mean_position_error_mm"], (0.0, 0.0, 0.0))
    assert 0.5 * offset_mm < mean_mm < 2.0 * offset_mm
    assert 0.5 * offset_deg < scan["mean_rotation_error_deg"] < 2.0 * offset_deg
    assert scan["centered_position_rmse_mm"] < scan["position_rmse_mm"] < 4.0 * offset_mm
    assert scan["position_rmse_mm"] > offset_mm * 0.8
    assert scan["centered_orientation_rmse_deg"] < scan["orientation_rmse_deg"] < 3 * offset_deg


def test_status_line_and_summary_report_a_failed_recording():
    ok = {"scan": 1, "scans_started": 1, "recording": {"error": None, "dropped": 0}}
    bad = {"recording": {"error": "OSError: [Errno 28] No space left on device", "dropped": 9}}
    assert status_line(ok, {"recording": ok["recording"]}, 5.0).endswith("scan 1, recording")
    assert status_line(ok, bad, 5.0).endswith("scan 1, recording FAILED")
    assert "recording" not in status_line({}, {}, 5.0)
    s = summarize(ok, bad, 5.0, {"expert": 0, "follower": 0})
    assert s["scans"] == 1 and s["recording"]["follower"]["dropped"] == 9
    assert summarize({}, {}, 5.0, {})["recording"] is None

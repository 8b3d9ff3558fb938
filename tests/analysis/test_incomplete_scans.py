"""A scan whose end is unknown (no stop event; or no scan events at all in a cut expert
recording) is marked incomplete, said so, and left out of the tables and the mean ± SD
(issue 20 item 5: an expert recording cut at 50 % was analysed as a complete scan 0)."""

from __future__ import annotations

import json

import pytest

from humantele.analysis.report import analyze, format_report
from humantele.cli import main
from humantele.recording.synthetic import SyntheticSession, write_synthetic


def _pair(tmp_path, **kw):
    e, f = tmp_path / "e.mcap", tmp_path / "f.mcap"
    cfg = SyntheticSession(duration_s=30.0, offset_mm=(10.0, 0.0, 0.0), lag_s=0.3, **kw)
    write_synthetic(e, cfg, follower_path=f)
    return e, f


def _cut(path, share: float):
    data = path.read_bytes()
    cut = path.with_name("cut-" + path.name)
    cut.write_bytes(data[: int(len(data) * share)])
    return cut


def test_a_cut_expert_recording_without_scan_events_is_not_a_complete_scan_0(tmp_path, capsys):
    e, f = _pair(tmp_path, n_scans=1, record_scan_events=False)
    whole, _ = analyze([e, f])  # intact, no events: the whole session is scan 0, complete
    assert [(s["scan"], s["complete"]) for s in whole["scans"]] == [(0, True)]
    assert whole["summary"]["position_rmse_mm"]["n"] == 1
    cut = _cut(e, 0.5)
    report, _ = analyze([cut, f])
    (scan,) = report["scans"]
    assert scan["scan"] == 0 and not scan["complete"]
    assert "expert's recording is cut" in scan["incomplete_reason"]
    assert report["summary"]["position_rmse_mm"] == {"mean": None, "sd": None, "n": 0}
    assert report["incomplete_scans"] == [
        {"session": "sim0001", "scan": 0, "reason": scan["incomplete_reason"]}
    ]
    text = format_report(report)
    assert "no complete scan" in text and "left out of the tables" in text
    assert "| 0 |" not in text  # not a row of the table
    # The command line says the same.
    assert main(["analyze", str(cut), str(f)]) == 0
    assert "Incomplete scans, left out of the tables" in capsys.readouterr().out


def test_a_scan_without_stop_is_reported_but_not_in_the_table_or_the_mean(tmp_path, capsys):
    e, f = _pair(tmp_path, n_scans=3)
    cut = _cut(e, 0.85)  # scans 1 and 2 whole, scan 3 started and cut
    report, _ = analyze([cut, f])
    done = [s for s in report["scans"] if s["complete"]]
    open_ = [s for s in report["scans"] if not s["complete"]]
    assert [s["scan"] for s in done] == [1, 2] and [s["scan"] for s in open_] == [3]
    assert "no stop event" in open_[0]["incomplete_reason"]
    summary = report["summary"]["position_rmse_mm"]
    assert summary["n"] == 2
    assert summary["mean"] == pytest.approx(sum(s["position_rmse_mm"] for s in done) / 2)
    assert main(["analyze", str(cut), str(f), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["incomplete_scans"][0]["scan"] == 3
    text = format_report(report)
    table = text.split("Incomplete scans")[0]
    assert "| 1 |" in table and "| 2 |" in table and "| 3 |" not in table
    assert "- scan 3 of session sim0001: no stop event" in text

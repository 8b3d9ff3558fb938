"""`humantele analyze`: the table, the JSON, the figures, errors and truncated recordings."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from humantele.cli import main
from humantele.recording.synthetic import SyntheticSession, write_synthetic

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
KEYS = (
    "position_rmse_mm",
    "centered_position_rmse_mm",
    "orientation_rmse_deg",
    "centered_orientation_rmse_deg",
)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "session.mcap"
    cfg = SyntheticSession(
        duration_s=36.0,
        n_scans=11,
        offset_mm=(12.0, 0.0, 0.0),
        lag_s=0.3,
        tremor_mm=1.0,
        dropout=0.05,
        clock_offset_s=0.8,
    )
    write_synthetic(path, cfg)
    return path


def test_json_has_the_papers_table_and_summary(recording, capsys):
    assert main(["analyze", str(recording), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert [s["scan"] for s in report["scans"]] == list(range(1, 12))
    for s in report["scans"]:
        for k in KEYS:
            assert s[k] > 0
        assert s["centered_position_rmse_mm"] < s["position_rmse_mm"]
        assert s["follower_id"] == "F01" and s["sonographer_id"] == "S1"
    for k in KEYS:
        values = [s[k] for s in report["scans"]]
        assert report["summary"][k]["mean"] == pytest.approx(sum(values) / len(values))
        assert report["summary"][k]["sd"] > 0 and report["summary"][k]["n"] == 11


def test_text_table_scores_questionnaires_and_plots(recording, tmp_path, capsys):
    plots = tmp_path / "figs"
    code = main(
        [
            "analyze",
            str(recording),
            "--scores",
            str(EXAMPLES / "scores.csv"),
            "--tlx",
            str(EXAMPLES / "nasa_tlx.csv"),
            "--usability",
            str(EXAMPLES / "usability.csv"),
            "--exclude-scans",
            "1,2",
            "--plots",
            str(plots),
        ]
    )
    out = capsys.readouterr().out
    assert code == 0
    assert "| Scan | Position RMSE (mm) | Centered Position RMSE (mm) |" in out
    assert "| Mean ± SD |" in out
    assert "Spearman quality vs Position RMSE (mm): rho" in out and "n = 11" in out
    assert "without excluded scans" in out and "Raw TLX" in out and "cumbersome" in out
    names = {p.name for p in plots.iterdir()}
    assert {
        "quality_scores.png",
        "quality_scores_excluded.png",
        "nasa_tlx.png",
        "usability.png",
        "sim0001_scan1_position.png",
        "sim0001_scan11_orientation.png",
    } <= names
    assert all((plots / n).stat().st_size > 5000 for n in names)


def test_spearman_in_json(recording, capsys):
    main(["analyze", str(recording), "--json", "--scores", str(EXAMPLES / "scores.csv")])
    q = json.loads(capsys.readouterr().out)["quality"]
    sp = q["spearman"]["position_rmse_mm"]
    assert sp["n"] == 11 and -1 <= sp["rho"] <= 1 and 0 <= sp["p"] <= 1


def test_truncated_recording_is_analysed_with_a_warning(recording, tmp_path, capsys):
    data = recording.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    assert main(["analyze", str(cut), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert 3 <= len(report["scans"]) < 11
    assert any("no footer" in w or "stopped early" in w for w in report["warnings"])


def test_errors_are_clear_exit_codes(tmp_path, capsys):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    assert main(["analyze", str(junk)]) == 2
    assert "not an MCAP recording" in capsys.readouterr().err
    assert main(["analyze"]) == 2
    bad = tmp_path / "bad.csv"
    bad.write_text("scan,target,R1\n1,aorta,9\n")
    assert main(["analyze", "--scores", str(bad)]) == 2
    assert "row 2: column 'R1'" in capsys.readouterr().err


def test_sim_image_quality_is_the_per_scan_quality_when_recorded(tmp_path, capsys):
    path = tmp_path / "simq.mcap"
    qualities = [0.1, 0.7, 0.4, 0.9]
    write_synthetic(
        path,
        SyntheticSession(
            duration_s=20.0,
            n_scans=4,
            offset_mm=(5.0, 0.0, 0.0),
            tremor_mm=1.0,
            us_quality=qualities,
            expert_rate_hz=200.0,  # the virtual probe's rate: nothing here depends on it
        ),  # fmt: skip
    )
    assert main(["analyze", str(path), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    got = [s["sim_image_quality"] for s in report["scans"]]
    assert got == pytest.approx(qualities)
    assert all(s["sim_image_quality_frames"] > 20 for s in report["scans"])
    q = report["quality"]
    assert q["source"] == "sim" and q["scan_quality"] == {
        str(s["scan"]): s["sim_image_quality"] for s in report["scans"]
    }
    assert q["spearman"]["position_rmse_mm"]["n"] == 4
    assert main(["analyze", str(path)]) == 0
    text = capsys.readouterr().out
    assert "sim ultrasound" in text and "in place of rater scores" in text
    assert "scan 2: 0.70" in text


def test_without_video_frames_there_is_no_sim_quality(recording, capsys):
    assert main(["analyze", str(recording), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert "quality" not in report
    assert all(s["sim_image_quality"] is None for s in report["scans"])

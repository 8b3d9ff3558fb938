"""`humantele bench video`: sources (one JSON line last, its section), the link's phases, quality
on the live link."""

import json

import pytest

from humantele.bench import video as bench_video
from humantele.cli import main


def test_bench_video_sources(tmp_path, monkeypatch, capsys):
    md = tmp_path / "benchmarks.md"
    md.write_text("# Benchmarks\n\n<!-- bench:loop -->\nloop figures\n<!-- /bench:loop -->\n")
    monkeypatch.setattr(bench_video, "BENCHMARKS_MD", md)
    monkeypatch.setattr(bench_video, "US_SIZES", [(320, 240)])
    monkeypatch.setattr(bench_video, "POV_SIZES", [(320, 180)])
    monkeypatch.setattr(bench_video, "BIT_RATES", [250_000])
    assert main(["bench", "video", "sources", "--frames", "6", "--json"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    r = json.loads(lines[0])
    assert r["part"] == "sources" and r["frames"] == 6
    for key in ("us 320x240", "pov 320x180"):
        assert 0.0 < r["render"][key]["median_ms"] <= r["render"][key]["p90_ms"]
        assert r["render"][key]["cpu_ms"] > 0.0
    for key in ("us 250000", "pov 250000"):
        c = r["vp8"][key]
        assert c["decoded"] == 6 and c["read_exact_pct"] == 100.0
        assert 15.0 < c["psnr_db"] < 60.0 and 0.0 < c["ssim"] <= 1.0
    text = md.read_text()
    assert "## Video sources" in text and "loop figures" in text
    assert "| sim us | 320x240 |" in text


def test_bench_video_render_prints_the_cost_per_frame_and_writes_nothing(
    tmp_path, monkeypatch, capsys
):
    md = tmp_path / "benchmarks.md"
    md.write_text("# Benchmarks\n")
    monkeypatch.setattr(bench_video, "BENCHMARKS_MD", md)
    assert main(["bench", "video", "render", "--frames", "5"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("render us ") and "CPU" in lines[0] and "per frame" in lines[0]
    r = json.loads(lines[-1])
    assert r["part"] == "render" and r["frames"] == 5
    for key in ("us 640x480", "pov 960x540"):
        f = r["render"][key]
        assert 0.0 < f["median_ms"] <= f["p90_ms"] and f["cpu_ms"] > 0.0
    assert md.read_text() == "# Benchmarks\n"


def test_phase_figures_split_a_run_at_the_loss_window():
    from humantele.bench.video_link import phase_figures

    # 20 fps; frames 50 ms old, except 1.5 s of 0.5 s old frames and a 1 s freeze in between
    t = [i * 0.05 for i in range(100)] + [6.0 + i * 0.05 for i in range(30)]
    ages = [0.05] * 100 + [0.5] * 30
    before = phase_figures(t, ages, 0.0, 5.0)
    assert before["frames"] == 100 and before["fps"] == 20.0
    assert before["age_p50_ms"] == before["age_max_ms"] == 50.0
    during = phase_figures(t, ages, 5.0, 7.5)
    assert during["frames"] == 30 and during["age_p95_ms"] == 500.0
    assert during["gap_max_ms"] == 1000  # 5.0 s (start) to 6.0 s, the first frame in it
    empty = phase_figures(t, [float("nan")] * len(t), 8.0, 9.0)
    assert empty["frames"] == 0 and empty["age_p50_ms"] is None and empty["gap_max_ms"] == 1000


def test_link_section_keeps_other_rows_and_its_recovery_table(tmp_path):
    from humantele.bench import video_link as vl
    from humantele.report import section_rows, write_section

    md = tmp_path / "benchmarks.md"
    row = ["a setting", *["x"] * (len(vl.HEADER) - 1)]
    phase = ["a setting", "during", *["y"] * (len(vl.PHASE_HEADER) - 2)]
    write_section(vl.SECTION, vl.markdown([row], [phase]), md)
    assert section_rows(vl.SECTION, len(vl.HEADER), md) == [row]
    assert section_rows(vl.SECTION, len(vl.PHASE_HEADER), md) == [phase]


@pytest.mark.slow
def test_bench_video_quality_on_the_live_link(tmp_path, monkeypatch, capsys):
    """One small point: the decoded US frames are compared with their sources."""
    from humantele.bench import video_quality

    md = tmp_path / "benchmarks.md"
    monkeypatch.setattr(video_quality, "BENCHMARKS_MD", md)
    monkeypatch.setattr(video_quality, "CHART", tmp_path / "img" / "chart.png")
    args = ["bench", "video", "quality", "--seconds", "4", "--sizes", "320x240", "--rates", "400"]
    assert main([*args, "--json"]) == 0
    r = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    (p,) = r["points"]
    assert p["size"] == "320x240" and p["kbps_set"] == 400 and p["compared"] >= 2
    assert 0.3 < p["ssim"] <= 1.0 and 20.0 < p["psnr_db"] < 60.0
    assert 0.0 < p["age_p50_ms"] <= p["age_p95_ms"]
    assert 0 < p["kbps_sent"] < 2 * 400
    assert (tmp_path / "img" / "chart.png").stat().st_size > 10_000
    assert "## Video: speed against quality" in md.read_text()


def test_a_thin_link_row_is_named_for_its_rate():
    import argparse

    from humantele.bench import video_link as vl

    p = argparse.ArgumentParser()
    vl.add_link_arguments(p)
    args = p.parse_args(["--delay-ms", "60", "--jitter-ms", "20", "--loss", "3", "--kbps", "1500"])
    assert "TURN +60±20 ms, 1500 kbit/s, 3 % loss" in vl.label(args)
    assert "kbit/s," not in vl.label(p.parse_args(["--turn"]))  # uncapped: no rate named

"""`humantele bench video sources`: prints one JSON line last and writes its section."""

import json

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
    for key in ("us 250000", "pov 250000"):
        c = r["vp8"][key]
        assert c["decoded"] == 6 and c["read_exact_pct"] == 100.0
        assert 15.0 < c["psnr_db"] < 60.0 and 0.0 < c["ssim"] <= 1.0
    text = md.read_text()
    assert "## Video sources" in text and "loop figures" in text
    assert "| sim us | 320x240 |" in text

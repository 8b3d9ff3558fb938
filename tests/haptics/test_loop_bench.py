"""`humantele bench loop`: runs the servo, prints one JSON line last, writes its section."""

import json

from humantele.bench import loop as bench_loop
from humantele.cli import main


def test_bench_loop_prints_json_last_and_keeps_the_other_row(tmp_path, monkeypatch, capsys):
    md = tmp_path / "benchmarks.md"
    monkeypatch.setattr(bench_loop, "BENCHMARKS_MD", md)
    assert main(["bench", "loop", "--seconds", "0.5", "--load"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    r = json.loads(last)
    for key in ("rate_hz", "period_p50_us", "period_p99_us", "period_max_us", "overruns"):
        assert key in r
    assert r["load"] is True and r["ticks"] > 0 and r["period_max_us"] >= r["period_p50_us"]
    floor = r["floor"]  # the bare timing loop measured under the same load
    assert 900.0 < floor["rate_hz"] < 1100.0 and floor["period_max_us"] >= floor["period_p99_us"]
    assert main(["bench", "loop", "--seconds", "0.3", "--json"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["load"] is False
    text = md.read_text()
    assert "| idle |" in text and "| one core busy |" in text  # each run kept the other's row

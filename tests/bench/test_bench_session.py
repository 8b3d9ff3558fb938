import json

import pytest

from humantele.cli import main


@pytest.mark.slow
def test_bench_session_runs_two_processes_and_prints_json(capsys):
    assert (
        main(["bench", "session", "--seconds", "1", "--rate", "200", "--json", "--no-write"]) == 0
    )
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["attempted"] >= 150  # ~200 poses in 1 s
    assert summary["delivered_pct"] > 90.0  # loopback; generous for a busy machine
    assert summary["pose_age_ms"]["n"] == summary["received"]
    assert summary["pose_age_ms"]["p50"] >= 0.0
    assert abs(summary["offset_us"]) < 5000  # one machine: the true offset is ~0
    assert summary["cpu_expert_pct"] > 0 and summary["cpu_follower_pct"] > 0

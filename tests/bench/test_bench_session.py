import json

import pytest

from humantele.cli import main


@pytest.mark.slow
@pytest.mark.whole_session  # one at a time across the lanes (tests/session_slot.py)
def test_bench_session_runs_two_processes_and_prints_json(capsys):
    assert (
        main(["bench", "session", "--seconds", "1", "--rate", "200", "--json", "--no-write"]) == 0
    )
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # ~200 ticks in 1 s: a pose sent on each, or the tick counted as skipped when it came too
    # late (the pacer's rule on a busy machine; the count of sends alone depends on the load)
    assert summary["attempted"] > 0 and summary["attempted"] + summary["pacer_skipped"] >= 150
    assert summary["delivered_pct"] > 90.0  # loopback; generous for a busy machine
    assert summary["pose_age_ms"]["n"] == summary["received"]
    assert summary["pose_age_ms"]["p50"] >= 0.0
    # one machine: the true offset is 0, found within half the sync's round trip (NTP's bound)
    assert abs(summary["offset_us"]) <= summary["rtt_ms"] * 1e3 / 2
    assert summary["cpu_expert_pct"] > 0 and summary["cpu_follower_pct"] > 0

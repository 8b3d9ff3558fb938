"""``humantele demo`` end to end: --json summary fields; a terminal's Ctrl-C ends everything
cleanly (SIGTERM: test_demo_supervision.py)."""

import time

import pytest
from session_helpers import pid_alive

from humantele.demo_report import summarize
from humantele.runtime.stats import percentile_ms


@pytest.mark.slow
def test_demo_json_and_ctrl_c_leave_no_process(demo_run):
    """The shared demo run (session_helpers.demo_run): Ctrl-C once calibrated and scanning."""
    seen, status = demo_run.seen, demo_run.status
    assert len(seen) >= 3, (seen, status)
    assert demo_run.returncode == 0, demo_run.err[-2000:]
    assert demo_run.stop_s < 20  # Ctrl-C ended it, not --duration
    summary = demo_run.summary
    for key in ("poses_sent", "poses_received", "pose_age_p50_ms", "pose_age_p99_ms",
                "servo_rate_hz", "servo_overruns", "calibrated", "dropped_messages",
                "cpu_percent_expert", "cpu_percent_follower"):  # fmt: skip
        assert key in summary, key
    assert summary["exit_codes"] == {"expert": 0, "follower": 0}
    assert 0 < summary["poses_received"] <= summary["poses_sent"]
    assert 0 <= summary["pose_age_p50_ms"] <= summary["pose_age_p99_ms"] < 5000
    assert summary["servo_rate_hz"] > 500 and summary["servo_overruns"] >= 0
    assert summary["calibrated"] is True and summary["model_installed"] is True
    assert summary["dropped_messages"] >= 0
    assert 0 < summary["cpu_percent_expert"] < 200 and 0 < summary["cpu_percent_follower"] < 200
    for _ in range(50):
        if not any(pid_alive(p) for p in seen):
            break
        time.sleep(0.1)
    assert not [p for p in seen if pid_alive(p)]


@pytest.mark.slow
def test_ctrl_c_to_the_process_group_stops_the_demo_with_exit_0(demo_run):
    """A terminal's Ctrl-C: SIGINT to the demo, both daemons and the servo at once."""
    assert demo_run.returncode == 0, "".join(demo_run.status[-5:]) + demo_run.err[-3000:]
    summary = demo_run.summary
    assert summary["exit_codes"] == {"expert": 0, "follower": 0}, summary
    assert summary["servo_restarts"] == 0 and summary["servo_state"] == "stopped"
    assert "Traceback" not in demo_run.err and "KeyboardInterrupt" not in demo_run.err


def test_summary_sums_and_percentiles():
    e = {"poses_sent": 10, "dropped_total": 2, "servo_rate_hz": 999.0, "cpu_percent": 5.0}
    f = {"poses_received": 9, "dropped_total": 3, "calibrated": True, "pose_age_p50_ms": 4.0}
    s = summarize(e, f, 3.0, {"expert": 0, "follower": 0})
    assert s["dropped_messages"] == 5 and s["calibrated"] is True and s["poses_received"] == 9
    assert percentile_ms([0.001, 0.002, 0.003, 0.1], 50) in (2.0, 3.0)
    assert percentile_ms([0.001, 0.002, 0.003, 0.1], 99) == 100.0
    assert percentile_ms([], 50) is None

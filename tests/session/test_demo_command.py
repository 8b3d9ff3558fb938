"""``humantele demo`` end to end: --json summary fields, SIGTERM ends everything cleanly."""

import asyncio
import json
import os
import signal
import sys
import time
from pathlib import Path

import pytest
from session_helpers import pid_alive

from humantele.demo import summarize
from humantele.runtime.stats import percentile_ms


def descendants(pid: int) -> set[int]:
    """All live descendants of ``pid`` (from /proc)."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            if c not in out:
                out.add(c)
                todo.append(c)
    return out


@pytest.mark.slow
async def test_demo_json_and_sigterm_leave_no_process():
    env = dict(os.environ)
    env.pop("HUMANTELE_TOKEN", None)
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "humantele", "demo", "--duration", "120", "--json",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=env,
    )  # fmt: skip
    seen: set[int] = set()
    status = []
    t_end = time.monotonic() + 60.0  # generous: a busy machine
    while time.monotonic() < t_end:
        # The status line (stderr with --json) says when the calibration is done.
        line = (await asyncio.wait_for(proc.stderr.readline(), 60.0)).decode()
        assert line, "demo ended early"
        status.append(line)
        seen |= descendants(proc.pid)  # expert, follower, the servo process
        if ", calibrated |" in line and "link connected" in line:
            break
    assert len(seen) >= 3, (seen, status)
    t_term = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    out, err = await asyncio.wait_for(proc.communicate(), 30)
    assert proc.returncode == 0, "".join(status) + err.decode()[-2000:]
    assert time.monotonic() - t_term < 20  # SIGTERM ended it, not --duration
    lines = out.decode().strip().splitlines()
    summary = json.loads(lines[-1])
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
        await asyncio.sleep(0.1)
    assert not [p for p in seen if pid_alive(p)]


def test_summary_sums_and_percentiles():
    e = {"poses_sent": 10, "dropped_total": 2, "servo_rate_hz": 999.0, "cpu_percent": 5.0}
    f = {"poses_received": 9, "dropped_total": 3, "calibrated": True, "pose_age_p50_ms": 4.0}
    s = summarize(e, f, 3.0, {"expert": 0, "follower": 0})
    assert s["dropped_messages"] == 5 and s["calibrated"] is True and s["poses_received"] == 9
    assert percentile_ms([0.001, 0.002, 0.003, 0.1], 50) in (2.0, 3.0)
    assert percentile_ms([0.001, 0.002, 0.003, 0.1], 99) == 100.0
    assert percentile_ms([], 50) is None

"""Recording by the real daemon processes: SIGKILL keeps all but the last moments, an unusable
path stops a daemon at start with a clear message (exit code 2)."""

import asyncio
import sys
import time

import pytest

from humantele.analysis.report import analyze
from humantele.recording import read_recording, role_path


async def run_cli(*args: str) -> tuple[int, str]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "humantele", *args,
        stdin=asyncio.subprocess.DEVNULL, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    return proc.returncode, (out + err).decode()


@pytest.mark.e2e  # starts a daemon (the fast lane leaves it out)
async def test_an_unusable_recording_path_is_a_clear_error_at_start(tmp_path):
    existing = tmp_path / "s.follower.mcap"
    existing.write_bytes(b"an earlier session")
    missing, exists, named = await asyncio.gather(  # three daemons at once: one start-up wait
        run_cli("expert", "--record", str(tmp_path / "missing" / "s.mcap")),
        run_cli("follower", "--state-dir", str(tmp_path), "--record", str(existing)),
        run_cli("follower", "--record", "x.mcap", "--follower-id", "Jane Doe"),
    )
    code, text = missing
    assert code == 2 and "no directory" in text and "Traceback" not in text
    code, text = exists
    assert code == 2 and "exists" in text and "Traceback" not in text
    assert existing.read_bytes() == b"an earlier session"  # never overwritten
    code, text = named
    assert code == 2 and "not a pseudonymous id" in text


@pytest.mark.slow
async def test_sigkill_of_the_expert_keeps_its_recording_to_half_a_second(session, tmp_path):
    base = tmp_path / "k.mcap"
    paths = {role: role_path(base, role) for role in ("expert", "follower")}

    def rec_args(role):
        return ["--record", str(paths[role]), "--session-id", "k01",
                "--follower-id", "F1", "--sonographer-id", "S1"]  # fmt: skip

    session.save_calibration()  # calibrating: tests/browser/test_headset_session.py
    await session.start("follower", *rec_args("follower"))
    await session.start("expert", *rec_args("expert"))
    await session.wait(
        "calibration, model and a scan",
        lambda e, f: f.get("calibrated") and e.get("scan") == 1 and f.get("scan") == 1,
        timeout=90,
    )
    # A scan long enough to analyse: the follower measures ~45 tracker images a second.
    frames = session.stats("follower")["measurements"] + 60
    await session.wait("a scan to analyse", lambda e, f: f["measurements"] >= frames)
    # What the expert had on disk at its last stats write before the kill (fsync'ed).
    uptime = session.stats("expert")["uptime_s"]
    await session.wait("expert stats", lambda e, f: e.get("uptime_s", 0) > uptime)
    flushed = session.stats("expert")["recording"]["written"]
    t_kill = time.monotonic()  # the daemons' clock (CLOCK_MONOTONIC is system-wide)
    await session.kill("expert")
    await session.wait("follower notices", lambda e, f: f.get("link_state") != "connected")
    assert await session.terminate("follower") == 0

    expert = read_recording(paths["expert"])
    assert not expert.complete  # killed: no footer, read all the same
    t = expert.times("/expert/pose")
    assert t[-1] >= t_kill - 0.5, f"lost {t_kill - t[-1]:.3f} s before the kill"
    # And nothing missing before that: every sample it had written is read back. (Gaps in
    # time are no measure of that: a starved expert publishes nothing for a while.)
    assert sum(expert.count(topic) for topic in expert.topics) >= flushed > 100
    assert expert.count("/expert/force") == len(t)
    assert [s["event"] for s in expert.samples("/expert/scan")] == ["start"]
    follower = read_recording(paths["follower"])
    assert follower.complete and follower.session["session_id"] == "k01"
    assert follower.count("/follower/probe_pose") > 20

    report, _ = analyze([paths["expert"], paths["follower"]])
    (scan,) = report["scans"]
    assert scan["scan"] == 1 and not scan["complete"]  # the kill ended it
    assert scan["follower_id"] == "F1" and scan["samples_used"] > 20
    assert report["sessions"][0]["clock"]["estimates"] > 0
    assert any("no stop" in w for w in report["warnings"])

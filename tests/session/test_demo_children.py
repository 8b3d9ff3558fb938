"""The follower's children killed during a demo with video (issue 20 §2): a SIGKILLed video
process is restarted, with a log line, and the status line and ``--json`` say so; a killed
sensing process is restarted and its time without measurements is counted; Ctrl-C exits 0
also while the new child starts; nothing is left running and nothing leaks (the
multiprocessing resource tracker reports leaked shared memory and semaphores in the log)."""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from session_helpers import descendants, pid_alive

from humantele.demo_status import poses_flowing

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.e2e, pytest.mark.slow]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("HUMANTELE_TOKEN", None)
    return env


def _children(parent: int) -> dict[int, tuple[str, str]]:
    """Live children of ``parent``: pid -> (comm, cmdline)."""
    out = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            stat = Path(f"/proc/{d}/stat").read_text()
            comm = Path(f"/proc/{d}/comm").read_text().strip()
            cmd = Path(f"/proc/{d}/cmdline").read_text().replace("\0", " ")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == parent and pid_alive(int(d)):
            out[int(d)] = (comm, cmd)
    return out


def _daemon(demo: int, role: str) -> int | None:
    return next((p for p, (_, cmd) in _children(demo).items() if f" {role} " in cmd), None)


def _victim(demo: int, comm: str) -> int | None:
    d = _daemon(demo, "expert" if comm == "humantele-servo" else "follower")
    if d is None:
        return None
    return next((p for p, (c, _) in _children(d).items() if c == comm), None)


@pytest.mark.parametrize(
    ("comm", "stop_when"),
    [
        ("humantele-video", "back"),  # restarted, frames again, then Ctrl-C
        ("humantele-video", "restarting"),  # Ctrl-C while the new one starts
        ("humantele-sensi", "back"),  # the sensing process: restarted, its gap counted
        ("humantele-sensi", "restarting"),
        ("humantele-servo", "back"),  # the expert's servo
        ("humantele-servo", "restarting"),
    ],
)
def test_a_killed_follower_child_is_restarted_and_ctrl_c_exits_0(comm, stop_when):
    track = {"humantele-video": "video", "humantele-sensi": "sensing"}.get(comm, "servo")
    proc = subprocess.Popen(
        [sys.executable, "-m", "humantele", "demo", "--config", "configs/demo.toml",
         "--duration", "900", "--json", "--keep"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(),
        start_new_session=True,
    )  # fmt: skip
    lines: list[str] = []
    seen: set[int] = set()
    killed = new = None
    saw_down = False
    good = 0
    try:
        t_end = time.monotonic() + 600.0  # generous: a loaded 2-core machine starts slowly
        while time.monotonic() < t_end:
            line = proc.stderr.readline()
            assert line, "demo ended early:\n" + "".join(lines[-10:])
            lines.append(line)
            seen |= descendants(proc.pid)
            flowing = poses_flowing(line)
            if killed is None:
                # (the sensing measuring: its time without measurements counts from its first)
                measuring = flowing and "starting the tracker" not in line
                victim = _victim(proc.pid, comm) if measuring else None
                if victim is not None:
                    killed = victim
                    os.kill(killed, signal.SIGKILL)
                continue
            down = f"{track} DOWN" in line or f"{track} restarting" in line
            down = down or (track == "servo" and "servo - Hz" in line)  # no rate: not running
            saw_down = saw_down or down
            current = _victim(proc.pid, comm)
            # (the sensing process is restarted at once, without a back-off: its new process
            # may be there before a status line could say "restarting"; Ctrl-C then lands while
            # it starts)
            if stop_when == "restarting" and (down or current not in (None, killed)):
                break
            if stop_when == "back" and current not in (None, killed) and not down and flowing:
                new = current
                good += 1
                if good >= 2:  # two status lines with the new one running
                    break
            else:
                good = 0
        else:
            pytest.fail(f"{track} process did not come back:\n" + "".join(lines[-10:]))
        seen |= descendants(proc.pid)
        os.killpg(proc.pid, signal.SIGINT)  # a terminal's Ctrl-C: the whole group
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    text = "".join(lines) + err
    assert proc.returncode == 0, text[-4000:]
    assert saw_down or stop_when == "back" or track == "sensing", "".join(lines[-10:])
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["exit_codes"] == {"expert": 0, "follower": 0}, summary
    assert summary["restarts"] == {"expert": 0, "follower": 0}  # the child, not the daemon
    child = summary["children"][track]
    if stop_when == "back":
        assert new is not None and child["restarts"] == 1, summary["children"]
    if track == "sensing" and stop_when == "back":
        assert summary["children"]["sensing"]["measurement_gaps"] >= 1
        assert summary["children"]["sensing"]["measurement_gap_s"] > 0.5
    run_dir = Path(re.search(r"run directory: (\S+)", err).group(1))
    log = (run_dir / ("expert.log" if track == "servo" else "follower.log")).read_text()
    said = {
        "video": "video process exited with code -9; restarting it in 1 s",
        "sensing": "the sensing process exited (code -9); restarting it",
        "servo": "servo process exited with code -9; restarting it in 2 s",
    }[track]
    assert said in log, log[-3000:]
    assert "leaked" not in log and "Traceback" not in log, log[-3000:]
    for _ in range(100):
        if not any(pid_alive(p) for p in seen):
            break
        time.sleep(0.1)
    assert not [p for p in seen if pid_alive(p)]
    shutil.rmtree(run_dir, ignore_errors=True)

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
from pathlib import Path

import pytest
from session_helpers import DemoLines

from humantele.demo_status import poses_flowing
from procgroups import children, descendants

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.whole_session]


def _victim(demo: DemoLines, comm: str) -> int | None:
    """The demo's child process ``comm`` (the servo's under the expert, the others under the
    follower)."""
    d = demo.daemon("expert" if comm == "humantele-servo" else "follower")
    if d is None:
        return None
    return next((p for p, (c, _) in children(d).items() if c == comm), None)


TRACKS = {"humantele-video": "video", "humantele-sensi": "sensing", "humantele-servo": "servo"}
SAID = {  # the owner's log line on noticing the kill
    "video": "video process exited with code -9; restarting it in 1 s",
    "sensing": "sensing process exited with code -9; restarting it in 0.5 s",
    "servo": "servo process exited with code -9; restarting it in 2 s",
}


def _down(track: str, line: str) -> bool:
    """The status line says ``track``'s child is not running."""
    down = f"{track} DOWN" in line or f"{track} restarting" in line
    return down or (track == "servo" and "servo - Hz" in line)  # no rate: not running


class Demo(DemoLines):
    """``humantele demo --json --keep`` with video, read status line by status line."""

    def __init__(self) -> None:
        super().__init__("--config", "configs/demo.toml", "--duration", "900", "--json", "--keep")

    def kill_when_measuring(self, comms: tuple[str, ...]) -> dict[str, int]:
        """SIGKILL the children ``comms``, together, once poses flow, the sensing measures
        (its time without measurements counts from its first) and all are running; their
        pids."""
        while True:
            line = self.line()
            if poses_flowing(line) and "starting the tracker" not in line:
                victims = {comm: _victim(self, comm) for comm in comms}
                if None not in victims.values():
                    for victim in victims.values():
                        os.kill(victim, signal.SIGKILL)
                    return victims

    def ctrl_c(self) -> tuple[dict, str, str]:
        """A terminal's Ctrl-C (the whole group); the ``--json`` summary, the whole stderr
        and the daemons' logs (expert then follower)."""
        try:
            self.seen |= descendants(self.proc.pid)
            os.killpg(self.proc.pid, signal.SIGINT)
            out, err = self.proc.communicate(timeout=120)
        finally:
            self.kill()
        text = "".join(self.lines) + err
        assert self.proc.returncode == 0, text[-4000:]
        summary = json.loads(out.strip().splitlines()[-1])
        assert summary["exit_codes"] == {"expert": 0, "follower": 0}, summary
        assert summary["restarts"] == {"expert": 0, "follower": 0}  # the child, not the daemon
        self.run_dir = Path(re.search(r"run directory: (\S+)", err).group(1))
        logs = {r: (self.run_dir / f"{r}.log").read_text() for r in ("expert", "follower")}
        for log in logs.values():
            assert "leaked" not in log and "Traceback" not in log, log[-3000:]
        assert not self.left_running()
        return summary, text, logs

    def close(self) -> None:
        self.kill()
        if getattr(self, "run_dir", None):
            shutil.rmtree(self.run_dir, ignore_errors=True)


def _log_of(logs: dict[str, str], track: str) -> str:
    return logs["expert" if track == "servo" else "follower"]


def test_killed_children_come_back_then_ctrl_c_while_all_three_restart_exits_0():
    """One demo. The video, sensing and servo processes SIGKILLed together once poses flow:
    each restarted (the new one running through two status lines with poses flowing; each
    on its own back-off), said in its daemon's log; the sensing's gap counted. Then the three
    SIGKILLed at once again, and Ctrl-C once the video's and the servo's are being replaced
    (a status line says so, or the new process is there; their back-offs have doubled): exit
    0, nothing left running, each death said in its daemon's log. (Killed one after the
    other, each once the one before was back, the first round took 21 s of the demo, not 10:
    each child's own restart is the same either way, and the daemons' tests kill each alone.)"""
    demo = Demo()
    try:
        killed = demo.kill_when_measuring(tuple(TRACKS))
        good = dict.fromkeys(TRACKS, 0)
        while min(good.values()) < 2:  # two status lines with each new one running
            line = demo.line()
            for comm, track in TRACKS.items():
                current = _victim(demo, comm)
                back = current not in (None, killed[comm]) and not _down(track, line)
                good[comm] = good[comm] + 1 if back and poses_flowing(line) else 0
        killed = demo.kill_when_measuring(tuple(TRACKS))
        replacing: set[str] = set()
        while not {"humantele-video", "humantele-servo"} <= replacing:
            line = demo.line()
            for comm in ("humantele-video", "humantele-servo"):
                new = _victim(demo, comm) not in (None, killed[comm])
                if new or _down(TRACKS[comm], line):
                    replacing.add(comm)
        summary, _, logs = demo.ctrl_c()
    finally:
        demo.close()
    for track in TRACKS.values():
        log = _log_of(logs, track)
        assert SAID[track] in log, log[-3000:]  # the first death: the first back-off
        assert log.count(f"{track} process exited with code -9") == 2, log[-3000:]
        assert summary["children"][track]["restarts"] in (1, 2), summary["children"]
    assert summary["children"]["sensing"]["measurement_gaps"] >= 1
    assert summary["children"]["sensing"]["measurement_gap_s"] > 0.5

"""Helpers for tests that run the daemons as real OS processes over loopback WebRTC."""

import asyncio
import contextlib
import json
import math
import os
import re
import resource
import secrets
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from humantele.follower.calibration import CALIBRATION_FILE, build_calibration
from humantele.follower.sim_human import SimPatient
from humantele.recording import read_recording
from humantele.runtime.signal_child import signal_child
from humantele.signaling.server import SignalConfig, SignalingServer
from procgroups import daemon_of, descendants, pid_alive, resource_tracker
from session_slot import scaled, whole_session_slot

ROOT = Path(__file__).resolve().parents[2]
# The daemons' page credentials in these tests (the daemons take them from the environment).
PAIRING_CODE = "24681357"
CONSOLE_KEY = "test-console-key-" + secrets.token_urlsafe(8)


def read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


class Session:
    """A signaling server in the test process and daemons in their own processes."""

    def __init__(self, tmp: Path, server: SignalingServer, token: str) -> None:
        self.tmp = tmp
        self.server = server
        self.env = dict(
            os.environ, HUMANTELE_TOKEN=token, HUMANTELE_PARENT_PID=str(os.getpid()),
            HUMANTELE_PAIRING_CODE=PAIRING_CODE, HUMANTELE_CONSOLE_KEY=CONSOLE_KEY,
        )  # fmt: skip
        self.procs: dict[str, asyncio.subprocess.Process] = {}
        self.state_dir = tmp / "follower-state"
        self.runs = 0
        self.stopped: set[str] = set()
        self.fd_limit: int | None = None  # RLIMIT_NOFILE of the daemons started from now on

    def stats_path(self, role: str) -> Path:
        return self.tmp / f"{role}.json"

    def stats(self, role: str) -> dict:
        return read_json(self.stats_path(role))

    def save_calibration(self) -> None:
        """Save the calibration of the sim patient's true landmarks where the follower looks
        for it: it starts calibrated (no presses), for tests of what comes after calibrating."""
        build_calibration(SimPatient().landmarks()).save(self.state_dir / CALIBRATION_FILE)

    async def start(self, role: str, *extra: str) -> asyncio.subprocess.Process:
        self.runs += 1
        self.stats_path(role).unlink(missing_ok=True)
        args = [
            sys.executable,
            "-m",
            "humantele",
            role,
            "--signaling-url",
            self.server.url,
            "--room",
            "t",
            "--stats-file",
            str(self.stats_path(role)),
            "--log-level",
            "INFO",
        ]
        if role == "follower":
            args += ["--state-dir", str(self.state_dir), "--feed-port", "0"]
        log = open(self.tmp / f"{role}-{self.runs}.log", "wb")  # noqa: SIM115
        limit = self.fd_limit

        def lower_limit() -> None:
            if limit is not None:
                resource.setrlimit(resource.RLIMIT_NOFILE, (limit, limit))

        proc = await asyncio.create_subprocess_exec(
            *args, *extra, stdin=asyncio.subprocess.DEVNULL, stdout=log, stderr=log, env=self.env,
            preexec_fn=lower_limit if limit is not None else None,
        )  # fmt: skip
        log.close()
        self.procs[role] = proc
        self.stopped.discard(role)
        return proc

    async def wait(self, what: str, pred, timeout: float = 30.0) -> None:
        """Poll ``pred(expert stats, follower stats)`` until true; ``timeout`` (s) scaled to
        the machine's load (session_slot.time_scale): a bound on a failure, not a wait."""
        timeout = scaled(timeout)
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            e, f = self.stats("expert"), self.stats("follower")
            if pred(e, f):
                return
            died = [r for r, p in self.procs.items() if p.returncode is not None]
            if died and not set(died) <= self.stopped:
                break
            await asyncio.sleep(0.2)
        logs = {p.name: p.read_text()[-3000:] for p in sorted(self.tmp.glob("*.log"))}
        raise AssertionError(
            f"failed waiting for {what} ({timeout:.0f} s)\nexpert {self.stats('expert')}\n"
            f"follower {self.stats('follower')}\nlogs {logs}"
        )

    async def kill(self, role: str) -> None:
        proc = self.procs[role]
        self.stopped.add(role)
        signal_child(proc, signal.SIGKILL)
        await proc.wait()

    async def terminate(self, role: str, timeout: float = 15.0) -> int:
        proc = self.procs[role]
        self.stopped.add(role)
        signal_child(proc, signal.SIGTERM)  # (not send_signal: it may take the exit code)
        try:
            return await asyncio.wait_for(proc.wait(), timeout)
        except TimeoutError:
            raise AssertionError(f"{role} still running {timeout} s after SIGTERM\n"
                                 f"{self.logs()}") from None  # fmt: skip

    def logs(self, tail: int = 3000) -> str:
        """The daemons' logs (stderr and stdout), the last ``tail`` characters of each."""
        return "\n".join(
            f"--- {p.name}\n{p.read_text(errors='replace')[-tail:]}"
            for p in sorted(self.tmp.glob("*.log"))
        )

    async def close(self) -> None:
        """Kill what is still running, the daemons' children (servo, sensing, video) too, but
        not their resource trackers: those unlink the shared memory the killed processes left
        (killed too, they left the servo's blocks in /dev/shm), and are waited for (5 s)."""
        trackers = set()
        for proc in self.procs.values():
            if proc.returncode is None:
                for child in descendants(proc.pid):
                    if resource_tracker(child):
                        trackers.add(child)
                        continue
                    with contextlib.suppress(OSError):
                        os.kill(child, signal.SIGKILL)
                signal_child(proc, signal.SIGKILL)
                await proc.wait()
        for _ in range(50):
            if not any(pid_alive(p) for p in trackers):
                break
            await asyncio.sleep(0.1)
        await self.server.stop()


@pytest.fixture
async def session(tmp_path):
    token = secrets.token_urlsafe(16)
    server = SignalingServer(SignalConfig(port=0), token=token)
    await server.start()
    s = Session(tmp_path, server, token)
    with whole_session_slot():  # one whole session at a time across the lanes
        try:
            yield s
        finally:
            await s.close()


class DemoLines:
    """``humantele demo ARGS`` in its own session (process group), read status line by status
    line (stderr, every 2 s with ``--json``); every process of the demo's is kept in
    :attr:`seen`, to check none is left."""

    def __init__(self, *args: str, timeout_s: float = 600.0) -> None:
        env = dict(os.environ)
        env.pop("HUMANTELE_TOKEN", None)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "humantele", "demo", *args],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
            start_new_session=True,
        )  # fmt: skip
        self.lines: list[str] = []
        self.seen: set[int] = set()
        self.t_end = time.monotonic() + timeout_s  # generous: a loaded 2-core machine is slow

    def line(self) -> str:
        """The next status line (fails the test at the timeout or if the demo ended)."""
        assert time.monotonic() < self.t_end, "timed out:\n" + "".join(self.lines[-10:])
        line = self.proc.stderr.readline()
        assert line, "demo ended early:\n" + "".join(self.lines[-10:])
        self.lines.append(line)
        self.seen |= descendants(self.proc.pid)
        return line

    def daemon(self, role: str) -> int | None:
        """The running ``humantele <role>`` daemon of the demo's (None: none now)."""
        return daemon_of(self.proc.pid, role)

    def left_running(self, wait_s: float = 10.0) -> list[int]:
        """The demo's processes still running after up to ``wait_s``."""
        end = time.monotonic() + wait_s
        while any(pid_alive(p) for p in self.seen) and time.monotonic() < end:
            time.sleep(0.1)
        return [p for p in self.seen if pid_alive(p)]

    def kill(self) -> None:
        """SIGKILL the whole group if the demo still runs."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.communicate()


@dataclass
class DemoRun:
    """One ``humantele demo --config configs/demo.toml --json --record --igtl-port 0`` run
    (with the video tracks, recorded, OpenIGTLink served for 3D Slicer), ended by a terminal's
    Ctrl-C (SIGINT to its process group: the demo, both daemons and the servo at once) once it
    has recorded a scan long enough to analyse and an OpenIGTLink client has had the probe:
    what the tests of that run check (run by tests/browser/scenarios/console_video.py, its
    console checked meanwhile). (The supervision test ends its demo with SIGTERM to the demo
    alone.)"""

    tmp: Path
    returncode: int | None
    summary: dict
    out: str
    err: str
    status: list[str] = field(default_factory=list)
    seen: set[int] = field(default_factory=set)  # the demo's descendants while it ran
    stop_s: float = math.inf  # from Ctrl-C to the demo's exit
    igtl: dict = field(default_factory=dict)  # the OpenIGTLink client's (IgtlClient.result)

    @property
    def recordings(self) -> tuple[Path, Path]:
        return self.tmp / "demo.expert.mcap", self.tmp / "demo.follower.mcap"


VIDEO_DEMO_TIMEOUT_S = 900.0  # the console_video scenario's bound (s, scaled to the load)
SCAN_S = 10.0  # scan 1 runs this long before the demo is stopped: long enough that the
# mean alignment error of the recorded scan settles on the sim offset (4 s gave 1.9-2.3 mm for
# a 5 mm offset: the lag of a short stretch of motion dominated it)
SCAN_POSES = 150  # and the follower has recorded this many tracked probe poses in it (the
# analysis test wants more than 50): on a busy machine the sensing process (niced) measures
# fewer of its 45 tracker images a second, and 10 s gave as few as 6


def scan_recorded(path: Path) -> bool:
    """Scan 1 is in the follower's recording (being written) for ``SCAN_S``, with
    ``SCAN_POSES`` tracked probe poses within it."""
    try:
        rec = read_recording(path, ["/follower/scan", "/follower/probe_pose"])
    except OSError:  # not there yet
        return False
    starts = [s["t"] for s in rec.samples("/follower/scan") if s["event"] == "start"]
    if not starts:
        return False
    stops = [s["t"] for s in rec.samples("/follower/scan") if s["event"] == "stop"]
    end = stops[0] if stops else float("inf")  # (a scan of a fixed length ends by itself)
    tracked = [s["t"] for s in rec.samples("/follower/probe_pose") if s["tracked"]]
    tracked = [t for t in tracked if starts[0] <= t <= end]
    return len(tracked) >= SCAN_POSES and tracked[-1] - starts[0] >= SCAN_S


IGTL_LINE = re.compile(r"OpenIGTLink \(follower, 3D Slicer\): 127\.0\.0\.1:(\d+)")


class IgtlClient(threading.Thread):
    """3D Slicer's side of ``demo --igtl-port 0``: the address the demo prints (its status
    lines), then a pyigtl client on it until the probe's ``ProbeToWorld`` transform comes.
    ``result``: ``port`` (None: never printed), ``shape`` (the transform's matrix, None: no
    message within ``wait_s``), ``error``."""

    def __init__(self, lines: list[str], stop: threading.Event, wait_s: float = 60.0) -> None:
        super().__init__(daemon=True)
        self.lines, self.stop, self.wait_s = lines, stop, wait_s
        self.result: dict = {"port": None, "shape": None, "error": None}

    @property
    def waiting(self) -> bool:
        """Whether it waits for the probe's transform on the printed address."""
        return self.is_alive() and self.result["port"] is not None

    def run(self) -> None:
        while self.result["port"] is None and not self.stop.wait(0.2):
            for line in list(self.lines):
                if m := IGTL_LINE.match(line):
                    self.result["port"] = int(m.group(1))
        if self.result["port"] is None:
            return
        import pyigtl

        client = pyigtl.OpenIGTLinkClient("127.0.0.1", self.result["port"])
        try:
            msg = client.wait_for_message("ProbeToWorld", timeout=self.wait_s)
            self.result["shape"] = None if msg is None else tuple(msg.matrix.shape)
        except Exception as exc:  # noqa: BLE001 - the test says what went wrong
            self.result["error"] = repr(exc)
        finally:
            client.stop()


@pytest.fixture(scope="session")
def demo_run(browser_scenario) -> DemoRun:
    """The demo run shared by the tests that check one run (the command, its recording and
    the analysis, the video's export, OpenIGTLink for 3D Slicer): the demo of the browser
    scenario console_video (tests/browser/scenarios/console_video.py), whose console checks
    run meanwhile, so one whole video session serves both (issue 33). It ends on its condition
    (the console's visits done; scan 1 recorded, after the calibration, for ``SCAN_S`` with
    ``SCAN_POSES`` tracked probe poses; the OpenIGTLink client done), not after a fixed
    duration. One whole session at a time across the lanes (tests/session_slot.py)."""
    run = browser_scenario("console_video", timeout_s=VIDEO_DEMO_TIMEOUT_S)
    d = dict(run.data["demo_run"])
    igtl = dict(d["igtl"])
    igtl["shape"] = None if igtl["shape"] is None else tuple(igtl["shape"])  # (JSON: a list)
    return DemoRun(run.out_dir / "rec", d["returncode"], d["summary"], d["out"], d["err"],
                   d["status"], set(d["seen"]), d["stop_s"], igtl)  # fmt: skip

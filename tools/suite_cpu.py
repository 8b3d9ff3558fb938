"""The CPU a command's whole process tree used, by kind of process: for the test suite's budget
(issue 33: the README's command within 400 s and 560 CPU-s on 2 cores).

    python tools/suite_cpu.py -- python -m pytest -q
    python tools/suite_cpu.py --json cpu.json -- python -m pytest -q tests/test_wire.py

It runs the command as a child, makes itself the child subreaper (``PR_SET_CHILD_SUBREAPER``:
an orphaned grandchild, a daemon whose test died, comes back to it and is reaped here, so its
CPU is counted too) and reads every descendant's ``/proc/<pid>/stat`` (utime + stime, all its
threads) every ``--interval`` s (0.5) through the run. The total is exact: the reaped
children's CPU from ``getrusage(RUSAGE_CHILDREN)``; the kinds come from the samples, each
process counted at its last sample, and what ran between a process's last sample and its end
(a short process seen never or late) is the row ``(between samples)``.

Kinds, from each process's name and command line: ``pytest`` (pytest and its xdist workers,
and daemons they run in process), Chromium's ``chromium gpu``, ``chromium renderer`` and
``chromium other``, the daemons (``follower``, ``expert``), their children (``sensing``,
``servo``, ``video``: the follower's video process and the console's sim video), and
``other`` (the demo, the signaling server, coturn, Playwright's driver, a compiler ...).
The command's exit code is this tool's.

The host's own speed moves the figures: on a shared host the same tests took a third more
CPU-s one hour than the hour before (nothing else running in the machine, no steal
reported), and within a run: a CPU-bound test took 10 s in one run and 18 s in the next,
the host's speed before and after each the same. So the tool times a fixed single-threaded
workload (:class:`Reference`) before and after the command and a twentieth of it every
``PROBE_EVERY_S`` through the run, and prints them beside the figures (``--reference 0``:
not).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
import json
import os
import resource
import signal
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

PR_SET_CHILD_SUBREAPER = 36
TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")
KINDS = (
    "pytest", "chromium gpu", "chromium renderer", "chromium other", "follower", "expert",
    "sensing", "servo", "video", "other",
)  # fmt: skip


def read_stat(pid: int) -> tuple[int, str, float] | None:
    """(parent pid, name, CPU s: utime + stime) of ``pid``, or None when it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    name = text[text.index("(") + 1 : text.rindex(")")]
    fields = text[text.rindex(")") + 2 :].split()  # from field 3 (state) on
    return int(fields[1]), name, (int(fields[11]) + int(fields[12])) * TICK_S


def cmdline(pid: int) -> list[str]:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return []
    return [a.decode(errors="replace") for a in raw.split(b"\0") if a]


def kind_of(name: str, argv: list[str]) -> str:
    """The kind of a process from its name (``comm``, 15 characters) and command line."""
    line = " ".join(argv)
    if name.startswith("humantele-sens"):
        return "sensing"
    if name.startswith("humantele-serv"):
        return "servo"
    if name.startswith(("humantele-vide", "humantele-csim")):
        return "video"
    if "chrom" in name.lower() or "headless_shell" in line or "chrome" in line.split(" ")[0]:
        if "--type=gpu-process" in line:
            return "chromium gpu"
        if "--type=renderer" in line:
            return "chromium renderer"
        return "chromium other"
    for i, a in enumerate(argv[:-1]):  # python -m humantele ROLE ..., or the humantele script
        if a == "humantele" or a.endswith("/humantele"):
            role = argv[i + 1]
            if role in ("follower", "expert"):
                return role
            break
    if "pytest" in line or "execnet" in line or "sys.stdin.readline()" in line:  # xdist's
        return "pytest"
    return "other"


class Tree:
    """The descendants of ``root`` seen so far: their kind and CPU at the last sample."""

    def __init__(self, root: int) -> None:
        self.root = root
        self.members = {root}
        self.kind: dict[int, str] = {}
        self.cpu: dict[int, float] = {}
        self.samples = 0

    def sample(self) -> None:
        """One pass over /proc: new descendants found (a parent in the tree, or reparented
        to us, the subreaper), every member's CPU read."""
        stats = {}
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                st = read_stat(int(entry))
                if st is not None:
                    stats[int(entry)] = st
        me = os.getpid()
        grew = True
        while grew:  # parents before children, whatever the order of /proc
            grew = False
            for pid, (ppid, _, _) in stats.items():
                if pid not in self.members and (ppid in self.members or ppid == me):
                    self.members.add(pid)
                    grew = True
        for pid in self.members:
            st = stats.get(pid)
            if st is None:
                continue
            if pid not in self.kind or self.kind[pid] == "other":  # exec may rename it
                self.kind[pid] = kind_of(st[1], cmdline(pid))
            self.cpu[pid] = st[2]
        self.samples += 1

    def by_kind(self) -> dict[str, tuple[int, float]]:
        out: dict[str, list] = defaultdict(lambda: [0, 0.0])
        for pid, cpu in self.cpu.items():
            row = out[self.kind.get(pid, "other")]
            row[0] += 1
            row[1] += cpu
        return {k: (n, s) for k, (n, s) in out.items()}


def reap_all(timeout_s: float) -> int:
    """Reap every child (ours and the orphans we were given) for up to ``timeout_s``; the
    number still running then."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            pid, _ = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return 0
        if pid == 0:
            if time.monotonic() > deadline:
                return len([p for p in os.listdir("/proc") if p.isdigit() and _is_child(int(p))])
            time.sleep(0.05)


def reap_orphans(keep: int) -> None:
    """Reap the orphans given to us (the subreaper) that have ended, once sampled: left as
    zombies they would look alive to a test that waits for a process to go (``keep``: the
    command itself, whose exit code ``Popen`` reads)."""
    me = os.getpid()
    for entry in os.listdir("/proc"):
        if entry.isdigit() and int(entry) != keep:
            st = read_stat(int(entry))
            if st is not None and st[0] == me:
                with contextlib.suppress(ChildProcessError):
                    os.waitpid(int(entry), os.WNOHANG)


def _is_child(pid: int) -> bool:
    st = read_stat(pid)
    return st is not None and st[0] == os.getpid()


SLICES = 20  # the reference workload is this many equal slices; one is timed during the run
PROBE_EVERY_S = 15.0  # between two timed slices during the run (s; --probe-every)
REFERENCE_LEAST_S = 0.57  # Reference().cpu_s(), the least seen on the 2-core machine (11-29)


class Reference:
    """A fixed single-threaded workload, timed in this process (its CPU-s not the command's):
    ``SLICES`` equal slices of JSON as the wire's, small numpy products as the poses', OpenCV
    blur and JPEG as the video's and a sort of 8 MB, past the caches, as the tracker's
    tables. The figure is always the whole workload's CPU-s (a slice's times ``SLICES``), so
    that a slice timed during the run reads like the whole timed before and after it."""

    def __init__(self) -> None:
        import cv2  # only here: the tool itself needs neither
        import numpy as np

        cv2.setNumThreads(1)
        self._np, self._cv2 = np, cv2
        self.rows = [{"t": i * 1e-3, "pose": [float(j) for j in range(7)], "kind": "pose"}
                     for i in range(2000)]  # fmt: skip
        rng = np.random.default_rng(7)
        self.R = rng.standard_normal((4, 4))
        self.img = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
        self.big = rng.standard_normal(1_000_000)
        self.work = np.empty_like(self.big)  # sorted in place: no 8 MB allocation to time

    def _slice(self) -> None:
        np, cv2 = self._np, self._cv2
        json.loads(json.dumps(self.rows))
        v = np.ones(4)
        for _ in range(5000):
            v = self.R @ v
            v /= np.linalg.norm(v)
        for _ in range(8):
            cv2.imencode(".jpg", cv2.GaussianBlur(self.img, (9, 9), 2.0))
        np.multiply(self.big, 1.0001, out=self.work)
        self.work.sort()

    def cpu_s(self, slices: int = SLICES) -> float:
        """The whole workload's CPU-s, from ``slices`` of it (the garbage collector off: a
        collection now and then was a third more on the slice it fell in)."""
        gc.disable()
        try:
            t0 = time.process_time()
            for _ in range(slices):
                self._slice()
            return (time.process_time() - t0) * SLICES / slices
        finally:
            gc.enable()

    def median_cpu_s(self, repeats: int) -> float:
        times = sorted(self.cpu_s() for _ in range(repeats))
        return times[len(times) // 2]


def host_speed_line(before: float, after: float, during: list[float]) -> str:
    """What the reference workload took before, during (median, slowest) and after a run."""
    mid = sorted(during)
    during_s = (
        f", during it {mid[len(mid) // 2]:.2f} (median of {len(mid)}, slowest {mid[-1]:.2f})"
        if mid else ""
    )  # fmt: skip
    return (
        f"host speed: the reference workload took {before:.2f} CPU-s before the run{during_s}, "
        f"{after:.2f} after (the least seen on the 2-core machine the budget is measured on: "
        f"{REFERENCE_LEAST_S:.2f})"
    )


def table(wall_s: float, total_s: float, tree: Tree, code: int, left: int) -> str:
    rows = tree.by_kind()
    sampled = sum(s for _, s in rows.values())
    lines = [f"{'kind':<20}{'processes':>10}{'CPU-s':>10}{'%':>7}"]
    for kind in KINDS:
        n, s = rows.get(kind, (0, 0.0))
        if n:
            lines.append(f"{kind:<20}{n:>10}{s:>10.1f}{100 * s / max(total_s, 1e-9):>7.1f}")
    gap = max(0.0, total_s - sampled)
    lines.append(
        f"{'(between samples)':<20}{'':>10}{gap:>10.1f}{100 * gap / max(total_s, 1e-9):>7.1f}"
    )
    lines.append(f"{'total':<20}{len(tree.cpu):>10}{total_s:>10.1f}{100.0:>7.1f}")
    lines.append(
        f"wall {wall_s:.1f} s, CPU {total_s:.1f} s ({total_s / max(wall_s, 1e-9):.2f} cores), "
        f"{tree.samples} samples, exit code {code}" + (f", {left} still running" if left else "")
    )
    me = resource.getrusage(resource.RUSAGE_SELF)
    lines.append(f"(this tool's own sampling: {me.ru_utime + me.ru_stime:.1f} CPU-s, not counted)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--interval", type=float, default=0.5, help="s between samples")
    parser.add_argument("--json", help="also write the figures to this file")
    parser.add_argument(
        "--reference", type=int, default=3, metavar="N",
        help="time the reference workload N times before and after (0: not)",
    )  # fmt: skip
    parser.add_argument(
        "--probe-every", type=float, default=PROBE_EVERY_S, metavar="S",
        help="time a slice of the reference workload every S seconds through the run",
    )  # fmt: skip
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- the command to run")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("no command: python tools/suite_cpu.py -- python -m pytest -q")
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        print("suite_cpu: not a subreaper: orphans' CPU is not counted", file=sys.stderr)
    ref = Reference() if args.reference > 0 else None
    before = ref.median_cpu_s(args.reference) if ref else 0.0
    during: list[float] = []
    t0 = time.monotonic()
    proc = subprocess.Popen(command)
    tree = Tree(proc.pid)
    old = signal.signal(signal.SIGINT, lambda *_: proc.send_signal(signal.SIGINT))
    next_probe = t0 + args.probe_every
    try:
        while proc.poll() is None:
            tree.sample()
            reap_orphans(proc.pid)
            if ref is not None and time.monotonic() >= next_probe:
                during.append(ref.cpu_s(1))
                next_probe += args.probe_every
            time.sleep(args.interval)
    finally:
        signal.signal(signal.SIGINT, old)
    wall = time.monotonic() - t0
    left = reap_all(10.0)
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    total = usage.ru_utime + usage.ru_stime
    after = ref.median_cpu_s(args.reference) if ref else 0.0
    print(table(wall, total, tree, proc.returncode, left), file=sys.stderr)
    if ref is not None:
        print(host_speed_line(before, after, during), file=sys.stderr)
    sys.stderr.flush()
    if args.json:
        rows = tree.by_kind()
        data = {
            "command": command, "wall_s": round(wall, 2), "cpu_s": round(total, 2),
            "exit_code": proc.returncode, "samples": tree.samples, "still_running": left,
            "reference_cpu_s": {"before": round(before, 3), "after": round(after, 3),
                                "during": [round(x, 3) for x in during]} if ref else None,
            "kinds": {k: {"processes": n, "cpu_s": round(s, 2)} for k, (n, s) in rows.items()},
        }  # fmt: skip
        Path(args.json).write_text(json.dumps(data, indent=1) + "\n")
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())

"""``humantele bench sensing``: how late the follower's event loop wakes with sensing beside it.

The follower's loop must read the expert's poses the moment they arrive (the demo's pose
age). Its sensing (sim frame rendering, the tracking pipeline, the force sensor: ~5 ms of
Python at 45 Hz) ran on a worker thread, so it competed for the loop's GIL. This bench runs a
loop shaped like the follower's (100 Hz ticks submitting tracker frames at 45 Hz, exactly as
:class:`~humantele.follower.daemon.FollowerDaemon` does) and, from another process, sends it
timestamped UDP datagrams at ``--rate`` Hz; it measures when the loop reads each one (receive
latency) and how late each tick starts. Sensing modes, interleaved ``--repeat`` times so
all see the same machine load: ``none`` (no sensing), ``thread`` (the old worker thread),
``process`` (:mod:`humantele.follower.sensing_process`).

Prints a table and, last, one JSON line; writes the "sensing" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import os
import socket
import struct
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from humantele.bench import publish
from humantele.report import machine_line, markdown_table

MODES = ("none", "thread", "process")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=10.0, help="measured time per run")
    p.add_argument("--repeat", type=int, default=3, help="runs per mode, interleaved")
    p.add_argument("--rate", type=float, default=1000.0, help="datagrams per second")
    p.add_argument("--json", action="store_true", help="print a JSON summary as the last line")
    p.add_argument("--no-write", action="store_true", help="do not write docs/")
    p.add_argument(
        "--realtime",
        action="store_true",
        help="run the loop (and sender) SCHED_FIFO 5 to shield them from other work on the "
        "machine (needs root or CAP_SYS_NICE); the sensing child drops to SCHED_OTHER itself",
    )


def _sender(port: int, seconds: float, rate: float) -> None:
    """Send ``struct('d', monotonic())`` datagrams at ``rate`` Hz, then an empty one."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    t_end = time.monotonic() + seconds
    nxt = time.monotonic()
    while time.monotonic() < t_end:
        s.sendto(struct.pack("d", time.monotonic()), ("127.0.0.1", port))
        nxt += 1.0 / rate
        d = nxt - time.monotonic()
        if d > 0:
            time.sleep(d)
    s.sendto(b"", ("127.0.0.1", port))
    s.close()


class _Follower:
    """The follower's loop shape: the sim world stepped at 100 Hz, a tracker frame at 45 Hz
    measured off the loop (thread or process), one in flight at most."""

    def __init__(self, mode: str) -> None:
        from humantele.follower.daemon import FollowerConfig
        from humantele.follower.sensing import Sensing
        from humantele.follower.sim_human import probe_down_quat
        from humantele.follower.sim_world import SimWorld
        from humantele.geometry import Pose

        self.mode = mode
        self.config = FollowerConfig(sensing_worker="process" if mode == "process" else "thread")
        self.world = SimWorld()
        self.world.human.hand = Pose([0.35, 1.0, -0.15], probe_down_quat([0.0, 1.0, 0.0]))
        self.sensing = Sensing(self.config, build=mode == "thread")
        self.executor = ThreadPoolExecutor(1) if mode == "thread" else None
        self.proc = None
        self.in_flight = False
        self.measured = 0
        self.skipped = 0
        self.tracked = 0

    async def start(self) -> None:
        if self.mode == "process":
            from humantele.follower.sensing_process import SensingProcess

            self.proc = SensingProcess(
                self.config, None, self._done_proc, priority=self.config.sensing_priority
            )
            self.proc.start()
            if not await self.proc.wait_ready():
                raise RuntimeError(f"the sensing process did not start: {self.proc.error}")

    def _took(self, m) -> None:
        self.in_flight = False
        self.measured += 1
        self.tracked += m.T_world_tip is not None

    def _done_proc(self, job: int, m, seconds: float) -> None:
        self._took(m)

    def frame(self, t: float) -> None:
        if self.mode == "none":
            return
        if self.in_flight:
            self.skipped += 1
            return
        truth = self.world.truth(t)
        if self.proc is not None:
            self.in_flight = self.proc.submit(self.measured + self.skipped, (t, truth))
            return
        self.in_flight = True
        fut = asyncio.get_running_loop().run_in_executor(
            self.executor, self.sensing.measure, t, truth
        )
        fut.add_done_callback(lambda f: self._took(f.result()))

    def close(self) -> None:
        if self.proc is not None:
            self.proc.close()
        if self.executor is not None:
            self.executor.shutdown(wait=True)
        self.sensing.close()


async def _run(mode: str, seconds: float, rate: float) -> dict:
    loop = asyncio.get_running_loop()
    fol = _Follower(mode)
    await fol.start()
    lat: list[float] = []
    late: list[float] = []
    done = loop.create_future()

    class Rx(asyncio.DatagramProtocol):
        def datagram_received(self, data: bytes, addr) -> None:
            if not data:
                if not done.done():
                    done.set_result(None)
                return
            lat.append(time.monotonic() - struct.unpack("d", data)[0])

    tr, _ = await loop.create_datagram_endpoint(Rx, local_addr=("127.0.0.1", 0))
    port = tr.get_extra_info("sockname")[1]
    ctx = mp.get_context("spawn")
    sender = ctx.Process(target=_sender, args=(port, seconds, rate), daemon=True)
    for _ in range(100):  # a second of the follower's loop before measuring (warm up)
        fol.frame(loop.time())
        await asyncio.sleep(0.01)
    sender.start()
    t0 = time.monotonic()
    nxt, last_frame = t0, -1.0
    try:
        while not done.done() and time.monotonic() - t0 < seconds + 30.0:
            now = time.monotonic()
            late.append(max(0.0, now - nxt))
            world_t = now - t0
            fol.world.step(world_t, None)
            if world_t - last_frame >= 1.0 / 45.0:
                last_frame = world_t
                fol.frame(world_t)
            nxt += 0.01
            if nxt < time.monotonic():
                nxt = time.monotonic()  # no catching up, as the daemon's pacer
            await asyncio.sleep(max(0.0, nxt - time.monotonic()))
    finally:
        tr.close()
        sender.join(5.0)
        if sender.is_alive():
            sender.kill()
        fol.close()
    a = np.array(lat) * 1e3
    k = np.array(late) * 1e3
    expected = int(seconds * rate)
    return {
        "mode": mode,
        "received": len(a),
        "lost": max(0, expected - len(a)),
        "p50_ms": float(np.percentile(a, 50)) if len(a) else None,
        "p99_ms": float(np.percentile(a, 99)) if len(a) else None,
        "p999_ms": float(np.percentile(a, 99.9)) if len(a) else None,
        "max_ms": float(a.max()) if len(a) else None,
        "over_2ms_pct": float(100.0 * np.mean(a > 2.0)) if len(a) else None,
        "tick_late_p99_ms": float(np.percentile(k, 99)) if len(k) else None,
        "frames": fol.measured,
        "skipped": fol.skipped,
        "load1": os.getloadavg()[0],
    }


def run(args: argparse.Namespace) -> int:
    runs: list[dict] = []
    policy = "normal scheduling"
    if args.realtime:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(5))
            policy = "loop, sender and sensing thread SCHED_FIFO 5 (`--realtime`)"
        except (OSError, AttributeError) as exc:
            print(f"--realtime: cannot set SCHED_FIFO ({exc}); normal scheduling", flush=True)
    for i in range(args.repeat):
        for mode in MODES:
            r = asyncio.run(_run(mode, args.seconds, args.rate))
            r["run"] = i
            runs.append(r)
            print(
                f"run {i} {mode:8s} p50 {r['p50_ms']:.3f} p99 {r['p99_ms']:.3f} "
                f"p99.9 {r['p999_ms']:.2f} max {r['max_ms']:.1f} ms, "
                f">2 ms {r['over_2ms_pct']:.2f} %, tick late p99 {r['tick_late_p99_ms']:.2f} ms, "
                f"lost {r['lost']}, frames "
                f"{r['frames']}, load {r['load1']:.1f}",
                flush=True,
            )
    summary: dict = {
        "runs": runs,
        "seconds": args.seconds,
        "rate_hz": args.rate,
        "policy": policy,
    }
    rows = []
    for mode in MODES:
        rs = [r for r in runs if r["mode"] == mode]
        med = {
            k: float(np.median([r[k] for r in rs]))
            for k in ("p50_ms", "p99_ms", "p999_ms", "max_ms", "over_2ms_pct", "tick_late_p99_ms")
        }
        med["frames_per_s"] = float(np.median([r["frames"] for r in rs])) / args.seconds
        summary[mode] = med
        rows.append(
            [
                mode,
                f"{med['p50_ms']:.3f}",
                f"{med['p99_ms']:.2f}",
                f"{med['p999_ms']:.2f}",
                f"{med['max_ms']:.1f}",
                f"{med['over_2ms_pct']:.2f}",
                f"{med['tick_late_p99_ms']:.2f}",
                f"{med['frames_per_s']:.0f}",
                " / ".join(f"{r['p99_ms']:.2f}" for r in rs),
            ]
        )
    loads = [r["load1"] for r in runs]
    md = "\n\n".join(
        [
            "## Follower sensing beside the event loop (`humantele bench sensing`)",
            machine_line()
            + f" {args.repeat} runs of {args.seconds:g} s per mode, interleaved; load "
            f"average during the runs {min(loads):.1f}-{max(loads):.1f}; {policy}. Figures "
            "are medians over the runs.",
            "A loop shaped like the follower's (100 Hz ticks, a sim tracker frame measured "
            "at 45 Hz, one in flight) receives timestamped UDP datagrams at "
            f"{args.rate:g} Hz from another process: receive latency is when the loop reads "
            "each one, the part of the demo's pose age the follower adds. *none*: no "
            "sensing; *thread*: sensing on a worker thread (the follower until issue 9); "
            "*process*: sensing in a child process (`humantele.follower.sensing_process`, "
            "nice +10, normal scheduling). With `--realtime` other work on the machine "
            "cannot delay the loop, so what is left is the cost of the sensing beside it: "
            "in a thread, the loop waits for the GIL the sensing holds (CPython hands it "
            "over every 5 ms, `sys.getswitchinterval()`); in a process, nothing. The "
            "frames/s column is what the sensing managed at the machine's load (45 asked): "
            "a niced child gives way to the loop and to other work.",
            markdown_table(
                [
                    "sensing",
                    "p50 ms",
                    "p99 ms",
                    "p99.9 ms",
                    "max ms",
                    "> 2 ms %",
                    "tick late p99 ms",
                    "frames/s",
                    "p99 per run ms",
                ],
                rows,
            ),
        ]
    )
    publish("sensing", md, summary, args)
    return 0

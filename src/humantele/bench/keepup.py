"""``humantele bench keepup``: does the follower's sensing measure the frames the headset
delivers, with the CPU busy? (issue 30 §2: "with one core busy, at least 90 % of delivered
frames measured").

An hl2ss server (the replay server, in this process's thread) sends 45 distinct AHAT frames
(the sim camera's, with rig poses) at ``--rate`` Hz, looped, to the follower's own sensing
machinery: a :class:`~humantele.follower.sensing_worker.SensingWorker` on an event loop ticking
at 100 Hz and submitting at 45 Hz as the follower's daemon does, its sensing process reading
the stream with the hl2ss client and tracking each frame. The force board is a silent stand-in
(the force is not what is measured here). ``--load N`` busy processes run beside it.

Figures per run: frames delivered to the follower's socket (decoded, plus those the client
skipped as older than the newest), frames the tracker measured, their ratio, the frames not
measured by reason, the sensing process's CPU. Prints a line per run and, with ``--json``, a
JSON line; writes the "keepup" section of docs/benchmarks.md unless ``--no-write``.

    humantele bench keepup --seconds 20 --load 1          # the issue's figure
    humantele bench keepup --seconds 3 --no-write         # a quick check
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import time

from humantele.bench import publish
from humantele.report import machine_line, markdown_table

FRAMES = 45


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=20.0, help="measured time per run")
    p.add_argument("--load", type=int, nargs="*", default=[0, 1],
                   help="busy processes beside the sensing, one run per value")  # fmt: skip
    p.add_argument("--rate", type=float, default=45.0, help="the headset's frame rate (Hz)")
    p.add_argument("--json", action="store_true", help="print a JSON summary as the last line")
    p.add_argument("--no-write", action="store_true", help="do not write docs/")


def _records():
    """45 frames of the sim camera (the probe sweeping) with the headset's rig pose."""
    from humantele.geometry import Pose, quat_from_axis_angle, quat_multiply
    from humantele.tracking.hl2ss_calibration import Hl2ssAhatCalibration
    from humantele.tracking.hl2ss_replay import AhatRecord
    from humantele.tracking.sim import SimFrameConfig, SimFrameSource, default_sim_pose

    sim = SimFrameSource(SimFrameConfig(seed=3))
    base = default_sim_pose()
    records = []
    for k in range(FRAMES):
        q = quat_multiply(quat_from_axis_angle([0, 1, 0], 0.3 * math.sin(k / 5)), base.quaternion)
        p = base.position + [0.05 * math.sin(k / 7), 0.02 * math.cos(k / 4), 0.0]
        f = sim.render(Pose(p, q), t=k / 45.0)
        rig = Pose([0.2, 1.6, -0.3], quat_from_axis_angle([0.2, 1.0, 0.1], 0.4))
        records.append(AhatRecord(10_000_000 + k * 222_222, f.depth_mm, f.ir, k, rig))
    T_rig_camera = Pose([0.004, -0.09, -0.012], quat_from_axis_angle([1, 0, 0], math.pi))
    return records, Hl2ssAhatCalibration.pinhole(sim.intrinsics, T_rig_camera)


class _SilentBoard:
    """A force board that never sends (the bench measures the camera's frames)."""

    name = "silent board"

    def open(self) -> None:
        pass

    def read(self, t=None):
        return None

    def close(self) -> None:
        pass


def keepup_sensing_main(config, sensing_config, conn, priority) -> None:
    """The bench's sensing child: the follower's sensing on the hl2ss client (its camera
    config in ``sensing_config``) and a silent board; then the follower's child loop."""
    import numpy as np

    from humantele.follower.sensing import ProbeSensing, Sensing
    from humantele.follower.sensing_devices import SensingDevices
    from humantele.follower.sensing_process import serve
    from humantele.forcesense.calibration import ForceCalibration
    from humantele.tracking.hl2ss_source import Hl2ssFrameSource
    from humantele.tracking.tool import load_tool

    tool = load_tool(config.tool)
    cal = ForceCalibration(np.zeros((1, 3)), np.zeros(3), np.ones(3))
    devices = SensingDevices(Hl2ssFrameSource(sensing_config.camera), _SilentBoard(), cal)
    sensing = Sensing(config, sensing_config, build=False)
    sensing.pipeline, sensing.unbuilt = ProbeSensing(sensing_config, tool, devices), False
    serve(sensing, conn, priority)


async def _run(port: int, seconds: float, calibration_file: str) -> dict:
    from humantele.follower.daemon import FollowerConfig
    from humantele.follower.sensing import SensingConfig, TrackerImage
    from humantele.follower.sensing_worker import SensingWorker
    from humantele.tracking.hl2ss_source import Hl2ssFrameConfig

    config = FollowerConfig()
    camera = Hl2ssFrameConfig(host="127.0.0.1", port=port, calibration_file=calibration_file)
    sensing_config = SensingConfig(camera=camera)
    measured = []
    worker = SensingWorker(config, sensing_config, lambda f, m: measured.append(m),
                           lambda reason: None, target=keepup_sensing_main)  # fmt: skip
    worker.start()
    try:
        ready = await worker.proc.wait_ready()
        if not ready:
            raise RuntimeError(f"the sensing process did not start: {worker.proc.error}")
        loop = asyncio.get_running_loop()
        period, last = 1.0 / config.sensing_rate_hz, 0.0
        t_end = loop.time() + seconds
        first = None
        while loop.time() < t_end:
            t = time.monotonic()
            if t - last >= period:  # the daemon's frame clock (see FollowerDaemon.tick)
                last = t if t - last >= 2 * period else last + period
                worker.submit(TrackerImage(t, None, None, None))
            if first is None and worker.proc.device_stats:
                first = dict(worker.proc.device_stats)  # counted from here (after the start)
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.5)  # the last counters
        end = worker.device_summary()
        cpu = worker.proc.cpu_percent()
    finally:
        worker.close()
    dev = end["sensing_devices"] or {}

    def delivered(d: dict) -> int:
        cam = d.get("camera") or {}
        return int(cam.get("received", 0)) + int((cam.get("dropped") or {}).get("stale", 0))

    first = first or {}
    n_delivered = delivered(dev) - delivered(first)
    n_measured = int(dev.get("frames", 0)) - int(first.get("frames", 0))
    return {
        "delivered": n_delivered,
        "measured": n_measured,
        "measured_pct": round(100.0 * n_measured / max(1, n_delivered), 1),
        "unmeasured": end["unmeasured"],
        "stalls": (dev.get("camera") or {}).get("stalls", 0),
        "cpu_percent_sensing": cpu,
        "caught_up": worker.caught_up,
        "load1": os.getloadavg()[0],
    }


def run(args: argparse.Namespace) -> int:
    import tempfile
    from pathlib import Path

    from humantele.bench.cpuload import cpu_load
    from humantele.tracking.hl2ss_replay import Hl2ssReplayServer

    records, cal = _records()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        cal_file = str(Path(tmp) / "ahat_calibration.json")
        cal.save(cal_file)
        for load in args.load:
            with Hl2ssReplayServer([records], calibration=cal, repeat=True, loop=True,
                                   rate_hz=args.rate) as srv:  # fmt: skip
                with cpu_load(load, time.monotonic() + args.seconds + 120):
                    r = asyncio.run(_run(srv.port, args.seconds, cal_file))
            r["load"] = load
            runs.append(r)
            print(f"load {load}: {r['measured']} of {r['delivered']} delivered frames measured "
                  f"({r['measured_pct']} %), unmeasured {r['unmeasured']}, sensing CPU "
                  f"{r['cpu_percent_sensing']} %, load average {r['load1']:.1f}",
                  flush=True)  # fmt: skip
    rows = [[r["load"], r["delivered"], r["measured"], f"{r['measured_pct']:.1f}",
             r["unmeasured"]["stale"], r["unmeasured"]["no_frame"],
             f"{r['cpu_percent_sensing'] or 0:.0f}", f"{r['load1']:.1f}"]
            for r in runs]  # fmt: skip
    md = "\n\n".join([
        "## The follower's sensing keeps up with the headset (`humantele bench keepup`)",
        machine_line() + f" {args.seconds:g} s per run; the headset's {args.rate:g} Hz "
        "AHAT stream from the hl2ss replay server (RAW, loopback) to the follower's sensing "
        "process through its hl2ss client, the daemon's 45 Hz frame clock submitting.",
        markdown_table(["busy processes", "delivered", "measured", "measured %",
                        "replaced unread", "no frame", "sensing CPU %", "load average"],
                       rows),  # fmt: skip
    ])  # fmt: skip
    publish("keepup", md, {"runs": runs, "seconds": args.seconds}, args)
    return 0

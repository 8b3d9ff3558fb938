"""``humantele bench igtl``: what serving OpenIGTLink costs the follower, and how fresh the
poses and images are when they reach a Slicer-like client.

The scene: a loopback session (signaling server in this process, follower and expert daemons
as processes, everything on this machine's cores), run twice for ``--seconds`` once the
follower is calibrated and following: without OpenIGTLink, then with it and one client in
this process reading every message (as Slicer's OpenIGTLinkIF does). Reported: the follower's
CPU % (of one core) in both runs and the difference; the latency of ``ProbeToPatient`` (from
the tracker frame's time to the client having the message) and of ``Image`` (from capture to
the client), p50/p99/max; the rates received; messages dropped.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import secrets
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from humantele.bench import publish
from humantele.report import machine_line, markdown_table
from humantele.runtime.signal_child import signal_child

SECTION = "igtl"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=20.0, help="measured window per run (s)")
    parser.add_argument(
        "--probe", choices=["truth", "pipeline"], default="truth",
        help="follower's probe: the sim truth (default) or the IR sensing pipeline",
    )  # fmt: skip
    parser.add_argument(
        "--start-timeout", type=float, default=300.0, help="wait this long for following (s)"
    )
    parser.add_argument("--json", action="store_true", help="print a JSON summary last")
    parser.add_argument("--no-write", action="store_true", help="do not write benchmarks.md")


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


async def _client(port: int, seconds: float) -> list[tuple[float, str, float, int]]:
    """(receive wall time, device name, message timestamp, size) of every message."""
    from pyigtl.messages import MessageBase

    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    out: list[tuple[float, str, float, int]] = []
    size = MessageBase.IGTL_HEADER_SIZE
    t_end = time.monotonic() + seconds

    async def loop() -> None:
        while True:
            header = await reader.readexactly(size)
            fields = MessageBase.parse_header(header)
            body = await reader.readexactly(fields["body_size"])
            msg = MessageBase.create_message(fields["message_type"])
            msg.unpack(fields, body)  # a client decodes what it gets, as Slicer does
            out.append((time.time(), msg.device_name, msg.timestamp, len(body)))

    task = asyncio.create_task(loop())
    await asyncio.sleep(max(0.0, t_end - time.monotonic()))
    task.cancel()
    writer.close()
    return out


async def _run(
    seconds: float,
    igtl: bool,
    tmp: Path,
    url: str,
    env: dict,
    truth: bool = False,
    start_timeout: float = 300.0,
) -> dict:
    from humantele.runtime.stats import process_cpu_seconds

    stats = {r: tmp / f"{r}-{int(igtl)}.json" for r in ("expert", "follower")}
    procs = {}
    for role in ("follower", "expert"):
        args = [sys.executable, "-m", "humantele", role, "--signaling-url", url,
                "--room", "bench", "--stats-file", str(stats[role])]  # fmt: skip
        if role == "follower":
            args += ["--state-dir", str(tmp / "state"), "--feed-port", "0"]
            if truth:
                cfg = tmp / "follower.toml"
                cfg.write_text('[follower]\nprobe_source = "truth"\n')
                args += ["--config", str(cfg)]
        if igtl:
            args += ["--igtl-port", "0"]
        log = open(tmp / f"{role}-{int(igtl)}.log", "wb")  # noqa: SIM115
        procs[role] = await asyncio.create_subprocess_exec(
            *args, stdin=asyncio.subprocess.DEVNULL, stdout=log, stderr=log, env=env
        )
        log.close()
    try:
        t_end = time.monotonic() + start_timeout
        while time.monotonic() < t_end:
            f, e = _read_json(stats["follower"]), _read_json(stats["expert"])
            if f.get("calibrated") and e.get("states_received", 0) > 100:
                break
            if any(p.returncode is not None for p in procs.values()):
                raise RuntimeError(f"a daemon stopped; see {tmp}")
            await asyncio.sleep(0.2)
        else:
            raise RuntimeError(
                f"the session did not start following within {start_timeout:.0f} s (machine "
                f"load {os.getloadavg()[0]:.1f}); logs were in {tmp}"
            )
        pid = procs["follower"].pid
        port = (_read_json(stats["follower"]).get("igtl") or {}).get("port") if igtl else None
        if port:  # the first client starts the image stream: let it settle for 3 s
            await _client(port, 3.0)
        m0 = _read_json(stats["follower"]).get("measurements", 0)
        c0, k0, t0 = process_cpu_seconds(pid), _children_cpu(pid), time.monotonic()
        messages = await _client(port, seconds) if port else (await asyncio.sleep(seconds) or [])
        c1, k1, t1 = process_cpu_seconds(pid), _children_cpu(pid), time.monotonic()
        await asyncio.sleep(1.5)  # the next stats file
        f_stats = _read_json(stats["follower"])
        igtl_stats = f_stats.get("igtl")
        meas_rate = (f_stats.get("measurements", 0) - m0) / (time.monotonic() - t0)
    finally:
        for p in procs.values():
            signal_child(p, signal.SIGTERM)
        for p in procs.values():
            try:
                await asyncio.wait_for(p.wait(), 20)
            except TimeoutError:
                signal_child(p, signal.SIGKILL)
                await p.wait()
    cpu = None if c0 is None or c1 is None else 100.0 * (c1 - c0) / (t1 - t0)
    return {"cpu_percent": cpu, "children_cpu_percent": 100.0 * (k1 - k0) / (t1 - t0),
            "messages": messages, "igtl": igtl_stats, "seconds": t1 - t0,
            "measurement_rate_hz": meas_rate}  # fmt: skip


def _children_cpu(pid: int) -> float:
    """CPU seconds of ``pid``'s child processes (video sources, sensing, a sim ultrasound)."""
    import psutil

    from humantele.runtime.stats import process_cpu_seconds

    try:
        kids = psutil.Process(pid).children()
    except psutil.Error:
        return 0.0
    return sum(process_cpu_seconds(k.pid) or 0.0 for k in kids)


def _lat(messages: list, name: str) -> dict:
    ms = np.array([(r - ts) * 1e3 for r, n, ts, _ in messages if n == name])
    if ms.size == 0:
        return {"n": 0}
    return {"n": int(ms.size), "p50_ms": float(np.median(ms)),
            "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max())}  # fmt: skip


async def _bench(seconds: float, truth: bool, start_timeout: float = 300.0) -> dict:
    from humantele.signaling.server import SignalConfig, SignalingServer

    token = secrets.token_urlsafe(16)
    server = SignalingServer(SignalConfig(port=0), token=token)
    await server.start()
    env = dict(os.environ, HUMANTELE_TOKEN=token, HUMANTELE_PARENT_PID=str(os.getpid()))
    try:
        with tempfile.TemporaryDirectory(prefix="humantele-bench-igtl-") as d:
            off = await _run(seconds, False, Path(d), server.url, env, truth, start_timeout)
            on = await _run(seconds, True, Path(d), server.url, env, truth, start_timeout)
    finally:
        await server.stop()
    msgs = on["messages"]
    dur = on["seconds"]
    return {
        "seconds": seconds,
        "cpu_off_percent": off["cpu_percent"],
        "cpu_on_percent": on["cpu_percent"],
        "cpu_children_off_percent": off["children_cpu_percent"],
        "cpu_children_on_percent": on["children_cpu_percent"],
        "tracker_rate_off_hz": off["measurement_rate_hz"],
        "tracker_rate_on_hz": on["measurement_rate_hz"],
        "pose": _lat(msgs, "ProbeToPatient"),
        "image": _lat(msgs, "Image"),
        "pose_rate_hz": sum(n == "ProbeToPatient" for _, n, _, _ in msgs) / dur,
        "image_rate_hz": sum(n == "Image" for _, n, _, _ in msgs) / dur,
        "messages_per_s": len(msgs) / dur,
        "kbytes_per_s": sum(s for *_, s in msgs) / dur / 1e3,
        "dropped": (on["igtl"] or {}).get("dropped", {}),
    }


def _f(v: object, fmt: str = "{:.1f}") -> str:
    return "n/a" if v is None else fmt.format(v)


def run(args: argparse.Namespace) -> int:
    load0 = os.getloadavg()[0]
    try:
        r = asyncio.run(_bench(args.seconds, args.probe == "truth", args.start_timeout))
    except RuntimeError as exc:
        print(f"humantele bench igtl: {exc}", file=sys.stderr)
        return 1
    load = f"{load0:.1f} at start, {os.getloadavg()[0]:.1f} at the end"
    added = (
        None
        if r["cpu_off_percent"] is None or r["cpu_on_percent"] is None
        else r["cpu_on_percent"] - r["cpu_off_percent"]
    )
    rows = [
        ["follower CPU, OpenIGTLink off", f"{_f(r['cpu_off_percent'])} %"],
        ["follower CPU, serving one client", f"{_f(r['cpu_on_percent'])} %"],
        ["added CPU in the follower", f"{_f(added)} % of one core"],
        ["follower's child processes (video sources, sensing), off / on",
         f"{_f(r['cpu_children_off_percent'])} / {_f(r['cpu_children_on_percent'])} %"],
        ["follower tracker frames measured, off / on",
         f"{r['tracker_rate_off_hz']:.1f} / {r['tracker_rate_on_hz']:.1f} Hz"],
        ["ProbeToPatient latency p50 / p99 / max",
         f"{_f(r['pose'].get('p50_ms'))} / {_f(r['pose'].get('p99_ms'))} / "
         f"{_f(r['pose'].get('max_ms'))} ms ({r['pose']['n']} msgs)"],
        ["Image latency p50 / p99 / max",
         f"{_f(r['image'].get('p50_ms'))} / {_f(r['image'].get('p99_ms'))} / "
         f"{_f(r['image'].get('max_ms'))} ms ({r['image']['n']} msgs)"],
        ["received", f"{r['pose_rate_hz']:.1f} poses/s, {r['image_rate_hz']:.1f} images/s, "
                     f"{r['kbytes_per_s']:.0f} kB/s"],
        ["dropped by the server", json.dumps(r["dropped"]) if r["dropped"] else "none"],
    ]  # fmt: skip
    md = "\n".join([
        "## OpenIGTLink (`humantele bench igtl`)",
        "",
        machine_line(),
        f"Loopback session (follower + expert daemons, signaling; probe: {args.probe}),"
        f" {args.seconds:.0f} s measured per run once following; the follower without"
        " OpenIGTLink, then serving one client in the bench process that decodes every"
        " message (pyigtl), as Slicer would. Latency:"
        " from the tracker frame's / image's capture time to the client holding the decoded"
        " message (same machine, wall clock). Image: the follower's 640x480 US track, sent"
        f" at most 10 Hz. Machine load average during the runs: {load} (2 cores; above 2,"
        " other jobs were running and the figures carry their noise).",
        "",
        markdown_table(["figure", "value"], rows),
    ])  # fmt: skip
    print(md)
    publish(SECTION, md, {**r, "cpu_added_percent": added}, args)
    return 0

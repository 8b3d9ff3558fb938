"""``humantele bench hl2ss``: hl2ss's AHAT stream settings over a Wi-Fi link, speed against
accuracy.

For each stream setting (depth SAME with AB RAW, H.264 or H.265 at a bitrate) and each link
(bandwidth in Mbit/s, one-way delay): a child process serves simulated AHAT frames (the probe
moving in front of the headset) as the hl2ss app does, live-stamped at capture, through the
user-space link model (:mod:`humantele.tracking.hl2ss_link`: what the link cannot carry
waits, as in the app); this process is the follower's tracker camera: the hl2ss client
(newest frame, backlog bound) and the tracker, as fast as frames come. Figures per case: the
delivered frame rate (frames tracked or not, per second), frame age at the follower (capture
to the tracker's input; p50/p95), tracking error against the truth (median, p95 in mm and
deg; wrong: > 5 mm or > 5 deg), the follower's CPU (this process, % of one core: receive,
decode, track) and the connections the backlog bound dropped. H.26x frames are encoded ahead
with the app's packing by libx264/libx265 (the encoders are slower than the headset's
hardware one; the encoding is not what is measured), sent at their capture times.

``--spells``: the hand tracker's 5 Hz spells (1 s of every 3) in the default setting's case.
``--stall S``: the default setting at 80 Mbit/s with the link stalled S s (no byte, no close) 4 s
after its start: the stalls found, the reconnects, and the time from the stall's end to the
next frame at the tracker.
Writes docs/img/hl2ss_settings.png and the "hl2ss" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import time
from pathlib import Path

import numpy as np

from humantele.bench import pyplot, save_chart
from humantele.geometry import Pose, quat_from_axis_angle, quat_multiply
from humantele.report import DOCS_DIR, machine_line, markdown_table, write_section

WRONG_MM, WRONG_DEG = 5.0, 5.0
SETTINGS = {  # name -> (ab_profile, bitrate or None: hl2ss's default)
    "RAW": ("raw", None),
    "H.264 37.7 Mbit/s": ("h264_high", None),
    "H.264 15 Mbit/s": ("h264_high", 15_000_000),
    "H.265 18.9 Mbit/s": ("h265_main", None),
}
DEFAULT_SETTING = "H.264 37.7 Mbit/s"
LOOP_FRAMES = 90  # distinct rendered frames, looped (2 s at 45 Hz)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=10.0, help="per case")
    p.add_argument("--bandwidths", default="30,80,200", help="Mbit/s, comma-separated")
    p.add_argument("--delay-ms", type=float, default=3.0, help="one-way delay of the link")
    p.add_argument("--settings", default=",".join(SETTINGS), help="comma-separated names")
    p.add_argument("--spells", action="store_true", help="also the default through 5 Hz spells")
    p.add_argument(
        "--stall",
        type=float,
        default=0.0,
        metavar="S",
        help="also the default through a stall of S s (no byte, no close)",
    )
    p.add_argument("--no-write", action="store_true", help="print only")


def scene(n: int, seed: int = 4):
    """``n`` frames of the probe sweeping and turning (45 Hz) and their truths."""
    from humantele.tracking.sim import SimFrameConfig, SimFrameSource, default_sim_pose

    sim = SimFrameSource(SimFrameConfig(seed=seed))
    base = default_sim_pose()
    frames = []
    for k in range(n):
        a = 2 * math.pi * k / n
        q = quat_multiply(quat_from_axis_angle([0, 1, 0], 0.3 * math.sin(a)), base.quaternion)
        p = base.position + np.array([0.05 * math.sin(a), 0.02 * math.cos(2 * a), 0.0])
        frames.append(sim.render(Pose(p, q), t=k / 45.0))
    return frames


def encode_run(frames, profile_ab: int, bitrate: int, seconds: float, spells) -> list:
    """The frames the headset captures in ``seconds`` (``sensor_frames``), encoded as the app
    would for this setting (RAW: the same payload object per distinct frame)."""
    from humantele.tracking.hl2ss_codec import AhatEncoder, default_gop_size
    from humantele.tracking.hl2ss_protocol import GOP_SIZE_OPTION, AhatConfiguration
    from humantele.tracking.hl2ss_replay import EncodedFrame, sensor_frames

    cfg = AhatConfiguration(mode=0, profile_ab=profile_ab, bitrate=bitrate,
                            options={GOP_SIZE_OPTION: default_gop_size(profile_ab)})  # fmt: skip
    enc = AhatEncoder(cfg)
    raw_cache: dict[int, bytes] = {}
    out = []
    for k, t in sensor_frames(seconds + 2.0, spells):
        f = frames[k % len(frames)]
        if profile_ab == 0xFF:
            payload = raw_cache.get(k % len(frames))
            if payload is None:
                payload = raw_cache[k % len(frames)] = enc.payload(f.depth_mm, f.ir, 0)
            payload = payload[:-8] + int(k).to_bytes(8, "little")  # sensor ticks: the index
        else:
            payload = enc.payload(f.depth_mm, f.ir, k)
        out.append(EncodedFrame(t, payload, profile_ab))
    return out


def _serve(items, bandwidth: float, delay_s: float, stalls, conn) -> None:
    """Child: the replay server behind the link; sends the link's port and start time (the
    stalls' origin, monotonic s), runs until told."""
    from humantele.tracking.hl2ss_link import LinkConfig, TcpLinkRelay
    from humantele.tracking.hl2ss_replay import Hl2ssReplayServer

    with Hl2ssReplayServer([items], repeat=True, live=True) as srv:
        link = LinkConfig(bandwidth_mbps=bandwidth, delay_s=delay_s, stalls=stalls)
        with TcpLinkRelay(("127.0.0.1", srv.port), link) as relay:
            conn.send((relay.port, relay.t0))
            conn.recv()


def run_case(frames, items, ab_profile: str, bitrate: int | None, bandwidth: float,
             delay_s: float, seconds: float, stalls=()) -> dict:  # fmt: skip
    """One setting over one link (``stalls``: (start, length) s from the link's start): the
    follower's figures."""
    from humantele.tracking.hl2ss_source import Hl2ssFrameConfig, Hl2ssFrameSource
    from humantele.tracking.pipeline import Tracker
    from humantele.tracking.tool import load_tool

    ctx = multiprocessing.get_context("fork")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_serve, args=(items, bandwidth, delay_s, list(stalls), child),
                       daemon=True)  # fmt: skip
    proc.start()
    try:
        port, link_t0 = parent.recv()
        src = Hl2ssFrameSource(Hl2ssFrameConfig(
            host="127.0.0.1", port=port, mode=0, download_calibration=False, newest=True,
            ab_profile=ab_profile, bitrate=bitrate, read_timeout_s=2.0, connect_timeout_s=10.0,
            retry_s=0.2))  # fmt: skip
        tracker = Tracker(load_tool("probe_default"))
        for f in frames[:3]:  # its tables are built at the first frames: not measured
            tracker.process(f)
        tracker = Tracker(load_tool("probe_default"))
        src.open()
        src.read()  # the first frame (encoder start-up, connection) is not measured
        ages, errs, angs, arrivals = [], [], [], []
        n = wrong = 0
        c0, t0 = time.process_time(), time.monotonic()
        while time.monotonic() - t0 < seconds:
            g = src.read()
            if g is None:
                continue
            n += 1
            arrivals.append(time.monotonic())
            ages.append(time.monotonic() - g.device_time_s)
            truth = frames[src.last_sensor_ticks % len(frames)].T_camera_probe_true
            r = tracker.process(g)
            if r.T_camera_probe is None:
                continue
            dp, da = r.T_camera_probe.distance_to(truth)
            if dp * 1e3 > WRONG_MM or math.degrees(da) > WRONG_DEG:
                wrong += 1
            errs.append(dp * 1e3)
            angs.append(math.degrees(da))
        wall, cpu = time.monotonic() - t0, time.process_time() - c0
        src.close()
    finally:
        parent.send("stop")
        proc.join(10)
        if proc.is_alive():
            proc.kill()

    def pct(x, q):
        return float(np.percentile(x, q)) if len(x) else float("nan")

    return {"hz": n / wall, "age_p50_ms": pct(ages, 50) * 1e3, "age_p95_ms": pct(ages, 95) * 1e3,
            "mm_p50": pct(errs, 50), "mm_p95": pct(errs, 95), "deg_p50": pct(angs, 50),
            "deg_p95": pct(angs, 95), "tracked_pct": 100.0 * len(errs) / max(n, 1),
            "wrong": wrong, "cpu_pct": 100.0 * cpu / wall,
            "backlog_drops": src.dropped.get("backlog", 0), "stalls": src.stalls,
            "reconnects": src.reconnects, "back_after_stall_s": [
                next((a - end for a in arrivals if a >= end), float("nan"))
                for end in (link_t0 + s0 + length for s0, length in stalls)]}  # fmt: skip


def chart(results: list[tuple[str, float, dict]]) -> Path:
    plt = pyplot()
    import matplotlib.ticker

    fig, axes = plt.subplots(1, 2, figsize=(11, 5.0), dpi=110)
    names = list(dict.fromkeys(r[0] for r in results))
    marks = dict(zip(sorted({r[1] for r in results}), "os^DvP", strict=False))
    for name, colour in zip(names, [f"C{i}" for i in range(10)], strict=False):
        for n, bw, r in results:
            if n != name:
                continue
            label = f"{name}" if bw == min(b for m, b, _ in results if m == name) else None
            axes[0].plot(r["hz"], r["mm_p50"], marks[bw], color=colour, label=label, ms=7)
            axes[1].plot(r["age_p95_ms"], r["mm_p50"], marks[bw], color=colour, ms=7)
            for ax, x in ((axes[0], r["hz"]), (axes[1], r["age_p95_ms"])):
                ax.annotate(f"{bw:g}", (x, r["mm_p50"]), fontsize=7, xytext=(4, 3),
                            textcoords="offset points")  # fmt: skip
    axes[0].axvline(40, color="r", lw=0.8, ls=":")
    axes[1].axvline(60, color="r", lw=0.8, ls=":")
    for ax in axes:
        ax.axhline(1.0, color="r", lw=0.8, ls=":")
        ax.set_ylabel("tracking error, median, mm")
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
    axes[0].set_xlabel("frames delivered to the tracker, Hz (headset: 45)")
    axes[1].set_xlabel("frame age at the tracker, p95, ms (log)")
    axes[1].set_xscale("log")
    axes[1].xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    axes[1].xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    axes[1].set_xticks([10, 20, 50, 100, 200, 500, 1000])
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.suptitle("hl2ss AHAT settings over a Wi-Fi link (numbers: link Mbit/s; red: targets)",
                 fontsize=10)  # fmt: skip
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return save_chart(fig, DOCS_DIR / "img" / "hl2ss_settings.png")


def run(args: argparse.Namespace) -> int:
    from humantele.tracking.hl2ss_codec import PROFILE_NAMES, default_bitrate

    load0 = os.getloadavg()[0]
    bandwidths = [float(b) for b in args.bandwidths.split(",") if b]
    names = [s.strip() for s in args.settings.split(",") if s.strip()]
    unknown = [n for n in names if n not in SETTINGS]
    if unknown:
        print(f"bench hl2ss: unknown settings {unknown}; known: {', '.join(SETTINGS)}")
        return 2
    frames = scene(LOOP_FRAMES)
    # (setting, link Mbit/s, the hand tracker's 5 Hz spells, the link's stalls)
    cases = [(n, bw, [], []) for n in names for bw in bandwidths]
    if args.spells:
        cases.append((DEFAULT_SETTING, 80.0, [(t, t + 1.0) for t in range(1, 600, 3)], []))
    if args.stall > 0:
        cases.append((DEFAULT_SETTING, 80.0, [], [(4.0, args.stall)]))
    results, rows, stall_line = [], [], ""
    for name, bw, spells, stalls in cases:
        ab_profile, bitrate = SETTINGS[name]
        profile = PROFILE_NAMES[ab_profile]
        items = encode_run(frames, profile, bitrate or default_bitrate(profile), args.seconds,
                           spells)  # fmt: skip
        r = run_case(frames, items, ab_profile, bitrate, bw, args.delay_ms / 1e3, args.seconds,
                     stalls)  # fmt: skip
        label = name + (", 5 Hz spells 1 s in 3" if spells else "")
        if stalls:
            label = f"{name}, a {args.stall:g} s stall"
            back = r["back_after_stall_s"][0]
            stall_line = (f"Through a {args.stall:g} s stall (no byte, no close) 4 s after the "
                          f"link's start: {r['stalls']} stall(s) found, {r['reconnects']} "
                          f"reconnect(s), the next frame at the tracker {back:.2f} s after the "
                          "stall's end.")  # fmt: skip
            print(stall_line, flush=True)
        if not spells and not stalls:
            results.append((name, bw, r))
        row = [label, f"{bw:g}", f"{r['hz']:.1f}", f"{r['age_p50_ms']:.0f}",
               f"{r['age_p95_ms']:.0f}", f"{r['mm_p50']:.2f}", f"{r['mm_p95']:.2f}",
               f"{r['deg_p50']:.2f}", f"{r['deg_p95']:.2f}", f"{r['tracked_pct']:.0f}",
               r["wrong"], f"{r['cpu_pct']:.0f}", r["backlog_drops"]]  # fmt: skip
        rows.append(row)
        print(" | ".join(str(c) for c in row), flush=True)
    if args.no_write:
        return 0
    path = chart(results)
    table = markdown_table(["setting", "link Mbit/s", "delivered Hz", "age p50 ms", "p95",
                            "mm p50", "p95", "deg p50", "p95", "tracked %", "wrong",
                            "follower CPU %", "backlog drops"], rows)  # fmt: skip
    md = f"""## hl2ss AHAT settings over a Wi-Fi link

`humantele bench hl2ss --seconds {args.seconds:g} --bandwidths {args.bandwidths}`
({machine_line()} Load average {load0:.2f} at start.) Simulated AHAT frames of the probe
moving in front of the headset, served as hl2ss serves them at 45 Hz through a user-space
link ({args.delay_ms:g} ms one way; what the link cannot carry waits, as in the app) to the
follower's hl2ss client and tracker (newest frame; 3 frames in a row queued over 0.5 s drop
the connection: "backlog drops"). Age: capture to the tracker's input. CPU: the follower's
process (receive, decode, track), % of one core. docs/hololens.md picks the default from it.

![hl2ss settings: speed against accuracy](img/{path.name})

{table}
{stall_line}
"""
    print(f"wrote {write_section('hl2ss', md)} and {path}")
    return 0

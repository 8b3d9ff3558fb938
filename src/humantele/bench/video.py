"""``humantele bench video``: the video sources' figures.

Part ``link``: glass to glass over the link in the whole session
(:mod:`humantele.bench.video_link`). Part ``sources`` (the default):

- render cost of each sim source per frame at a few sizes (median and p90 ms, one OpenCV
  thread: the cost on one core), over the demo scene's moving probe;
- the frame counter read back after VP8 (libvpx set up as aiortc does) at a few bit rates:
  the share of frames whose counter reads exactly, with PSNR and SSIM of the decoded frames
  against their sources (the counter's rows left out) and the encoder's ms per frame.

Prints a table and, as the last line, one JSON object; writes the "video" section of
docs/benchmarks.md. Deterministic images (seeded); times depend on the machine.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from humantele.report import BENCHMARKS_MD, machine_line, markdown_table, write_section
from humantele.video.counter import patch_size, read_counter
from humantele.video.fidelity import psnr, ssim
from humantele.video.roundtrip import codec_round_trip
from humantele.video.scene import DemoScene
from humantele.video.sim_pov import SimPov, SimPovConfig
from humantele.video.sim_ultrasound import SimUltrasound, SimUltrasoundConfig

US_SIZES = [(320, 240), (640, 480), (800, 600)]
POV_SIZES = [(640, 360), (960, 540), (1280, 720)]
BIT_RATES = [100_000, 250_000, 500_000, 1_000_000]
DEFAULT_US, DEFAULT_POV = (640, 480), (960, 540)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from humantele.bench.video_link import add_link_arguments

    p.add_argument("part", nargs="?", default="sources", choices=["sources", "link"])
    p.add_argument("--frames", type=int, default=60, help="sources: frames per measurement")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print only the JSON summary line")
    p.add_argument("--no-write", action="store_true", help="do not update docs/benchmarks.md")
    add_link_arguments(p)


def make_source(kind: str, size: tuple[int, int], seed: int, scene: DemoScene):
    w, h = size
    if kind == "us":
        return SimUltrasound(SimUltrasoundConfig(width=w, height=h, seed=seed), scene)
    return SimPov(SimPovConfig(width=w, height=h), scene)


def render_frames(kind: str, size: tuple[int, int], n: int, seed: int):
    """``n`` frames of the demo scene at 20 fps of scene time; (frames, seconds per frame)."""
    t = {"now": 0.0}
    scene = DemoScene(clock=lambda: t["now"])
    src = make_source(kind, size, seed, scene)
    src.render(scene())  # warm up (first-use allocations)
    frames, times = [], []
    for i in range(n):
        t["now"] = i / 20.0
        snapshot = scene()
        t0 = time.perf_counter()
        frames.append(src.render(snapshot))
        times.append(time.perf_counter() - t0)
    return frames, np.asarray(times)


def counter_after_vp8(frames, bit_rate: int) -> dict:
    images = [f.image for f in frames]
    decoded, enc_s = codec_round_trip(images, "vp8", bit_rate)
    _, ch = patch_size()
    h, w = images[0].shape[:2]
    region = (ch, h, 0, w)
    pairs = list(zip(frames, decoded, strict=False))  # a lost frame would shorten decoded
    exact = sum(read_counter(d) == f.seq for f, d in pairs)
    return {
        "bit_rate": bit_rate,
        "frames": len(frames),
        "decoded": len(decoded),
        "read_exact_pct": 100.0 * exact / len(frames),
        "psnr_db": float(np.median([psnr(f.image, d, region) for f, d in pairs])),
        "ssim": float(np.median([ssim(f.image, d, region) for f, d in pairs])),
        "encode_ms": enc_s * 1e3,
    }


def run(args: argparse.Namespace) -> int:
    if args.part == "link":
        from humantele.bench.video_link import run_link

        return run_link(args)
    import cv2

    cv2.setNumThreads(1)
    n, seed = max(args.frames, 5), args.seed
    renders, rows = {}, []
    for kind, sizes in (("us", US_SIZES), ("pov", POV_SIZES)):
        for size in sizes:
            _, times = render_frames(kind, size, n, seed)
            r = {
                "median_ms": float(np.median(times) * 1e3),
                "p90_ms": float(np.percentile(times, 90) * 1e3),
            }
            renders[f"{kind} {size[0]}x{size[1]}"] = r
            rows.append([f"sim {kind}", f"{size[0]}x{size[1]}", f"{r['median_ms']:.2f}",
                         f"{r['p90_ms']:.2f}"])  # fmt: skip
            if not args.json:
                print(f"render {kind:3s} {size[0]:4d}x{size[1]:<4d} {r['median_ms']:6.2f} ms")
    counters, crow = {}, []
    for kind, size in (("us", DEFAULT_US), ("pov", DEFAULT_POV)):
        frames, _ = render_frames(kind, size, n, seed)
        for rate in BIT_RATES:
            c = counter_after_vp8(frames, rate)
            counters[f"{kind} {rate}"] = c
            crow.append([f"sim {kind} {size[0]}x{size[1]}", f"{rate // 1000}",
                         f"{c['read_exact_pct']:.0f}", f"{c['psnr_db']:.1f}", f"{c['ssim']:.3f}",
                         f"{c['encode_ms']:.1f}"])  # fmt: skip
            if not args.json:
                print(f"vp8 {kind:3s} {rate // 1000:5d} kbit/s: counter {c['read_exact_pct']:.0f} %"
                      f", PSNR {c['psnr_db']:.1f} dB, SSIM {c['ssim']:.3f}, "
                      f"encode {c['encode_ms']:.1f} ms")  # fmt: skip
    summary = {"part": "sources", "frames": n, "seed": seed, "render": renders, "vp8": counters}
    if not args.no_write:
        md = "\n\n".join(
            [
                "## Video sources",
                machine_line() + f" {n} frames per row, seed {seed}, `humantele bench video`.",
                "Render cost of the sim sources per frame (one OpenCV thread, the demo scene's "
                "probe sweeping; the US image at 20 fps and the POV at 25 fps beside the 1 kHz "
                "servo). Default sizes: US 640x480, POV 960x540.",
                markdown_table(["source", "size", "median ms", "p90 ms"], rows),
                "The frame counter (24 bits + 8-bit check, 8 px cells) after VP8 (libvpx, "
                "real-time settings as aiortc's; aiortc sends 250-1500 kbit/s), with PSNR and "
                "SSIM of the decoded frame against its source (grey, counter rows left out, "
                "median) and the encoder's time per frame:",
                markdown_table(
                    ["source", "kbit/s", "counter read %", "PSNR dB", "SSIM", "encode ms"], crow
                ),
            ]
        )
        write_section("video", md, BENCHMARKS_MD)
    print(json.dumps(summary))
    return 0

"""``humantele bench video``: the video sources' figures.

Part ``link``: glass to glass over the link in the whole session
(:mod:`humantele.bench.video_link`). Part ``render``: only the sim sources' render cost per
frame (wall and CPU ms, one OpenCV thread; quick, writes nothing: ``--frames`` sets the
length). Part ``quality``: the US image's latency and fidelity
against its bit rate and size on the live link (:mod:`humantele.bench.video_quality`). Part
``sources`` (the default):

- render cost of each sim source per frame at a few sizes (median and p90 ms, one OpenCV
  thread: the cost on one core; and the CPU ms per frame, which a busy machine does not
  inflate as much), over the demo scene's moving probe;
- the frame counter read back after VP8 at a few bit rates, through aiortc's own encoder and
  through ours (humantele.media.encoders): the share of frames whose counter reads exactly,
  with PSNR and SSIM of our decoded frames against their sources (the counter's rows left
  out) and our encoder's ms per frame.

Prints a table and, as the last line, one JSON object; writes the "video" section of
docs/benchmarks.md. Deterministic images (seeded); times depend on the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from humantele.bench import publish
from humantele.report import BENCHMARKS_MD, machine_line, markdown_table
from humantele.video.counter import patch_size, read_counter
from humantele.video.fidelity import psnr, ssim
from humantele.video.scene import DemoScene
from humantele.video.sim_pov import SimPov, SimPovConfig
from humantele.video.sim_ultrasound import SimUltrasound, SimUltrasoundConfig

US_SIZES = [(320, 240), (640, 480), (800, 600)]
POV_SIZES = [(640, 360), (960, 540), (1280, 720)]
BIT_RATES = [250_000, 500_000, 1_000_000, 1_500_000]
DEFAULT_US, DEFAULT_POV = (640, 480), (960, 540)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from humantele.bench.video_link import add_link_arguments
    from humantele.bench.video_quality import add_quality_arguments

    p.add_argument(
        "part", nargs="?", default="sources", choices=["sources", "render", "link", "quality"]
    )
    p.add_argument("--frames", type=int, default=60, help="sources: frames per measurement")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print only the JSON summary line")
    p.add_argument("--no-write", action="store_true", help="do not update docs/benchmarks.md")
    add_link_arguments(p)
    add_quality_arguments(p)


def make_source(kind: str, size: tuple[int, int], seed: int, scene: DemoScene):
    w, h = size
    if kind == "us":
        return SimUltrasound(SimUltrasoundConfig(width=w, height=h, seed=seed), scene)
    return SimPov(SimPovConfig(width=w, height=h), scene)


def render_frames(kind: str, size: tuple[int, int], n: int, seed: int, cpu: list | None = None):
    """``n`` frames of the demo scene at 20 fps of scene time; (frames, seconds per frame).
    ``cpu``: a list given gets the CPU seconds per frame (the process's, in the renders)."""
    t = {"now": 0.0}
    scene = DemoScene(clock=lambda: t["now"])
    src = make_source(kind, size, seed, scene)
    src.render(scene())  # warm up (first-use allocations)
    frames, times, spent = [], [], 0.0
    for i in range(n):
        t["now"] = i / 20.0
        snapshot = scene()
        c0, t0 = time.process_time(), time.perf_counter()
        frames.append(src.render(snapshot))
        times.append(time.perf_counter() - t0)
        spent += time.process_time() - c0
    if cpu is not None:
        cpu.append(spent / max(n, 1))
    return frames, np.asarray(times)


def render_costs(sizes, n: int, seed: int, echo: bool) -> tuple[dict, list]:
    """Render cost per frame of each (kind, size): ({name: figures}, table rows)."""
    renders, rows = {}, []
    for kind, size in sizes:
        cpu: list[float] = []
        _, times = render_frames(kind, size, n, seed, cpu)
        r = {
            "median_ms": float(np.median(times) * 1e3),
            "p90_ms": float(np.percentile(times, 90) * 1e3),
            "cpu_ms": cpu[0] * 1e3,
        }
        renders[f"{kind} {size[0]}x{size[1]}"] = r
        rows.append([f"sim {kind}", f"{size[0]}x{size[1]}", f"{r['median_ms']:.2f}",
                     f"{r['p90_ms']:.2f}", f"{r['cpu_ms']:.2f}"])  # fmt: skip
        if echo:
            print(f"render {kind:3s} {size[0]:4d}x{size[1]:<4d} {r['median_ms']:6.2f} ms "
                  f"(p90 {r['p90_ms']:.2f}), CPU {r['cpu_ms']:.2f} ms per frame")  # fmt: skip
    return renders, rows


def through_encoder(encoder, frames) -> tuple[list[np.ndarray], float]:
    """The sim ``frames`` sent as the follower sends them (I420, 20 fps) through ``encoder``
    (aiortc's encoder interface) and aiortc's VP8 decoder: (decoded BGR images, encoder s per
    frame)."""
    import fractions

    import av
    import cv2
    from aiortc.codecs.vpx import Vp8Decoder, vp8_depayload
    from aiortc.jitterbuffer import JitterFrame

    decoder = Vp8Decoder()
    out, spent = [], 0.0
    for i, f in enumerate(frames):
        vf = av.VideoFrame.from_ndarray(cv2.cvtColor(f.image, cv2.COLOR_BGR2YUV_I420), "yuv420p")
        vf.pts, vf.time_base = i * 4500, fractions.Fraction(1, 90000)
        t0 = time.perf_counter()
        payloads, ts = encoder.encode(vf)
        spent += time.perf_counter() - t0
        data = b"".join(vp8_depayload(p) for p in payloads)
        out += [d.to_ndarray(format="bgr24") for d in decoder.decode(JitterFrame(data, ts))]
    return out, spent / max(len(frames), 1)


def counter_after_vp8(frames, bit_rate: int) -> dict:
    """The counter read back, PSNR and SSIM after our VP8 encoder at ``bit_rate`` (bit/s,
    fixed), and the counter after aiortc's own VP8 encoder at the same rate."""
    from aiortc.codecs.vpx import Vp8Encoder as AiortcVp8Encoder

    from humantele.media.config import BitrateConfig
    from humantele.media.encoders import Vp8Encoder

    kbps = bit_rate // 1000
    ours, enc_s = through_encoder(Vp8Encoder(BitrateConfig(start_kbps=kbps, min_kbps=kbps,
                                                           max_kbps=kbps)), frames)  # fmt: skip
    theirs = AiortcVp8Encoder()
    theirs.target_bitrate = bit_rate  # aiortc clamps it to 250-1500 kbit/s
    aiortc_decoded, _ = through_encoder(theirs, frames)
    _, ch = patch_size()
    h, w = frames[0].image.shape[:2]
    region = (ch, h, 0, w)
    pairs = list(zip(frames, ours, strict=False))  # a lost frame would shorten decoded

    def read_pct(decoded) -> float:
        exact = sum(read_counter(d) == f.seq for f, d in zip(frames, decoded, strict=False))
        return 100.0 * exact / len(frames)

    return {
        "bit_rate": bit_rate,
        "frames": len(frames),
        "decoded": len(ours),
        "read_exact_pct": read_pct(ours),
        "aiortc_read_exact_pct": read_pct(aiortc_decoded),
        "psnr_db": float(np.median([psnr(f.image, d, region) for f, d in pairs])),
        "ssim": float(np.median([ssim(f.image, d, region) for f, d in pairs])),
        "encode_ms": enc_s * 1e3,
    }


def run(args: argparse.Namespace) -> int:
    if args.part == "link":
        from humantele.bench.video_link import run_link

        return run_link(args)
    if args.part == "quality":
        from humantele.bench.video_quality import run_quality

        return run_quality(args)
    import cv2

    cv2.setNumThreads(1)
    load = os.getloadavg()[0]
    n, seed = max(args.frames, 5), args.seed
    if args.part == "render":
        sizes = [("us", DEFAULT_US), ("pov", DEFAULT_POV)]
        renders, _ = render_costs(sizes, n, seed, not args.json)
        print(json.dumps({"part": "render", "frames": n, "seed": seed, "load": load,
                          "render": renders}))  # fmt: skip
        return 0
    sizes = [("us", s) for s in US_SIZES] + [("pov", s) for s in POV_SIZES]
    renders, rows = render_costs(sizes, n, seed, not args.json)
    counters, crow = {}, []
    for kind, size in (("us", DEFAULT_US), ("pov", DEFAULT_POV)):
        frames, _ = render_frames(kind, size, n, seed)
        for rate in BIT_RATES:
            c = counter_after_vp8(frames, rate)
            counters[f"{kind} {rate}"] = c
            crow.append([f"sim {kind} {size[0]}x{size[1]}", f"{rate // 1000}",
                         f"{c['aiortc_read_exact_pct']:.0f}", f"{c['read_exact_pct']:.0f}",
                         f"{c['psnr_db']:.1f}", f"{c['ssim']:.3f}",
                         f"{c['encode_ms']:.1f}"])  # fmt: skip
            if not args.json:
                print(f"vp8 {kind:3s} {rate // 1000:5d} kbit/s: counter {c['read_exact_pct']:.0f} %"
                      f" (aiortc's encoder {c['aiortc_read_exact_pct']:.0f} %), PSNR "
                      f"{c['psnr_db']:.1f} dB, SSIM {c['ssim']:.3f}, "
                      f"encode {c['encode_ms']:.1f} ms")  # fmt: skip
    summary = {"part": "sources", "frames": n, "seed": seed, "render": renders, "vp8": counters}
    md = "\n\n".join(
        [
            "## Video sources",
            machine_line() + f" {n} frames per row, seed {seed}, `humantele bench video`; "
            f"load average {load:.1f} at the start (above 1.5 the times are provisional).",
            "Render cost of the sim sources per frame (one OpenCV thread, the demo scene's "
            "probe sweeping; the US image at 20 fps and the POV at 25 fps beside the 1 kHz "
            "servo). Default sizes: US 640x480, POV 960x540.",
            markdown_table(["source", "size", "median ms", "p90 ms", "CPU ms"], rows),
            "The frame counter (24 bits + 8-bit check, 8 px cells) read back after VP8, "
            "the frames sent as the follower sends them (I420, 20 fps) and decoded by "
            "aiortc's decoder: through aiortc's own VP8 encoder (its libvpx settings: "
            "temporal denoiser and encode breakout on) and through ours "
            "(`humantele.media.encoders`: both off), at a fixed bit rate; with PSNR and "
            "SSIM of our decoded frame against its source (grey, counter rows left out, "
            "median) and our encoder's time per frame:",
            markdown_table(
                [
                    "source",
                    "kbit/s",
                    "counter read % (aiortc's encoder)",
                    "counter read % (ours)",
                    "PSNR dB",
                    "SSIM",
                    "encode ms",
                ],
                crow,
            ),  # fmt: skip
        ]
    )
    publish("video", md, summary, args, BENCHMARKS_MD, always_json=True)
    return 0

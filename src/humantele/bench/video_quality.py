"""``humantele bench video quality``: the US image's speed against its quality, on the live link.

For each US image size and bit rate (fixed: ``start = min = max``, so REMB does not move it) a
follower in a child process (this module run as a script) sends both tracks as the daemon does
(sim sources in its video process, the demo scene's probe sweeping over the kidney, our
encoders; the POV at its defaults) over a real aiortc link on loopback to an expert link in
this process, for ``--seconds``:

- latency, capture to decoded at the expert (p50/p95 ms; the frame counter and the clock sync,
  as in ``bench video link``), over the frames after the first 2 s;
- PSNR (dB) and SSIM of every ``EVERY``-th decoded US frame against the very frame the
  follower handed its encoder (grey, the counter's rows left out; the child saves those);
- the bit rate sent (RTP payload bytes of the US track per second) and the frames per second
  decoded.

It charts SSIM and latency against the bit rate sent, one line per size
(``docs/img/video_speed_quality.png``), and writes the "video-quality" section of
docs/benchmarks.md. Prints a row per point and, last, one JSON object.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from humantele.bench import publish, pyplot, save_chart
from humantele.report import BENCHMARKS_MD, machine_line, markdown_table
from humantele.runtime.signal_child import signal_child
from humantele.runtime.stats import percentile_ms

SECTION = "video-quality"
CHART = Path(BENCHMARKS_MD).parent / "img" / "video_speed_quality.png"
SIZES = [(320, 240), (640, 480), (800, 600)]
RATES_KBPS = [150, 300, 600, 1200, 2500]
EVERY = 10  # every 10th US frame is compared with its source
WARMUP_S = 2.0
TOKEN = "bench-video-quality"
HEADER = ["US size", "kbit/s set", "kbit/s sent", "US fps", "latency p50 / p95 ms",
          "PSNR dB", "SSIM", "frames compared", "load"]  # fmt: skip


def add_quality_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--rates", default=",".join(map(str, RATES_KBPS)), help="quality: kbit/s, comma-separated"
    )
    p.add_argument(
        "--sizes", default=",".join(f"{w}x{h}" for w, h in SIZES),
        help="quality: US sizes WxH, comma-separated",
    )  # fmt: skip


# --- the follower (a child process) -----------------------------------------------------------


async def follower(url: str, room: str, out: Path, width: int, height: int, kbps: int,
                   seconds: float) -> None:  # fmt: skip
    """Send both tracks for ``seconds`` after the link is up; save every EVERY-th US frame's
    luma as handed to the encoder (``out/<seq>.npy``) and the bytes sent (``out/sent.json``)."""
    from humantele.media.config import FollowerVideoConfig
    from humantele.media.receiver import luma_plane
    from humantele.media.sender import VideoSender
    from humantele.transport import LinkConfig, PeerLink
    from humantele.video.scene import DEFAULT_PATIENT, DemoScene
    from humantele.video.sim_ultrasound import SimUltrasoundConfig

    config = FollowerVideoConfig(
        enabled=True, record_us_hz=0.0, record_pov_hz=0.0,
        us=SimUltrasoundConfig(width=width, height=height),
        us_bitrate={"start_kbps": kbps, "min_kbps": kbps, "max_kbps": kbps},
    )  # fmt: skip

    class Saving(VideoSender):
        def _on_sent(self, name: str, cf: Any) -> None:
            super()._on_sent(name, cf)
            if name == "us" and cf.seq % EVERY == 0:
                np.save(out / f"{cf.seq}.npy", luma_plane(cf.frame)[: cf.height, : cf.width])

    sender = Saving(config, None, None, DEFAULT_PATIENT)
    link = PeerLink(
        "follower",
        LinkConfig(signaling_url=url, room=room, token=TOKEN),
        media=lambda pc, role: sender.attach(pc),
    )
    scene = DemoScene()
    await asyncio.to_thread(sender.open)
    sender.start(asyncio.get_running_loop())
    run = asyncio.ensure_future(link.run())

    async def world() -> None:  # the sim world's snapshots, as the follower's tick publishes
        while True:
            sender.publish_scene(scene())
            await asyncio.sleep(0.01)

    tick = asyncio.ensure_future(world())
    try:
        await link.wait_state("connected", timeout=60)
        t0 = time.monotonic()
        await asyncio.sleep(seconds)
        stats = await sender._senders["us"].getStats()
        sent = next(s for s in stats.values() if getattr(s, "type", "") == "outbound-rtp")
        (out / "sent.json").write_text(
            json.dumps({"bytes": sent.bytesSent, "s": time.monotonic() - t0})
        )
    finally:
        tick.cancel()
        await link.close()
        await asyncio.to_thread(sender.close)
        run.cancel()


# --- the expert (this process) ----------------------------------------------------------------


async def point(width: int, height: int, kbps: int, seconds: float) -> dict[str, Any]:
    """One size and bit rate: a follower child, the expert here; the figures."""
    from humantele.media.config import ExpertVideoConfig
    from humantele.media.receiver import VideoReceiver, luma_plane
    from humantele.signaling.messages import TOKEN_ENV
    from humantele.signaling.server import SignalConfig, SignalingServer
    from humantele.transport import LinkConfig, PeerLink
    from humantele.video.fidelity import psnr, ssim

    server = SignalingServer(SignalConfig(port=0), TOKEN)
    await server.start()
    holder: dict[str, VideoReceiver] = {}
    expert = PeerLink(
        "expert",
        LinkConfig(signaling_url=server.url, room="q", token=TOKEN),
        media=lambda pc, role: holder["rx"].prepare(pc),
    )
    rx = holder["rx"] = VideoReceiver(ExpertVideoConfig(enabled=True), expert.clock, expert.now)
    with tempfile.TemporaryDirectory(prefix="humantele-bench-quality-") as tmp:
        out = Path(tmp)
        child = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "humantele.bench.video_quality", server.url, "q", tmp,
            str(width), str(height), str(kbps), str(seconds),
            env={**os.environ, TOKEN_ENV: TOKEN}, stdout=asyncio.subprocess.DEVNULL,
        )  # fmt: skip
        run = asyncio.ensure_future(expert.run())
        decoded: dict[int, np.ndarray] = {}
        ages: list[tuple[float, float]] = []
        try:
            while child.returncode is None:
                try:
                    f = await rx.wait_frame("us", timeout=1.0)
                except TimeoutError:
                    continue
                if f.age_s is not None:
                    ages.append((f.t_received, f.age_s))
                if f.seq is not None and f.seq % EVERY == 0 and f.seq not in decoded:
                    decoded[f.seq] = luma_plane(f.frame)[: f.height, : f.width].copy()
            await child.wait()
        finally:
            signal_child(child, signal.SIGTERM)
            await child.wait()
            await expert.close()
            await rx.close()
            run.cancel()
            await server.stop()
        sent = json.loads((out / "sent.json").read_text()) if (out / "sent.json").exists() else {}
        region = (32, height, 0, width)  # below the counter's rows
        scores = []
        for seq, y in decoded.items():
            src = out / f"{seq}.npy"
            if src.exists():
                ref = np.load(src)
                if ref.shape == y.shape:
                    scores.append((psnr(ref, y, region), ssim(ref, y, region)))
    t_first = ages[0][0] if ages else 0.0
    a = np.asarray([age for t, age in ages if t - t_first >= WARMUP_S])
    span = (ages[-1][0] - t_first) if len(ages) > 1 else 0.0
    p = np.asarray([s for s, _ in scores])
    return {
        "size": f"{width}x{height}",
        "kbps_set": kbps,
        "kbps_sent": round(8e-3 * sent["bytes"] / sent["s"]) if sent.get("s") else None,
        "fps": round((len(ages) - 1) / span, 1) if span > 0 else None,
        "age_p50_ms": percentile_ms(a, 50, ndigits=1),
        "age_p95_ms": percentile_ms(a, 95, ndigits=1),
        "psnr_db": round(float(np.median(p[np.isfinite(p)])), 2) if p.size else None,
        "ssim": round(float(np.median([s for _, s in scores])), 4) if scores else None,
        "compared": len(scores),
        "load": round(os.getloadavg()[0], 1),
    }


def _sizes(text: str) -> list[tuple[int, int]]:
    out = []
    for part in text.split(","):
        w, h = (int(v) for v in part.lower().split("x"))
        out.append((w, h))
    return out


def chart(points: list[dict[str, Any]], path: Path) -> None:
    plt = pyplot()

    fig, (q, lat) = plt.subplots(1, 2, figsize=(10, 4.2), dpi=110)
    for size in dict.fromkeys(p["size"] for p in points):
        mine = [p for p in points if p["size"] == size and p["kbps_sent"]]
        x = [p["kbps_sent"] for p in mine]
        q.plot(x, [p["ssim"] for p in mine], "o-", label=f"US {size}")
        (line,) = lat.plot(x, [p["age_p95_ms"] for p in mine], "o-", label=f"US {size} p95")
        lat.plot(x, [p["age_p50_ms"] for p in mine], "o--", color=line.get_color(), alpha=0.6)
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    for ax in (q, lat):
        ax.set_xscale("log")
        ax.set_xticks(sorted({p["kbps_set"] for p in points}))
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("US bit rate sent (kbit/s)")
        ax.grid(True, which="both", alpha=0.3)
    q.set_ylabel("SSIM, decoded vs source frame (grey)")
    q.set_title("Quality of the US image over the link")
    lat.set_ylabel("capture to decoded (ms): p95 solid, p50 dashed")
    lat.axhline(100, color="gray", ls=":", lw=0.8)
    lat.set_title(
        f"Latency of the US image (load {points[0]['load']:g}-{max(p['load'] for p in points):g})"
    )
    q.legend(fontsize=8)
    lat.legend(fontsize=8)
    fig.tight_layout()
    save_chart(fig, path)


def run_quality(args: argparse.Namespace) -> int:
    sizes = _sizes(args.sizes)
    rates = [int(r) for r in args.rates.split(",")]
    load0 = os.getloadavg()[0]
    points = []
    for w, h in sizes:
        for kbps in rates:
            r = asyncio.run(point(w, h, kbps, args.seconds))
            points.append(r)
            if not args.json:
                print(json.dumps(r), flush=True)
    if not args.no_write:
        chart(points, CHART)
    rows = [[p["size"], p["kbps_set"], p["kbps_sent"], p["fps"],
             f"{p['age_p50_ms']} / {p['age_p95_ms']}", p["psnr_db"], p["ssim"],
             p["compared"], p["load"]] for p in points]  # fmt: skip
    md = "\n\n".join(
        [
            "## Video: speed against quality (`humantele bench video quality`)",
            machine_line() + f" Load average {load0:.1f} at the start (a figure taken at a "
            "load above 1.5 is provisional).",
            f"Per US size and bit rate (fixed), {args.seconds:g} s of a live link on loopback:"
            " a follower process (sim sources in its video process, the demo scene, our "
            "encoders, the POV at its defaults) and the expert's receiver in the bench "
            "process. Latency: capture to decoded (counter and clock sync), after the first "
            f"{WARMUP_S:g} s. PSNR and SSIM (median): every {EVERY}th decoded US frame "
            "against the frame the follower gave its encoder, grey, the counter's rows left "
            "out. kbit/s sent: RTP payload of the US track.",
            f"![speed against quality](img/{CHART.name})",
            markdown_table(HEADER, rows),
        ]
    )
    summary = {"part": "quality", "points": points}
    publish(SECTION, md, summary, args, BENCHMARKS_MD, always_json=True)
    return 0


if __name__ == "__main__":  # the follower child of point()
    url, room, tmp, w, h, kbps, secs = sys.argv[1:8]
    asyncio.run(follower(url, room, Path(tmp), int(w), int(h), int(kbps), float(secs)))

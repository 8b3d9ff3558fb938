"""The two pages' figures (issue 11 §4), from one ``humantele demo`` with the video tracks on
(``configs/demo.toml``: the follower's sim ultrasound and POV over WebRTC), each page open in
headless Chromium in turn for ``seconds``; the console once per video transport
(``designs``, default both: ``webcodecs``, ``jpeg``; docs/console.md says why the WebRTC
transport the earlier runs also measured was removed), interleaved over
``rounds`` rounds (default 2) in the same run, a fresh page each time (issue 19 §1):

- the console: ultrasound glass to glass as the page shows it (the follower's capture time to
  the page's draw call, for the frame whose counter the page read back from its own canvas),
  what the console adds over the expert's receipt (the receiver's decode to the draw call),
  the page's frame rate; the expert's receipt alone (capture to decode, the receiver's);
- the headset page: the follower's receipt of a pose to the page's draw call of it (the
  page's echoes, see :mod:`humantele.follower.feed`);
- for each, CPU (% of one core) of the browser (all its processes), the expert daemon, its
  servo, the follower daemon and the follower's child processes (video, sensing), with the
  servo's rate and overruns over the same window, and the machine's load average.

    python tests/browser/netns.py pages_bench --arg seconds=30 --arg write=1

(``write=1``: the tables go to docs/benchmarks.md, sections ``pages`` and ``console``,
and the chart of latency against frames drawn to docs/img/console_video.png.)
"""

from __future__ import annotations

import asyncio
import os
import time
from pathlib import Path

from session_helpers import descendants  # tests/session (stage.py puts it on the path)
from stage import console_url, page_url

from humantele.runtime.stats import process_cpu_seconds

REPO = Path(__file__).resolve().parents[3]
LIVE = "(() => { const h = headset.hud(); return ['green', 'amber', 'red'].includes(h.cue)" \
       " && h.guide.live; })()"  # fmt: skip


def browser_pids() -> set[int]:
    """Chromium's processes (this runner's descendants named chromium)."""
    out = set()
    for pid in descendants(os.getpid()):
        try:
            if "chromium" in Path(f"/proc/{pid}/comm").read_text():
                out.add(pid)
        except OSError:
            pass
    return out


class Window:
    """CPU seconds of the processes that matter, and the servo's counters, at one instant."""

    def __init__(self, demo) -> None:
        e, f = demo.stats("expert"), demo.stats("follower")
        self.t = time.monotonic()
        self.load = os.getloadavg()[0]
        kids = descendants(f["pid"])
        self.cpu = {
            "browser": _sum(browser_pids()),
            "expert": process_cpu_seconds(e["pid"]) or 0.0,
            "servo": process_cpu_seconds(e["servo_pid"]) or 0.0,
            "follower": process_cpu_seconds(f["pid"]) or 0.0,
            "follower children": _sum(kids),
        }
        self.overruns = e.get("servo_overruns", 0)
        self.servo_hz = e.get("servo_rate_hz")
        self.measurements = f.get("measurements", 0)  # tracker frames measured so far
        self.pose_age_p99 = f.get("pose_age_recent_p99_ms")  # the expert's pose, last 10 s
        self.state_age_p99 = e.get("state_age_p99_ms")  # the follower's state on arrival

    def to(self, later: Window) -> dict:
        dt = later.t - self.t
        cpu = {k: round(100.0 * (later.cpu[k] - v) / dt, 1) for k, v in self.cpu.items()}
        return {"seconds": round(dt, 1), "cpu_percent": cpu, "servo_rate_hz": later.servo_hz,
                "servo_overruns": later.overruns - self.overruns,
                "tracker_hz": round((later.measurements - self.measurements) / dt, 1),
                "pose_age_p99_ms": later.pose_age_p99, "state_age_p99_ms": later.state_age_p99,
                "load": [round(self.load, 2), round(later.load, 2)]}  # fmt: skip


def _sum(pids) -> float:
    return sum(process_cpu_seconds(p) or 0.0 for p in pids)


DESIGNS = ("webcodecs", "jpeg")  # the default first (the pages section takes it)


async def console_phase(ctx, demo, seconds: float, transport: str | None = None,
                        shot: str = "bench_console") -> dict:  # fmt: skip
    url = console_url(demo.stats("expert"))
    if transport:
        base, _, frag = url.partition("#")
        url = f"{base}?transport={transport}#{frag}"
    page = await ctx.page(url, width=1440, height=900)
    await ctx.until(page, "window.consoleApp && consoleApp.frames.us > 10"
                    " && consoleApp.frames.pov > 10", 120)  # fmt: skip
    got = await page.evaluate("consoleApp.transport")
    if transport and got != transport:
        raise AssertionError(f"asked for the {transport} transport, the page has {got}")
    f0 = await page.evaluate("({...consoleApp.frames})")
    w0 = Window(demo)
    await asyncio.sleep(seconds)
    w1 = Window(demo)
    f1 = await page.evaluate("({...consoleApp.frames})")
    await asyncio.sleep(1.2)  # the expert's stats file is written every 0.5 s
    e = demo.stats("expert")
    await ctx.shot(page, shot)
    await ctx.close_page(page)
    dt = w1.t - w0.t
    video = e.get("video") or {}
    return {
        **w0.to(w1),
        "transport": got,
        "page_fps": {t: round((f1[t] - f0[t]) / dt, 1) for t in f0},
        "received_fps": {t: (video.get(t) or {}).get("fps") for t in ("us", "pov")},
        "console": {t: e["console"][t] for t in ("us", "pov")},
        "receiver": video,
    }


async def designs_phase(ctx, demo, seconds: float, designs, rounds: int) -> list[dict]:
    """Each design's console window, interleaved: round 1 all designs, round 2..."""
    out = []
    for r in range(rounds):
        for d in designs:
            ph = await console_phase(ctx, demo, seconds, d, shot=f"bench_console_{d}_{r}")
            ph["round"] = r
            out.append(ph)
            ctx.mark(f"console {d} round {r}")
    return out


async def headset_phase(ctx, demo, seconds: float) -> dict:
    ctx.headset_frame_ms = 0  # the page at Chromium's own rate: its figures are the bench's
    page = await ctx.page(page_url(demo.stats("follower")), headset=True, width=1280, height=800)
    await ctx.until(page, LIVE, 90)
    fr0 = await page.evaluate("headset.frames")
    w0 = Window(demo)
    await asyncio.sleep(seconds)
    w1 = Window(demo)
    fr1 = await page.evaluate("headset.frames")
    feed = demo.stats("follower").get("feed") or {}
    await ctx.shot(page, "bench_headset")
    await ctx.close_page(page)
    return {**w0.to(w1), "page_fps": round((fr1 - fr0) / (w1.t - w0.t), 1), "feed": feed}


async def run(ctx) -> dict:
    seconds = float(ctx.args.get("seconds", 30.0))
    busy = None
    if ctx.args.get("busy"):  # one core kept busy by another process at normal priority
        import subprocess
        import sys

        busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        return await _run(ctx, seconds, busy is not None)
    finally:
        if busy is not None:
            busy.kill()
            busy.wait()


async def _run(ctx, seconds: float, busy: bool) -> dict:
    demo = await ctx.demo("--config", str(REPO / "configs" / "demo.toml"), "--duration", "3600")

    def ready(e, f):
        following = f.get("calibrated") and f.get("link_state") == "connected"
        us = (e.get("video") or {}).get("us") or {}
        return following and (e.get("console") or {}).get("url") and us.get("frames", 0) > 20

    await demo.wait("calibrated, following, video received", ready, timeout=180)
    ctx.mark("demo ready")
    data: dict = {"seconds": seconds, "started_load": round(os.getloadavg()[0], 2), "busy": busy}
    designs = ctx.args.get("designs", ",".join(DESIGNS))
    designs = [d for d in str(designs).split(",") if d]
    rounds = int(ctx.args.get("rounds", 2))
    data["designs"] = await designs_phase(ctx, demo, seconds, designs, rounds)
    data["console"] = data["designs"][0]  # the default design's first window
    ctx.mark("console")
    data["headset"] = await headset_phase(ctx, demo, seconds)
    ctx.mark("headset")
    data["load_note"] = load_note(data)
    if ctx.args.get("write") and busy:
        write_designs(data)  # the pages section is the quiet scene's
    elif ctx.args.get("write"):
        write_benchmarks(data)
    return data


def load_note(data: dict) -> str:
    """What the load says about the figures. The scene's own processes count in it (the
    demo, and Chromium rendering in software on the CPU), so it rises during the windows;
    other work is what was there before the demo started (2 cores: above 1.5)."""
    before = data["started_load"]
    if data.get("busy"):
        return (
            f"One core kept busy by another process at normal priority (`python -c 'while"
            f" True: pass'`) from before the demo started; load {before:g} at the start."
        )
    hi = max(x for ph in (*data["designs"], data["headset"]) for x in ph["load"])
    if before <= 1.5:
        return (f"Load {before:g} before the demo started, up to {hi:g} during the windows:"
                " the scene's own processes (the browser renders on the CPU); nothing else"
                " ran.")  # fmt: skip
    return (f"Load {before:g} before the demo started, up to {hi:g} during the windows: other"
            " work was running, so these figures are provisional (rerun on a quiet"
            " machine).")  # fmt: skip


CPU_COLUMNS = ["window", "browser", "expert", "servo", "follower", "follower children",
               "servo Hz", "servo overruns", "load"]  # fmt: skip


def _ms(v) -> str:
    return "-" if v is None else f"{v:.1f}"


def write_benchmarks(data: dict) -> None:
    from humantele.report import machine_line, markdown_table, write_section

    c, h = data["console"], data["headset"]
    us, pov, feed = c["console"]["us"], c["console"]["pov"], h["feed"]
    rows = [
        ["console: US glass to glass (capture at the follower to the page's draw, counter "
         "read from the page's canvas), p50 / p95 ms",
         f"{_ms(us['capture_to_draw_p50_ms'])} / {_ms(us['capture_to_draw_p95_ms'])}"
         f" ({us['counter_read']} frames; counter unread {us['counter_unread']}, "
         f"unmatched {us['counter_unmatched']})"],
        ["console: US, what the console adds (the expert's receipt to the page's draw), "
         "p50 / p95 ms",
         f"{_ms(us['seen_to_draw_p50_ms'])} / {_ms(us['seen_to_draw_p95_ms'])}"],
        ["console: US, the expert's receipt of the same frames (capture at the follower to"
         " decoded at the expert), p50 / p95 ms",
         f"{_ms(us['capture_to_seen_p50_ms'])} / {_ms(us['capture_to_seen_p95_ms'])}"],
        ["console: POV glass to glass, p50 / p95 ms",
         f"{_ms(pov['capture_to_draw_p50_ms'])} / {_ms(pov['capture_to_draw_p95_ms'])}"],
        ["console: page draws, US / POV fps", f"{c['page_fps']['us']} / {c['page_fps']['pov']}"],
        ["headset page: pose receipt (follower) to the page's draw call, p50 / p95 ms",
         f"{_ms(feed.get('draw_latency_p50_ms'))} / {_ms(feed.get('draw_latency_p95_ms'))}"
         f" ({feed.get('echoes')} echoes)"],
        ["headset page: frames drawn per second", f"{h['page_fps']}"],
    ]  # fmt: skip
    cpu_rows = []
    for name, ph in (("console open", c), ("headset page open", h)):
        cp = ph["cpu_percent"]
        cpu_rows.append([name, cp["browser"], cp["expert"], cp["servo"], cp["follower"],
                         cp["follower children"], _ms(ph["servo_rate_hz"]), ph["servo_overruns"],
                         f"{ph['load'][0]} / {ph['load'][1]}"])  # fmt: skip
    text = (
        "## The pages: console and headset (`python tests/browser/netns.py pages_bench --arg"
        " seconds=S --arg write=1`)\n\n"
        f"One `humantele demo --config configs/demo.toml` (both daemons on sim devices, the"
        " follower's sim ultrasound 640 x 480 and POV over WebRTC, VP8, loopback), calibrated"
        f" and following; then the console open in headless Chromium ({c['transport']}, 1440 x"
        f" 900, compositing in software as without a GPU) for {data['seconds']:g} s, then the"
        " headset page (1280 x 800, no WebXR; a second Chromium compositing on SwiftShader's"
        f" emulated GPU, as a headset's GPU would) for {data['seconds']:g} s. Latencies are on"
        " one machine's monotonic clock (the"
        " follower's capture times mapped onto the expert's by the link's clock sync);"
        " a draw is the page's draw call, echoed to its daemon with the time between draw"
        " and echo taken off (the echo's transit, under 1 ms on loopback, is included).\n\n"
        + markdown_table(["figure", "value"], rows)
        + "\n\nCPU in % of one core over the same windows (the browser: all its processes;"
        " the follower's children: its video process and sensing process), the 1 kHz"
        " servo's mean rate since it started and its overruns (periods over 1.5 ms) in the"
        " window, and the machine's 1-minute load average at the start / end of the window."
        f" {load_note(data)}\n\n" + markdown_table(CPU_COLUMNS, cpu_rows) + "\n\n" + machine_line()
    )
    write_section("pages", text)
    write_designs(data)


def summarize_designs(data: dict) -> dict[str, dict]:
    """Per design, over its windows: US and POV glass to glass p50/p95 (the median of the
    windows' figures), frames drawn per second, received per second, CPU of expert and
    browser (mean), and the loads."""
    from statistics import mean, median

    out: dict[str, dict] = {}
    for ph in data["designs"]:
        d = out.setdefault(ph["transport"], {"windows": []})
        d["windows"].append(ph)
    for d in out.values():
        ws = d["windows"]

        def med(track, key, ws=ws):
            xs = [w["console"][track][key] for w in ws if w["console"][track][key] is not None]
            return round(median(xs), 1) if xs else None

        for t in ("us", "pov"):
            d[t] = {
                "p50_ms": med(t, "capture_to_draw_p50_ms"),
                "p95_ms": med(t, "capture_to_draw_p95_ms"),
                "drawn_fps": round(mean(w["page_fps"][t] for w in ws), 1),
                "received_fps": round(mean((w["received_fps"][t] or 0) for w in ws), 1),
                "counted": sum(w["console"][t]["counter_read"] for w in ws),
            }
        d["cpu_expert"] = round(mean(w["cpu_percent"]["expert"] for w in ws), 1)
        d["cpu_browser"] = round(mean(w["cpu_percent"]["browser"] for w in ws), 1)
        d["tracker_hz_min"] = min(w.get("tracker_hz", 0.0) for w in ws)
        ages = [w.get("pose_age_p99_ms") for w in ws if w.get("pose_age_p99_ms") is not None]
        d["pose_age_p99_ms"] = max(ages) if ages else None
        d["overruns_per_20s"] = max(20.0 * w["servo_overruns"] / w["seconds"] for w in ws)
        d["loads"] = [w["load"] for w in ws]
    return out


NOMINAL_FPS = {"us": 20, "pov": 25}  # the demo's sim sources (configs/demo.toml)


def write_designs(data: dict) -> None:
    from humantele.report import machine_line, markdown_table, write_section

    summary = summarize_designs(data)
    rows = []
    for name, d in summary.items():
        us, pov = d["us"], d["pov"]
        rows.append([
            name, f"{_ms(us['p50_ms'])} / {_ms(us['p95_ms'])}",
            f"{us['drawn_fps']} of {us['received_fps']}",
            f"{_ms(pov['p50_ms'])} / {_ms(pov['p95_ms'])}",
            f"{pov['drawn_fps']} of {pov['received_fps']}",
            d["cpu_expert"], d["cpu_browser"], d["tracker_hz_min"], _ms(d["pose_age_p99_ms"]),
            f"{d['overruns_per_20s']:.1f}", len(d["windows"]),
            "; ".join(f"{a}-{b}" for a, b in d["loads"]),
        ])  # fmt: skip
    busy = bool(data.get("busy"))
    chart = plot_designs(summary, "console_video_busy.png" if busy else "console_video.png")
    title = "one core busy" if busy else "quiet"
    text = (
        f"## Console video, {title}: the three transports, A/B (`python tests/browser/netns.py"
        f" pages_bench --arg seconds=S{' --arg busy=1' if busy else ''} --arg write=1`)\n\n"
        "One `humantele demo --config configs/demo.toml` (the run of the pages section when"
        " both are written together); the console opened afresh for each transport in turn"
        f" ({data['seconds']:g} s windows, the designs interleaved round by round). Glass to"
        " glass: the follower's capture to the page's draw of the frame whose counter the"
        " page read back from its canvas (the median of the windows' p50 and p95). Frames"
        " drawn per second by the page, of those the expert received per second (the sim"
        f" sources make US {NOMINAL_FPS['us']} and POV {NOMINAL_FPS['pov']} a second). CPU in"
        " % of one core, means over the windows. Load: the 1-minute load average at the"
        f" start-end of each window. Tracker: frames the follower measured per second (the"
        f" lowest window; 45 due). Pose age: the expert's pose on arrival at the follower, p99"
        f" of the last 10 s of each window (the worst window). Servo overruns: periods over"
        f" 1.5 ms, per 20 s (the worst window). {load_note(data)}\n\n"
        + markdown_table(
            [
                "transport",
                "US p50 / p95 ms",
                "US drawn / received fps",
                "POV p50 / p95 ms",
                "POV drawn / received fps",
                "expert CPU %",
                "browser CPU %",
                "tracker Hz",
                "pose age p99 ms",
                "servo overruns / 20 s",
                "windows",
                "load",
            ],
            rows,
        )  # fmt: skip
        + f"\n\n![latency against frames drawn]({chart})\n\n"
        + machine_line()
    )
    write_section("console_busy" if busy else "console", text)


def plot_designs(summary: dict, filename: str = "console_video.png") -> str:
    """docs/img/<filename>: US and POV p50 (marker) to p95 (bar) glass to glass
    against frames drawn per second, one colour per design; its path from docs/."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    colours = {"webcodecs": "tab:green", "jpeg": "tab:red"}
    for ax, t in zip(axes, ("us", "pov"), strict=True):
        for name, d in summary.items():
            x, p50, p95 = d[t]["drawn_fps"], d[t]["p50_ms"], d[t]["p95_ms"]
            if p50 is None or p95 is None:
                continue
            c = colours.get(name, "k")
            for w in d["windows"]:  # each window's p95, faint
                w95 = w["console"][t]["capture_to_draw_p95_ms"]
                if w95 is not None:
                    ax.plot(w["page_fps"][t], w95, "x", color=c, alpha=0.4, ms=5)
            ax.plot([x, x], [p50, p95], color=c, lw=2)
            ax.plot(x, p50, "o", color=c, label=f"{name} (p50 to p95)")
            ax.plot(x, p95, "_", color=c, ms=14, mew=2)
        ax.axvline(NOMINAL_FPS[t], color="0.6", ls=":", lw=1)
        ax.set_xlim(0, NOMINAL_FPS[t] + 2)
        ax.set_title(f"{t.upper()} ({NOMINAL_FPS[t]} fps sent)")
        ax.set_xlabel("frames drawn per second")
        ax.set_ylabel("capture to draw (ms)")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, title="median of windows; x: each window's p95",
                   title_fontsize=7)  # fmt: skip
    fig.tight_layout()
    path = REPO / "docs" / "img" / filename
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return f"img/{filename}"

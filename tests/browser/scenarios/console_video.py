"""The console on the follower's received video (``humantele demo --config
configs/demo.toml``, scan 1 ends after :data:`SCAN_LENGTH_S`: sim ultrasound and POV over
WebRTC), with the default transport
(WebCodecs) and then JPEG (issue 19 §1): no console work per frame while no page is open; both
pictures drawn; freeze keeps the frame on screen and a capture saves that very frame (its
counter, its pixels); once the page has closed the console takes no frame again.

The same demo is the shared demo run of tests/session (``session_helpers.demo_run``: the
command's ``--json`` summary and a terminal's Ctrl-C, its recording and the analysis, the
video's export, OpenIGTLink for 3D Slicer): started as a terminal starts it (``--json
--record --igtl-port 0``, in its own process group), it is ended by Ctrl-C once the console's
visits are done, scan 1 has been recorded long enough to analyse and an OpenIGTLink client has
had the probe. One whole video session for both (issue 33: the suite's CPU budget)."""

from __future__ import annotations

import asyncio
import base64
import json
import threading
import time
from pathlib import Path

from console_views import pixels, result
from session_helpers import IgtlClient, scan_recorded
from stage import console_url, scaled

from procgroups import descendants

REPO = Path(__file__).resolve().parents[3]
CANVAS_PNG = "document.getElementById('us').toDataURL('image/png')"
FROZEN_SETTLED = (
    "consoleApp.frozen && consoleApp.cine.length > 0 && !consoleApp.cineInFlight"
    " && consoleApp.pendingCine == null"
)
CONTACT_MEAN = 8.0  # the US canvas's mean grey with an image (no contact: black, ~1)
# US frames received with no page open, over which the console must take none (1.5 s of the
# demo's 20 fps; was a fixed 3 s, 60 frames on a quiet machine, fewer on a loaded one)
IDLE_FRAMES = 30


def console_frames(demo) -> dict:
    c = demo.stats("expert").get("console") or {}
    return {"us": (c.get("us") or {}).get("frames"), "pov": (c.get("pov") or {}).get("frames"),
            "subscribed": c.get("subscribed"), "clients": c.get("clients")}  # fmt: skip


def received(expert_stats: dict) -> int:
    """US frames the expert has received (its video receiver's count)."""
    return ((expert_stats.get("video") or {}).get("us") or {}).get("frames") or 0


async def idle(demo, frames: int = IDLE_FRAMES) -> dict:
    """The console's frame counters while the expert receives ``frames`` US frames with no page
    open (and the receiver's count): each one a frame the console could have taken."""
    a, ra = console_frames(demo), received(demo.stats("expert"))
    await demo.wait(f"{frames} more US frames received", lambda e, f: received(e) >= ra + frames)
    b, rb = console_frames(demo), received(demo.stats("expert"))
    return {"before": a, "after": b, "received": [ra, rb]}


async def visit(ctx, demo, transport: str | None) -> dict:
    """Open the console (asking ``transport``), freeze, capture, close: what it showed."""
    url = console_url(demo.stats("expert"))
    if transport:
        base, _, frag = url.partition("#")
        url = f"{base}?transport={transport}#{frag}"
    name = transport or "default"
    page = await ctx.page(url, width=1440, height=900)
    # Both pictures drawn, the POV at least once: at the link's start a loaded machine can
    # read as a thin link, and the POV, lowered first, was off (a frame every 5 s) for 40 s
    # (2026-11-29, a fresh venv's suite run: this step took 38 s instead of 5).
    await ctx.until_progress(
        page,
        "window.consoleApp && consoleApp.frames.us > 10 && consoleApp.frames.pov > 0",
        "window.consoleApp ? [consoleApp.frames.us, consoleApp.frames.pov] : null",
        stall_s=90,
    )
    out: dict = {"transport": await page.evaluate("consoleApp.transport")}
    ctx.mark(f"{name}: drawing")
    out["pixels"] = {t: await pixels(page, t) for t in ("us", "pov")}
    out["open"] = console_frames(demo)
    await ctx.shot(page, f"console_video_{name}_live")
    # Freeze while the probe is in contact (the picture has an image, not the black of no
    # contact): the frame on screen stays; capture it. The sim novice lifts now and then, and
    # on a loaded machine the picture trails the force by seconds: a frozen picture that came
    # out empty is let go, and it is tried again until a deadline (not a count of tries).
    deadline = asyncio.get_running_loop().time() + scaled(180.0)
    while not out.get("frozen"):
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError(f"{name}: never frozen on a picture of contact")
        await ctx.until(page, "(consoleApp.state?.force?.measured_n ?? 0) > 3", 120)
        if (await pixels(page, "us"))["mean"] > CONTACT_MEAN:
            await page.click("#freeze")
            # the freeze answered with the cine's index, and the frame the page shows settled
            # (one it had not been sent is asked of the cine: wait for it to be drawn)
            await ctx.until(page, FROZEN_SETTLED, 20)
            if (await pixels(page, "us"))["mean"] > CONTACT_MEAN:
                out["frozen"] = True
                break
            await page.click("#freeze")  # live again
            await ctx.until(page, "!consoleApp.frozen", 5)
        await asyncio.sleep(0.3)
    ctx.mark(f"{name}: frozen in contact")
    await asyncio.sleep(0.5)  # frames keep coming: none may replace the frozen one
    out["shown"] = await page.evaluate("consoleApp.shown")
    png = await page.evaluate(CANVAS_PNG)
    out["png"] = f"shown_us_{name}.png"
    (ctx.out / out["png"]).write_bytes(base64.b64decode(png.split(",", 1)[1]))
    await page.click("#capture")
    out["capture"] = await result(ctx, page, "capture", 1)
    out["shown_after"] = await page.evaluate("consoleApp.shown")
    await ctx.shot(page, f"console_video_{name}_frozen")
    await page.evaluate("document.getElementById('freeze').click()")
    await ctx.until(page, "!consoleApp.frozen", 5)
    await ctx.close_page(page)
    await demo.wait("the page gone", lambda e, f: not console_frames(demo)["subscribed"], 30)
    return out


async def watch(demo, rec_dir: Path, seen: set[int], recorded: list[bool]) -> None:
    """While the demo runs: its processes (``seen``), and whether scan 1 has been recorded
    long enough to analyse (``recorded[0]``; the follower's recording is read until then)."""
    while demo.proc.returncode is None:
        seen |= descendants(demo.proc.pid)  # the daemons, the servo, their children
        if not recorded[0]:
            recorded[0] = await asyncio.to_thread(scan_recorded, rec_dir / "demo.follower.mcap")
        await asyncio.sleep(0.5)


SCAN_LENGTH_S = 30.0  # scan 1 of the shared demo (session_helpers.SCAN_S, 10 s, is analysed)


def demo_config(out: Path) -> Path:
    """configs/demo.toml with scan 1 of ``SCAN_LENGTH_S``: the demo outlasts the console's
    visits (a minute or more under load), and the shared run's export and analysis read scan
    1 only, whose length they need not pay for."""
    unset = "# length_s = 60.0"
    expert = (REPO / "configs" / "expert.toml").read_text()
    assert unset in expert, "configs/expert.toml's [expert.scans] changed: update demo_config"
    (out / "expert.toml").write_text(expert.replace(unset, f"length_s = {SCAN_LENGTH_S}", 1))
    demo = (REPO / "configs" / "demo.toml").read_text()
    for name in ("expert", "follower"):
        src = str(out / "expert.toml") if name == "expert" else str(REPO / "configs/follower.toml")
        demo = demo.replace(f'{name}_config = "configs/{name}.toml"', f'{name}_config = "{src}"')
    assert str(out / "expert.toml") in demo, "configs/demo.toml changed: update demo_config"
    (out / "demo.toml").write_text(demo)
    return out / "demo.toml"


async def run(ctx) -> dict:
    rec_dir = ctx.out / "rec"
    rec_dir.mkdir()
    demo = await ctx.demo(
        "--config", str(demo_config(ctx.out)), "--duration", "900", "--json",
        "--record", str(rec_dir / "demo.mcap"), "--igtl-port", "0", own_group=True,
    )  # fmt: skip
    stop = threading.Event()
    igtl = IgtlClient(demo.lines, stop)  # 3D Slicer's side, on the address the demo prints
    igtl.start()
    seen: set[int] = set()
    recorded = [False]
    watcher = asyncio.create_task(watch(demo, rec_dir, seen, recorded))
    try:
        data = await console_visits(ctx, demo)
        # The shared demo run's end: once scan 1 is recorded and the client is done (not
        # waited for if no address was printed), a terminal's Ctrl-C.
        deadline = time.monotonic() + scaled(180.0)
        while demo.proc.returncode is None and time.monotonic() < deadline:
            if recorded[0] and not igtl.waiting:
                break
            await asyncio.sleep(0.5)
        seen |= descendants(demo.proc.pid)
        t_stop = time.monotonic()
        returncode = await demo.ctrl_c()
        stop_s = time.monotonic() - t_stop
    finally:
        stop.set()
        watcher.cancel()
        await asyncio.to_thread(igtl.join, 70)
    out = demo.stdout()
    lines = out.strip().splitlines()
    try:
        summary = json.loads(lines[-1]) if lines else {}
    except ValueError:
        summary = {}
    data["demo_run"] = {
        "returncode": returncode, "summary": summary, "out": out, "err": "".join(demo.lines),
        "status": demo.lines, "seen": sorted(seen), "stop_s": stop_s, "igtl": igtl.result,
        "recorded": recorded[0],
    }  # fmt: skip
    return data


async def console_visits(ctx, demo) -> dict:
    """The console's checks: idle, the two visits, idle again."""

    def ready(e, f):
        us = (e.get("video") or {}).get("us") or {}
        return (e.get("console") or {}).get("url") and us.get("frames", 0) > 20

    await demo.wait("video received", ready, timeout=240)
    ctx.mark("video received")
    data: dict = {"idle_before": await idle(demo)}
    for transport in ctx.args.get("transports", [None, "jpeg"]):
        data[transport or "default"] = await visit(ctx, demo, transport)
        ctx.mark(f"visit {transport or 'default'}")
    data["idle_after"] = await idle(demo)
    return data

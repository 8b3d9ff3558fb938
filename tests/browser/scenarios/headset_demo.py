"""``humantele demo`` (both daemons on sim devices) with the headset page open: the page is
served, calibrates and follows; the feed's added latency (pose receipt to the page's draw
call) over ``seconds`` of following, from the page's echoes."""

from __future__ import annotations

import asyncio

from headset_views import capture
from stage import page_url

LIVE = "['green', 'amber', 'red'].includes(h.cue) && h.guide.live && headset.state.model"


async def hud_when(ctx, page, condition: str, timeout: float = 60.0) -> dict:
    js = f"(() => {{ const h = headset.hud(); return ({condition}) ? h : null; }})()"
    return await ctx.until(page, js, timeout)


async def run(ctx) -> dict:
    seconds = float(ctx.args.get("seconds", 5.0))
    demo = await ctx.demo("--duration", "900")
    await demo.wait("the headset page", lambda e, f: (f.get("feed") or {}).get("page_url"))
    page = await ctx.page(page_url(demo.stats("follower")))
    data: dict = {"calibrating_seen": []}
    for _ in range(300):  # the sim technician's presses, as the page shows them
        h = await page.evaluate("headset.hud()")
        if h["cue"] != "calibrating":
            if data["calibrating_seen"] or h["guide"]["live"]:
                break
        elif h["headline"] not in data["calibrating_seen"]:
            data["calibrating_seen"].append(h["headline"])
            if len(data["calibrating_seen"]) == 1 or "3 of 4" in h["headline"]:
                await ctx.shot(page, "demo_calibrating")  # a picture for the README
        await asyncio.sleep(0.1)
    await demo.wait("calibrated and following", lambda e, f: f.get("calibrated")
                    and f.get("link_state") == "connected", timeout=90)  # fmt: skip
    data["following"] = await hud_when(ctx, page, LIVE)
    try:  # a picture once the novice has caught up (not needed for the figures)
        await hud_when(ctx, page, f"{LIVE} && parseFloat(h.mm) < 25", timeout=30)
    except AssertionError:
        pass
    data["view"] = await capture(ctx, page, "demo_following")
    before = (demo.stats("follower").get("feed") or {}).get("echoes", 0)
    f0 = await page.evaluate("headset.frames")
    await asyncio.sleep(seconds)
    data["page_fps"] = round((await page.evaluate("headset.frames") - f0) / seconds, 1)
    follower = demo.stats("follower")
    data["feed"] = follower.get("feed")
    data["echoes_during"] = data["feed"]["echoes"] - before
    data["pose_age_p50_ms"] = follower.get("pose_age_p50_ms")
    data["cpu_percent_follower"] = follower.get("cpu_percent")
    return data

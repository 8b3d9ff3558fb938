"""``humantele demo --record`` with the sonographer's console open: both videos play, the
state and the force plot are live, the scan button stops and starts scans, freeze + cine +
calipers + annotation + capture work and are recorded, a second console is refused, and the
page shows everything as not live once the daemons are gone. Screenshots for the README."""

from __future__ import annotations

import asyncio

from console_views import image_point, measure, pixels, result, scroll_cine

from humantele.recording import role_path
from humantele.recording.reader import read_recording


def expert_console(demo) -> dict:
    return demo.stats("expert").get("console") or {}


async def state(page, expr: str):
    return await page.evaluate(f"(() => {{ const s = consoleApp.state; return {expr}; }})()")


async def run(ctx) -> dict:
    record = ctx.out / "rec"
    demo = await ctx.demo("--duration", "900", "--record", str(record))
    await demo.wait("the console", lambda e, f: expert_console(demo).get("url"), timeout=90)
    url = expert_console(demo)["url"]
    page = await ctx.page(url, width=1440, height=900)
    data: dict = {"url": url}

    # 1. Both videos play: frames drawn, pictures change, not black.
    await ctx.until(
        page, "window.consoleApp && consoleApp.frames.us > 10 && consoleApp.frames.pov > 10", 90
    )
    a = {t: await pixels(page, t) for t in ("us", "pov")}
    await asyncio.sleep(1.0)
    b = {t: await pixels(page, t) for t in ("us", "pov")}
    data["pixels"] = {"before": a, "after": b}
    f0 = await page.evaluate("({...consoleApp.frames})")
    await asyncio.sleep(2.0)
    f1 = await page.evaluate("({...consoleApp.frames})")
    data["page_fps"] = {t: round((f1[t] - f0[t]) / 2.0, 1) for t in f0}
    await ctx.shot(page, "console_demo_start")  # the received tracks, before calibration

    # 2. The session as the page shows it (calibration may still be going on: the checks of
    # the force plot with a moving force are in test_console_page.py).
    await ctx.until(page, "consoleApp.state && consoleApp.state.link.state === 'connected'", 60)
    data["state_live"] = await page.evaluate("consoleApp.state")
    data["plot_draws"] = await page.evaluate("consoleApp.plot.draws")
    await ctx.shot(page, "console_live")

    # 3. The scan button: start a scan, stop it, start the next (recorded by the expert).
    scripted = await page.evaluate("consoleApp.state.scan")
    if scripted:  # the demo's scripted scan already runs: stop it first
        await page.click("#scan")
        await ctx.until(page, "consoleApp.state.scan === null", 60)
    await page.click("#scan")
    await ctx.until(page, "consoleApp.state.scan !== null", 60)
    first = await page.evaluate("consoleApp.state.scan")
    await page.click("#scan")
    await ctx.until(page, "consoleApp.state.scan === null", 60)
    await page.click("#scan")
    await ctx.until(page, f"consoleApp.state.scan === {first + 1}", 60)
    data["scan_button"] = await page.text_content("#scan")
    data["scans_clicked"] = [first, first + 1]

    # 4. Freeze, scroll back, caliper, annotation, capture.
    await page.click("#freeze")
    await ctx.until(page, "consoleApp.cine.length > 5", 15)
    n = await page.evaluate("consoleApp.cine.length")
    seq = await scroll_cine(ctx, page, n // 2)
    data["cine"] = {"frames": n, "shown": seq, "time": await page.text_content("#cine-time")}
    shown = await page.evaluate("consoleApp.shown")
    w, h = shown["width"], shown["height"]
    await page.click("#tool-caliper")
    data["caliper"] = await measure(ctx, page, (0.45 * w, 0.25 * h), (0.45 * w, 0.85 * h))
    await page.click("#tool-note")
    x, y = await image_point(page, 0.6 * w, 0.45 * h)
    await page.mouse.click(x, y)
    await page.keyboard.type("lower pole, R kidney")
    await page.keyboard.press("Enter")
    data["annotation"] = await result(ctx, page, "annotation", 1)
    await page.click("#capture")
    data["capture"] = await result(ctx, page, "capture", 1)
    await ctx.shot(page, "console_frozen")
    await page.evaluate("document.getElementById('freeze').click()")  # live again (a DOM
    # click: playwright's scroll-into-view step once hung for 30 s on a loaded machine)
    await ctx.until(page, "!consoleApp.frozen && consoleApp.frames.us > 0", 5)

    # 5. A second console is refused (and counted); the first one goes on.
    second = await ctx.page(url, width=800, height=600)
    await asyncio.sleep(2.0)
    data["second_state"] = await second.evaluate("consoleApp.state === null")
    await ctx.close_page(second)
    data["console_stats"] = expert_console(demo)

    # 6. The daemons gone: nothing on the page is live.
    await demo.stop()
    await ctx.until(page, "document.body.dataset.conn === 'lost'", 15)
    await asyncio.sleep(0.5)
    data["lost_overlay"] = await page.evaluate("!document.getElementById('us-stale').hidden")
    await ctx.shot(page, "console_lost")
    rec = read_recording(role_path(record, "expert"))
    data["recorded_scans"] = rec.samples("/expert/scan")
    data["recorded_console"] = rec.samples("/expert/console")
    return data

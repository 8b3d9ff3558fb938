"""The sonographer's console served from this process over real sim video (the ultrasound
phantom and the POV, rendered in threads) and a scripted session: the videos play, the force
plot moves, the buttons reach the session, freeze + cine + calipers measure the known pixel
spacing, annotations and captures are saved, stale video and a lost link are shown as such and
clear again, and bad pages are refused and counted."""

from __future__ import annotations

import math
import threading
import time

from console_views import pixels, use_frozen_tools

from humantele.expert.console import SourceFrames
from humantele.video.scene import DemoScene
from humantele.video.sim_pov import SimPov, SimPovConfig
from humantele.video.sim_ultrasound import SimUltrasound, SimUltrasoundConfig


class PausableFrames(SourceFrames):
    """Sim sources in threads; ``paused`` holds the latest frame (as a dead link would)."""

    def __init__(self, sources) -> None:
        super().__init__(sources)
        self.paused = False
        self.demand = self

    def latest(self, track: str):
        if self.paused:
            return self._held.get(track)
        self._held = {t: super(PausableFrames, self).latest(t) for t in ("us", "pov")}
        return self._held.get(track)

    def _notify(self, track: str, frame) -> None:  # paused: no new frame reaches the console
        if not self.paused:
            super()._notify(track, frame)


class ScriptedSession:
    """A session whose force breathes (measured 4 +- 2 N at 0.5 Hz, rendered a third of it),
    whose link can be cut, and which remembers the sonographer's commands."""

    def __init__(self) -> None:
        self.recorder = None
        self.scan = None
        self.scans = 0
        self.clutch = False
        self.link = "connected"
        self.commands: list = []
        self.t0 = time.monotonic()
        self.lock = threading.Lock()

    def snapshot(self) -> dict:
        t = time.monotonic() - self.t0
        fm = 4.0 + 2.0 * math.sin(2 * math.pi * 0.5 * t)
        up = self.link == "connected"
        return {
            "link": {"state": self.link, "pose_age_ms": 35.0 if up else 4200.0},
            "calibration": {"state": "calibrated", "landmark": None, "last": "done"},
            "alignment": {"mm": 3.4, "deg": 2.1} if up else None,
            "servo": {"alive": True, "rate_hz": 1000.0, "fault": ""},
            "recording": {"on": True, "error": None, "written": 1000},
            "scan": self.scan,
            "clutch": {"on": self.clutch, "engaged": self.clutch},
            "force": {"measured_n": fm, "rendered_n": fm / 3.0, "contact": True},
        }

    def pose_at(self, t: float):
        return {"position": [0.1, 0.02, 0.05], "quaternion": [0.0, 0.0, 0.0, 1.0]}

    def start_scan(self) -> int:
        self.scans += 1
        self.scan = self.scans
        self.commands.append(["scan", "start"])
        return self.scan

    def stop_scan(self) -> None:
        self.scan = None
        self.commands.append(["scan", "stop"])

    def set_clutch(self, on: bool) -> None:
        self.clutch = on
        self.commands.append(["clutch", on])


async def run(ctx) -> dict:
    scene = DemoScene()
    frames = PausableFrames(
        {
            "us": SimUltrasound(SimUltrasoundConfig(fps=10.0), scene),
            "pov": SimPov(SimPovConfig(fps=10.0, width=640, height=360), scene),
        }
    )
    session = ScriptedSession()
    server = await ctx.console(frames, session)
    data: dict = {}
    page = await ctx.page(server.url, width=1280, height=800)

    # 1. Both videos play; the force plot moves.
    await ctx.until(
        page, "window.consoleApp && consoleApp.frames.us > 5 && consoleApp.frames.pov > 5", 90
    )
    a = {t: await pixels(page, t) for t in ("us", "pov")}
    await ctx.until(page, "consoleApp.frames.us > 12 && consoleApp.frames.pov > 12", 60)
    b = {t: await pixels(page, t) for t in ("us", "pov")}
    data["pixels"] = {"before": a, "after": b}
    await ctx.until(page, "consoleApp.plot.samples.length > 40", 30)
    data["force_samples"] = await page.evaluate("consoleApp.plot.samples.map(s => s[1])")
    data["live_info"] = await page.text_content("#us-info")
    data["counters"] = await page.evaluate(
        "({...consoleApp.counters, masked: !document.getElementById('us-counter').hidden,"
        " scale: consoleApp.depthScale.labels, scale_h: consoleApp.depthScale.canvas.clientHeight,"
        " image_h: document.getElementById('us').height})"
    )
    await ctx.shot(page, "console_page_live")

    # 2. The buttons reach the session, and the page follows its state.
    await page.click("#scan")
    await ctx.until(page, "consoleApp.state.scan === 1", 10)
    data["scan_text"] = await page.text_content("#scan")
    await page.click("#clutch")
    await ctx.until(page, "consoleApp.state.clutch.on === true", 10)
    await page.click("#scan")
    await ctx.until(page, "consoleApp.state.scan === null", 10)
    data["commands"] = list(session.commands)

    # 3. Freeze, scroll back, caliper between known image pixels, annotation, capture.
    tools = await use_frozen_tools(
        ctx, page, 10, lambda n: n // 3, ((0.30, 0.30), (0.62, 0.80)), (0.55, 0.45),
        "lower pole, right kidney", "console_page_frozen",
    )  # fmt: skip
    data.update(tools)
    frames_live = await page.evaluate("consoleApp.frames.us")
    await ctx.until(page, f"consoleApp.frames.us > {frames_live + 3}", 20)

    # 4. Video stops and the link drops: shown as not live; then it comes back.
    frames.paused = True
    session.link = "disconnected"
    await ctx.until(page, "!document.getElementById('us-stale').hidden"
                    " && !document.getElementById('pov-stale').hidden", 15)  # fmt: skip
    await ctx.until(page, "document.getElementById('chip-link').dataset.level === 'bad'", 10)
    data["stale"] = {
        "us": await page.text_content("#us-stale"),
        "info": await page.text_content("#us-info"),
        "link": await page.text_content("#chip-link"),
        "align": await page.text_content("#chip-align"),
        "bar": await page.text_content("#fbar-value"),
    }
    await ctx.shot(page, "console_page_stale")
    frames.paused = False
    session.link = "connected"
    await ctx.until(page, "document.getElementById('us-stale').hidden"
                    " && document.getElementById('pov-stale').hidden", 15)  # fmt: skip
    data["recovered_link"] = await page.text_content("#chip-link")

    # 5. A second console is refused; a page of another site cannot open the socket.
    second = await ctx.page(server.url, width=640, height=480)
    await ctx.wait("the second console refused", lambda: server.refused["second_console"] > 0)
    data["second_has_state"] = await second.evaluate("consoleApp.state !== null")
    await ctx.close_page(second)
    other = await ctx.other_site()
    data["cross_origin"] = await other.evaluate(
        f"""() => new Promise(res => {{
          const ws = new WebSocket('ws://127.0.0.1:{server.port}/ws');
          ws.onopen = () => res('open'); ws.onerror = () => res('refused'); }})"""
    )
    data["malformed_sent"] = await page.evaluate(
        """() => { const ws = consoleApp.ws; ws.send('nonsense'); ws.send('{"type":"fire"}');
                   ws.send(JSON.stringify({type: 'caliper', seq: 1, a: [0, 0], b: ['x', 0]}));
                   return 3; }"""
    )
    await ctx.wait("the nonsense counted", lambda: server.refused["malformed"] >= 3)

    # 6. Without the run's key (a stale bookmark, another local program): the page says why.
    lost = "!document.getElementById('lost').hidden && document.getElementById('lost').textContent"
    nokey = await ctx.page(server.address, width=1280, height=800)
    data["no_key"] = await ctx.until(nokey, lost, 15)
    await ctx.shot(nokey, "console_page_no_key")
    await ctx.close_page(nokey)
    wrong = await ctx.page(f"{server.address}#key=not-this-run-s-key", width=1280, height=800)
    data["wrong_key"] = await ctx.until(wrong, f"/wrong/.test(({lost}) || '') && ({lost})", 15)
    data["wrong_key_address"] = await wrong.evaluate("location.href")
    await ctx.close_page(wrong)
    data["keyed_address"] = await page.evaluate("location.href")
    data["still_live"] = await page.evaluate("consoleApp.frames.us")
    data["stats"] = server.stats()
    data["captures"] = sorted(p.name for p in (ctx.out / "captures").iterdir())
    await ctx.close_page(page)
    frames.stop()
    return data

"""The headset page against a feed this scenario publishes to: known poses, every cue state,
the calibration prompt, bad input from pages, a closed tab. Deterministic: nothing moves
unless the scenario publishes it."""

from __future__ import annotations

import asyncio
import math
import time

import numpy as np
from headset_views import BAD_INPUT_JS, CROSS_ORIGIN_JS, capture, next_frames

from humantele.follower.feed import model_fields
from humantele.follower.sim_human import SimPatient, probe_down_quat
from humantele.geometry import Pose, quat_from_axis_angle, quat_multiply
from humantele.haptics.ellipsoid import Ellipsoid

# The virtual probe: on the sim patient's abdomen, beam into it, tilted and turned so that a
# wrong rotation (or quaternion order) would draw the handle somewhere else.
PATIENT = SimPatient()
TILT = quat_from_axis_angle((1.0, 0.0, 0.0), math.radians(25))
TURN = quat_from_axis_angle((0.0, 0.0, 1.0), math.radians(60))
TOP = PATIENT.T_world_body.apply([0.05, PATIENT.config.half_height_m, 0.03])
VIRTUAL = Pose(TOP, quat_multiply(probe_down_quat((0.0, 1.0, 0.0)), quat_multiply(TILT, TURN)))


def offset(pose: Pose, mm: float, deg: float) -> Pose:
    """``pose`` moved ``mm`` along world x+z and turned ``deg`` about its beam's normal."""
    d = np.array([1.0, 0.0, 1.0]) / math.sqrt(2.0) * mm / 1000.0
    turn = quat_from_axis_angle((1.0, 0.0, 0.0), math.radians(deg))
    return Pose(pose.position + d, quat_multiply(pose.quaternion, turn))


class Publisher:
    """Publishes the virtual probe and the tracked probe at 100 Hz while ``running``; each
    virtual pose is new (a 1 um step), as the expert's are, so the page echoes them."""

    def __init__(self, feed) -> None:
        self.feed = feed
        self.real = offset(VIRTUAL, 20.0, 8.0)
        self.age_ms = 20.0
        self.clutch = False
        self.running = True
        self.n = 0
        self.task = asyncio.create_task(self.loop())

    def publish(self) -> None:
        self.n += 1
        p = VIRTUAL.position + np.array([1e-6 * (self.n % 2), 0.0, 0.0])
        self.feed.publish(
            "virtual_probe",
            {"position": p, "quaternion": VIRTUAL.quaternion, "age_ms": self.age_ms,
             "stale": False, "clutch": self.clutch},
        )  # fmt: skip
        self.feed.publish(
            "probe",
            {"position": self.real.position, "quaternion": self.real.quaternion,
             "force": [0.0, 4.0, 0.0], "contact": True, "tracking": "tracked"},
        )  # fmt: skip

    async def loop(self) -> None:
        while True:
            if self.running:
                self.publish()
            await asyncio.sleep(0.01)


def calibration(**kw):
    base = {"calibrated": False, "calibrating": False, "step": None, "prompt": "",
            "event": None, "landmark": None, "message": ""}  # fmt: skip
    return {**base, **kw}


async def hud_when(ctx, page, condition: str, timeout: float = 15.0) -> dict:
    """The page's HUD as soon as ``condition`` (JavaScript on ``h``, the HUD) holds."""
    js = f"(() => {{ const h = headset.hud(); return ({condition}) ? h : null; }})()"
    return await ctx.until(page, js, timeout)


async def run(ctx) -> dict:
    feed = await ctx.feed()
    data: dict = {"virtual_pose": [list(VIRTUAL.position), list(VIRTUAL.quaternion)]}
    # The model: the sim patient's own ellipsoid, with the paper's long body semi-axis.
    heading = math.radians(PATIENT.config.yaw_deg)
    model = Ellipsoid(PATIENT.T_world_body.position, (10.0, *PATIENT.semi_axes[1:]), heading)
    feed.publish("model", model_fields(model))
    feed.publish("link", {"state": "connected"})
    feed.publish("calibration", calibration(calibrated=True))
    pub = Publisher(feed)
    url = f"https://127.0.0.1:{feed.port}/#code={feed.code}"
    page = await ctx.page(url, headset=True)
    data["first_hud"] = await hud_when(ctx, page, "h.cue === 'red'")
    t_page = time.monotonic()

    # 1. Where things are drawn, and with which objects.
    data["red"] = await capture(ctx, page, "feed_red")

    # 2. The colour follows the error (thresholds 5 mm/5 deg, 15 mm/15 deg).
    data["grades"] = []
    for mm, deg, want in ((2.0, 2.0, "green"), (10.0, 3.0, "amber"), (3.0, 10.0, "amber"),
                          (30.0, 2.0, "red"), (2.0, 20.0, "red")):  # fmt: skip
        pub.real = offset(VIRTUAL, mm, deg)
        hud = await hud_when(ctx, page, f"h.cue === '{want}' && h.mm === '{mm:.1f} mm'")
        await next_frames(ctx, page)
        data["grades"].append({
            "mm": mm, "deg": deg, "cue": hud["cue"], "hud": hud,
            "colour": await page.evaluate("headset.colour()"),
            "arrow": await page.evaluate("headset.visible('arrow')"),
        })  # fmt: skip

    # 3. Not live: the pose stops (older than 0.5 s), an old pose, the link down, a clutch.
    pub.running = False
    t_stop = time.monotonic()
    data["stopped"] = await hud_when(ctx, page, "h.cue === 'stale'")
    data["stopped_after_s"] = time.monotonic() - t_stop
    await ctx.shot(page, "feed_stale")
    pub.running = True
    data["resumed"] = await hud_when(ctx, page, "h.guide.live")
    pub.age_ms = 800.0  # fresh messages of a pose sent 0.8 s ago
    data["old_pose"] = await hud_when(ctx, page, "h.cue === 'stale'")
    pub.age_ms = 20.0
    await hud_when(ctx, page, "h.guide.live")
    feed.publish("link", {"state": "disconnected"})
    data["link_down"] = await hud_when(ctx, page, "h.cue === 'stale'")
    feed.publish("link", {"state": "connected"})
    await hud_when(ctx, page, "h.guide.live")
    pub.clutch = True
    data["clutch"] = await hud_when(ctx, page, "h.cue === 'stale'")
    pub.clutch = False
    await hud_when(ctx, page, "h.guide.live")

    # 4. Calibrating: the landmark asked for, and why the last press was refused.
    refusal = "press again on the right side: it is 9 cm above the xiphoid"
    prompt = "press the probe on the patient's extreme right side"
    asked = calibration(calibrating=True, step="right", prompt=prompt, event="refused",
                        landmark="right", message=refusal)  # fmt: skip
    feed.publish("calibration", asked)
    data["calibrating"] = await hud_when(ctx, page, "h.cue === 'calibrating'")
    data["calibrating_virtual_visible"] = await page.evaluate("headset.visible('virtual')")
    await ctx.shot(page, "feed_calibrating")
    feed.publish("calibration", calibration(calibrated=True))
    await hud_when(ctx, page, "h.guide.live")

    # 5. The outline button hides the body outline.
    await page.click("#outline")
    await next_frames(ctx, page)
    data["outline_after_click"] = await page.evaluate("headset.visible('outline')")
    await page.click("#outline")

    # 6. Bad input from pages; a tab closed mid-stream. The feed goes on.
    before = dict(feed.refused)
    wss = f"wss://127.0.0.1:{feed.port}/feed?code={feed.code}"
    data["bad_input_close_code"] = await page.evaluate(BAD_INPUT_JS, wss)
    other = await ctx.other_site()
    data["cross_origin"] = await other.evaluate(CROSS_ORIGIN_JS, wss)
    await ctx.close_page(other)
    tab = await ctx.page(url, headset=True)
    await ctx.until(tab, "headset.frames > 5 && headset.state.messages > 5")
    disconnects = feed.disconnects
    await ctx.close_page(tab)
    await ctx.wait("the closed tab noticed", lambda: feed.disconnects > disconnects, 10)
    data["closed_tab_disconnects"] = feed.disconnects - disconnects
    data["refused_before"] = before
    m0 = await page.evaluate("headset.state.messages")
    await ctx.until(page, f"headset.state.messages > {m0}")
    data["messages_after"] = await page.evaluate("headset.state.messages") - m0
    # 7. Pairing: a headset without the code is asked for it, a wrong one is refused and asked
    # again, the right one (typed with its space) pairs and is kept for the next visit.
    plain = f"https://127.0.0.1:{feed.port}/"
    fresh = await ctx.page(plain, headset=True)
    form = "!document.getElementById('pairing').hidden"
    note = "document.getElementById('pairing-note').textContent"
    data["pairing_asked"] = await ctx.until(fresh, f"({form}) && {note}", 15)
    data["pairing_hides_hud"] = await fresh.evaluate("document.body.dataset.pairing")
    await ctx.shot(fresh, "headset_pairing")
    wrong = "00000000" if feed.code != "00000000" else "11111111"
    await fresh.fill("#pairing-code", wrong)
    await fresh.click("#pairing button")
    refused_note = f"({form}) && /not accept/.test({note}) && {note}"
    data["pairing_wrong"] = await ctx.until(fresh, refused_note, 15)
    await ctx.shot(fresh, "headset_pairing_wrong")
    await fresh.fill("#pairing-code", f"{feed.code[:4]} {feed.code[4:]}")
    await fresh.click("#pairing button")
    await ctx.until(fresh, "headset.state.socket && headset.state.messages > 2", 15)
    data["paired_form_hidden"] = await fresh.evaluate("document.getElementById('pairing').hidden")
    await fresh.reload()
    await ctx.until(fresh, "headset.state.socket && headset.state.messages > 2", 15)
    data["paired_after_reload"] = await fresh.evaluate("document.getElementById('pairing').hidden")
    await ctx.close_page(fresh)
    data["code_address"] = await page.evaluate("location.href")
    # the page's frame rate (a figure: stage.HEADSET_FRAME_MS, and the machine)
    data["page_fps"] = round(await page.evaluate("headset.frames") / (time.monotonic() - t_page), 1)
    data["feed"] = feed.stats()
    data["latencies_ms"] = [round(v * 1000.0, 3) for v in feed.latencies]
    pub.task.cancel()
    return data

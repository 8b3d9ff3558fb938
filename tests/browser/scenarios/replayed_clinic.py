"""One session with no simulator in the follower (issue 18 §3), the headset page included.

The follower runs on real backends fed by a recorded clinic (tests/session/replayed_clinic.py,
made here by the simulator in this process, never the follower's): AHAT frames and rig poses
from the hl2ss replay server in its own process, the force board's reports through the real
HID reader, US and POV from files through OpenCV; the expert on the fake libHD Touch X. The
follower calibrates from the replayed landmark presses and records tracked probe poses (the
test compares them with the recording's truth).

The headset page runs under Meta's IWER emulator, in AR, registered: this headset's
registration was saved earlier (``headsets.json`` in the follower's state dir: its XR space
sits at a known ``T_WORLD_XR`` in the tracker's world, with its viewer-to-rig offset), and the
page is offered it on hello. The IWER headset moves as the recorded one did: each tick this
scenario reads which recorded frame the follower has measured last (the ``probe`` object's
``device_time_s``, as the page has it) and puts the emulated viewer where that frame's rig
pose says the head was (``T_xr_world @ T_world_rig @ T_rig_viewer``), so the follower's watch
compares the page's own viewer poses with the hl2ss rig poses it tracks. The page must draw
the virtual probe where the expert put it: the expert's published pose (patient frame, its
recording) through the follower's calibration and the registration.
"""

from __future__ import annotations

import asyncio
import json
import math
import time

from headset_views import next_frames
from replayed_clinic import (
    T_RIG_CAMERA,
    calibration_presses,
    expert_on_fake_touchx,
    follower_config,
    make_recording,
    replay_env,
    start_hl2ss_server,
)
from stage import page_url

from humantele.follower.registration import HEADSETS_FILE
from humantele.follower.sim_world import SimWorld
from humantele.geometry import Pose, quat_from_axis_angle, quat_multiply

REST_S = 6.0  # after the presses, resting on the abdomen
HEADSET = "h-replayed-clinic"  # this headset's id (the page keeps it in its storage)
# Where this headset's XR space (local-floor) sits in the tracker's world: offset and turned
# (as a registration found it earlier; the test knows it exactly).
T_WORLD_XR = Pose(
    [0.62, -0.05, -0.85],
    quat_multiply(
        quat_from_axis_angle((0.0, 1.0, 0.0), math.radians(-35.0)),
        quat_from_axis_angle((1.0, 0.0, 0.3), math.radians(0.8)),
    ),
)
# The viewer (WebXR: -z ahead, y up) looks where the AHAT camera does (OpenCV: +z ahead, y
# down): half a turn about x, a little behind and above it.
T_VIEWER_CAMERA = Pose([0.0, 0.03, 0.06], quat_from_axis_angle((1.0, 0.0, 0.0), math.pi))
T_VIEWER_RIG = T_VIEWER_CAMERA @ T_RIG_CAMERA.inverse()
SET_ID = f"localStorage.setItem('humantele.headset', '{HEADSET}');"


def fields(T: Pose) -> dict[str, list[float]]:
    return {"position": T.position.tolist(), "quaternion": T.quaternion.tolist()}


def save_registration(state_dir) -> None:
    """This headset registered earlier (as the follower's registration saves one)."""
    state_dir.mkdir(parents=True, exist_ok=True)
    entry = {"T_world_xr": fields(T_WORLD_XR), "residual_mm": 0.9, "points": 4,
             "saved_at": "2026-11-25 09:00", "T_viewer_rig": fields(T_VIEWER_RIG)}  # fmt: skip
    (state_dir / HEADSETS_FILE).write_text(json.dumps({HEADSET: entry}))


# In the page, every 20 ms: the recorded frame nearest the probe's device time (binary search
# in ``table``: [t, device position, device quaternion]), and IWER's device put there.
FOLLOW_JS = """(table) => {
  window.recordedHead = { moves: 0 };
  setInterval(() => {
    const p = headset.state.probe;
    const t = p && p.device_time_s;
    if (t === undefined || t === null) return;
    let lo = 0, hi = table.length - 1;
    while (hi - lo > 1) {
      const m = (lo + hi) >> 1;
      if (table[m][0] <= t) lo = m; else hi = m;
    }
    const r = Math.abs(table[hi][0] - t) < Math.abs(table[lo][0] - t) ? table[hi] : table[lo];
    xrDevice.position.set(r[1], r[2], r[3]);
    xrDevice.quaternion.set(r[4], r[5], r[6], r[7]);
    window.recordedHead.moves += 1;
  }, 20);
}"""


async def follow_the_recorded_head(page, rigs: dict[float, Pose]) -> None:
    """Move the IWER headset as the recorded head: the viewer pose (XR) of the recorded frame
    the page last heard of (done in the page: a loaded machine's round trips lag seconds)."""
    # IWER's device pose and the viewer pose the page gets (local-floor) differ by a fixed
    # transform: measured once, the headset still.
    while not await page.evaluate("!!headset.registration.viewer"):
        await asyncio.sleep(0.05)
    p, q = "xrDevice.position", "xrDevice.quaternion"
    d = await page.evaluate(f"[[{p}.x, {p}.y, {p}.z], [{q}.x, {q}.y, {q}.z, {q}.w]]")
    await asyncio.sleep(0.3)
    v = await page.evaluate("headset.registration.viewer")
    T_device_viewer = (Pose(v["position"], v["quaternion"]) @ Pose(d[0], d[1]).inverse()).inverse()
    table = []
    for t in sorted(rigs):
        device = T_device_viewer @ T_WORLD_XR.inverse() @ rigs[t] @ T_VIEWER_RIG.inverse()
        table.append([t, *device.position.tolist(), *device.quaternion.tolist()])
    await page.evaluate(FOLLOW_JS, table)


async def hud_when(ctx, page, condition: str, timeout: float = 60.0) -> dict:
    js = f"(() => {{ const h = headset.hud(); return ({condition}) ? h : null; }})()"
    return await ctx.until(page, js, timeout)


async def run(ctx) -> dict:
    data: dict = {"T_world_xr": fields(T_WORLD_XR)}
    world = SimWorld()
    targets, presses_end = calibration_presses(world)
    rec = make_recording(ctx.out, presses_end + REST_S, targets, world)
    truth = {str(t): fields(T) for t, T in rec.truth.items()}  # for the test: by device time
    (ctx.out / "truth.json").write_text(json.dumps(truth))
    ctx.mark("recorded")
    # Looped, frames and force board alike: a press the follower was not yet measuring comes
    # round again, as a technician re-presses. Both from the follower's first read of either
    # (a start shared in a file), as one clinic's devices run together: each from its own first
    # read, a loaded machine opened the frames 1-2 s after the board, and the xiphoid press was
    # paired with the hover 16 cm above it; from one fixed epoch, the follower joined mid-turn
    # and took a later landmark's press as the xiphoid (the recorded technician's order is fixed).
    start_file = ctx.out / "clinic_start"
    server, port = start_hl2ss_server(rec.dir / "ahat.npz", loop=True, start_file=start_file)
    s = await ctx.daemons()
    try:
        expert_cfg = expert_on_fake_touchx(ctx.out, s.env)
        await s.start("expert", "--config", str(expert_cfg), "--record", str(ctx.out / "e.mcap"))
        save_registration(s.state_dir)
        registration = "[follower.registration]\nwatch_samples = 5\n"
        follower_cfg = ctx.out / "follower.toml"
        follower_cfg.write_text(follower_config(rec.dir, port, s.state_dir, extra=registration))
        s.env.update(replay_env(rec.dir, loop=True, start_file=start_file))
        await s.start("follower", "--config", str(follower_cfg),
                      "--record", str(ctx.out / "f.mcap"))  # fmt: skip
        await s.wait("the follower calibrated from the replayed presses",
                     lambda e, f: f.get("calibrated") is True, timeout=120)  # fmt: skip
        ctx.mark("calibrated")
        await s.wait("poses from the expert's Touch X, the model at the expert",
                     lambda e, f: f.get("poses_received", 0) > 50 and e.get("has_model")
                     and f.get("states_sent", 0) > 60, timeout=60)  # fmt: skip

        # The headset page in AR under IWER, registered (the saved one offered), following.
        page = await ctx.page(page_url(s.stats("follower")), iwer=True, init_script=SET_ID)
        await ctx.until(page, "headset.xr.supported", timeout=20)
        await page.click("#enter-ar")
        await ctx.until(page, "headset.presenting", timeout=20)
        await ctx.until(page, "headset.state.probe && headset.state.probe.device_time_s", 30)
        await follow_the_recorded_head(page, rec.rigs)
        watched = (
            "h.registration.state === 'registered' && h.registration.watch === 'ok'"
            " && h.guide.live && headset.state.model"
        )
        try:
            data["registered"] = await hud_when(ctx, page, watched, timeout=90)
        except AssertionError as exc:
            moves = await page.evaluate("recordedHead.moves")
            raise AssertionError(f"{exc}; the IWER head moved {moves} times") from None
        ctx.mark("registered and watched")
        # The picture held still while live: the virtual probe drawn (XR) and the pose the
        # feed sent for it (world).
        freeze = f"(() => {{ const h = headset.hud(); if (!({watched})) return false;" \
                 " headset.freeze(true); return true; })()"  # fmt: skip
        await ctx.until(page, freeze, 60)
        await next_frames(ctx, page)
        data["t_drawn"] = time.monotonic()  # the machine's clock, the expert records on it
        data["virtual_xr"] = await page.evaluate("headset.matrixWorld('virtual')")
        data["virtual_world"] = await page.evaluate("headset.state.virtual")
        data["virtual_visible"] = await page.evaluate("headset.visible('virtual')")
        data["hud"] = await page.evaluate("headset.hud()")
        await ctx.shot(page, "replayed_clinic_headset")
        await page.evaluate("headset.freeze(false)")
        data["head_moves"] = await page.evaluate("recordedHead.moves")
        data["follower"] = s.stats("follower")
        data["expert"] = s.stats("expert")
        await ctx.close_page(page)
        data["follower_exit"] = await s.terminate("follower")
        data["expert_exit"] = await s.terminate("expert")
    finally:
        server.kill()
        server.communicate(timeout=10)
        (rec.dir / "ahat.npz").unlink()  # 0.7 GB of frames, stored uncompressed: not kept
    return data

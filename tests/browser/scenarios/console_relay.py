"""What the console's video path adds, measured both ways on the same sim ultrasound frames:
JPEG over the console's WebSocket (what the console does) against relaying the frames to the
page over a local WebRTC connection (aiortc encodes VP8, Chromium decodes it in a <video>).

The sim ultrasound renders in a child process (as the expert's stand-in does) at ``fps``;
each mode runs ``seconds``. From a frame's arrival at the server (``seen``: the provider
has it, as a decoded received frame would be) to the page's draw call, from the page's echo
(the frame's number, read back from the canvas's counter patch in the WebRTC mode), less the
time between draw and echo: p50/p95 in ms, and the page's draw rate.

    python tests/browser/netns.py console_relay --arg seconds=20 --arg write=1

(``write=1``: the figures go to docs/benchmarks.md, section ``console``.)
"""

from __future__ import annotations

import asyncio
import fractions
import json
import time
from pathlib import Path

import numpy as np
from aiohttp import WSMsgType, web

from humantele.expert.console.frames import ProcessFrames
from humantele.expert.console.server import WEB_DIR
from humantele.video.counter import MODULUS, unwrap
from humantele.video.scene import DemoScene
from humantele.video.sim_ultrasound import SimUltrasoundConfig

# The WebRTC page: a <video>, each frame drawn to a canvas, its counter read and echoed.
RELAY_PAGE = (Path(__file__).resolve().parent.parent / "console_relay.html").read_text()


class FrameTrack:
    """A video track sending the provider's newest ultrasound frame when there is a new one."""

    def __init__(self, frames, seen: dict) -> None:
        from aiortc import MediaStreamTrack

        class _Track(MediaStreamTrack):
            kind = "video"

            async def recv(inner):  # noqa: N805 - the track's own method
                import av

                while True:
                    f = frames.latest("us")
                    if f is not None and f.seq != self.last:
                        break
                    await asyncio.sleep(0.002)
                self.last = f.seq
                seen[f.seq] = time.monotonic()
                vf = av.VideoFrame.from_ndarray(f.image, format="bgr24")
                vf.pts = int((time.monotonic() - self.t0) * 90000)
                vf.time_base = fractions.Fraction(1, 90000)
                return vf

        self.last = None
        self.t0 = time.monotonic()
        self.track = _Track()


def pct(values: list[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)) * 1000.0, 1) if values else None


async def relay_mode(ctx, frames, seconds: float) -> dict:
    from aiortc import RTCPeerConnection, RTCSessionDescription

    seen: dict[int, float] = {}
    lat: list[float] = []
    pcs = []

    async def page(_r):
        return web.Response(text=RELAY_PAGE, content_type="text/html")

    async def offer(request):
        desc = json.loads(await request.text())
        pc = RTCPeerConnection()
        pcs.append(pc)
        pc.addTrack(FrameTrack(frames, seen).track)
        await pc.setRemoteDescription(RTCSessionDescription(desc["sdp"], desc["type"]))
        await pc.setLocalDescription(await pc.createAnswer())
        return web.json_response({"sdp": pc.localDescription.sdp, "type": pc.localDescription.type})

    async def echo(request):
        ws = web.WebSocketResponse()
        await ws.prepare(request)
        last = 0
        async for msg in ws:
            if msg.type != WSMsgType.TEXT:
                continue
            now = time.monotonic()
            m = json.loads(msg.data)
            seq = unwrap(int(m["seq"]) % MODULUS, last or int(m["seq"]))
            last = seq
            if seq in seen:
                lat.append(now - seen[seq] - m["draw_to_send_ms"] / 1000.0)
        return ws

    app = web.Application()
    app.router.add_get("/", page)
    app.router.add_get("/counter.js", lambda _r: web.FileResponse(WEB_DIR / "counter.js"))
    app.router.add_post("/offer", offer)
    app.router.add_get("/echo", echo)
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = site._server.sockets[0].getsockname()[1]
    p = await ctx.page(f"http://127.0.0.1:{port}/", width=800, height=600)
    await ctx.until(p, "window.relay && window.relay.drawn > 10", 60)
    lat.clear()
    d0 = await p.evaluate("window.relay.drawn")
    await asyncio.sleep(seconds)
    drawn = await p.evaluate("window.relay.drawn") - d0
    unread = await p.evaluate("window.relay.unread")
    await ctx.close_page(p)
    for pc in pcs:
        await pc.close()
    await runner.cleanup()
    return {"p50_ms": pct(lat, 50), "p95_ms": pct(lat, 95), "n": len(lat),
            "page_fps": round(drawn / seconds, 1), "unread": unread}  # fmt: skip


class Quiet:
    """A session with nothing to say (the figures are about the video)."""

    recorder = None

    def snapshot(self) -> dict:
        return {"link": {"state": "connected", "pose_age_ms": 10.0}}

    def pose_at(self, t):
        return None

    def start_scan(self):
        return 1

    def stop_scan(self):
        pass

    def set_clutch(self, on):
        pass


async def jpeg_mode(ctx, frames, seconds: float) -> dict:
    server = await ctx.console(frames, Quiet())
    p = await ctx.page(server.url, width=1280, height=800)
    await ctx.until(p, "window.consoleApp && consoleApp.frames.us > 10", 90)
    st = server.tracks["us"]
    st.seen_to_draw.clear()
    f0 = await p.evaluate("consoleApp.frames.us")
    await asyncio.sleep(seconds)
    drawn = await p.evaluate("consoleApp.frames.us") - f0
    rx = [v / 1000.0 for v in await p.evaluate("consoleApp.rxToDraw")]
    lat = list(st.seen_to_draw)
    enc = list(st.encode_s)
    await ctx.close_page(p)
    return {"p50_ms": pct(lat, 50), "p95_ms": pct(lat, 95), "n": len(lat),
            "page_fps": round(drawn / seconds, 1), "encode_p50_ms": pct(enc, 50),
            "page_arrival_to_draw_p50_ms": pct(rx, 50)}  # fmt: skip


async def run(ctx) -> dict:
    seconds = float(ctx.args.get("seconds", 10.0))
    fps = float(ctx.args.get("fps", 20.0))
    frames = ProcessFrames({"us": SimUltrasoundConfig(fps=fps)}, DemoScene())
    frames.start()
    try:
        for _ in range(600):  # the child process imports and starts
            if frames.latest("us") is not None:
                break
            await asyncio.sleep(0.1)
        data = {"fps": fps, "seconds": seconds}
        modes = str(ctx.args.get("modes", "jpeg,relay,jpeg")).split(",")
        for i, mode in enumerate(modes):  # alternated: the machine's load drifts
            run_mode = jpeg_mode if mode == "jpeg" else relay_mode
            data[f"{i}_{mode}"] = await run_mode(ctx, frames, seconds)
    finally:
        await asyncio.to_thread(frames.stop)
    if ctx.args.get("write"):
        write_benchmarks(data)
    return data


def write_benchmarks(data: dict) -> None:
    from humantele.report import machine_line, markdown_table, write_section

    rows = []
    for key, d in data.items():
        if not isinstance(d, dict) or "p50_ms" not in d:
            continue
        mode = "JPEG over the console's WebSocket" if key.endswith("jpeg") else "WebRTC relay (VP8)"
        rows.append([key.split("_")[0], mode, d["n"], d["p50_ms"], d["p95_ms"], d["page_fps"]])
    text = (
        "## Console video path (`python tests/browser/netns.py console_relay --arg seconds=S"
        " --arg write=1`)\n\n"
        f"The sim ultrasound (640 x 480, {data['fps']:g} fps, rendered in a child process) to a"
        " page in headless Chromium (software GPU), each way for"
        f" {data['seconds']:g} s, alternated (the machine's load drifts): from the frame's arrival"
        " at the server to the page's draw call (the page echoes each frame it draws; the echo's"
        " own transit included), and the page's draw rate. JPEG: encode once, a binary"
        " WebSocket message, `createImageBitmap`, canvas; at most 2 frames in flight. WebRTC:"
        " aiortc VP8 to a `<video>`, each frame drawn to a canvas and its counter read.\n\n"
        + markdown_table(["run", "path", "frames", "p50 ms", "p95 ms", "page fps"], rows)
        + "\n\n"
        + machine_line()
    )
    write_section("console", text)

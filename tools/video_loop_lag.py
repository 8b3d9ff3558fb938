"""Does sending the video hold up the follower's event loop? (a diagnostic for the pose path)

A follower process (link, and video as asked) measures its asyncio loop's lag: a task sleeps
1 ms again and again and records how late it wakes (ms). The expert (receiver) runs in this
process. Variants, interleaved ``--repeats`` times, ``--seconds`` each once connected:

- ``none``: no video at all;
- ``render``: the video process renders both sim sources and the follower wraps the frames,
  but no track is sent (the CPU of the video without aiortc's encoding and sending);
- ``250`` / ``2500``: both tracks sent, encoders fixed at that many kbit/s.

If ``render`` lags like the sending variants, the lag is CPU contention; if the lag grows
with the bit rate, it is work on the loop per packet. Prints one JSON line per run, then the
medians. Usage: ``PYTHONPATH=src python tools/video_loop_lag.py [--seconds 15] [--repeats 2]``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time

import numpy as np

TOKEN = "video-loop-lag"
VARIANTS = ("none", "render", "250", "2500")


async def follower(url: str, variant: str, seconds: float) -> None:
    from humantele.media.config import FollowerVideoConfig
    from humantele.media.sender import VideoSender
    from humantele.transport import LinkConfig, PeerLink
    from humantele.video.scene import DEFAULT_PATIENT, DemoScene

    kbps = int(variant) if variant.isdigit() else 1000
    rate = {"start_kbps": kbps, "min_kbps": kbps, "max_kbps": kbps}
    config = FollowerVideoConfig(enabled=True, record_us_hz=0.0, record_pov_hz=0.0,
                                 us_bitrate=rate, pov_bitrate=rate)  # fmt: skip
    sender = None if variant == "none" else VideoSender(config, None, None, DEFAULT_PATIENT)
    send = variant.isdigit()
    link = PeerLink(
        "follower",
        LinkConfig(signaling_url=url, room="lag", token=TOKEN),
        media=(lambda pc, role: sender.attach(pc)) if send and sender else None,
    )
    scene = DemoScene()
    if sender is not None:
        await asyncio.to_thread(sender.open)
        sender.start(asyncio.get_running_loop())

    async def world() -> None:
        while True:
            if sender is not None:
                sender.publish_scene(scene())
            await asyncio.sleep(0.01)

    tasks = [asyncio.ensure_future(link.run()), asyncio.ensure_future(world())]
    await link.wait_state("connected", timeout=60)
    await asyncio.sleep(3.0)  # the video settles (REMB cannot move a fixed rate)
    late = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t0 = time.perf_counter()
        await asyncio.sleep(0.001)
        late.append(time.perf_counter() - t0 - 0.001)
    a = np.asarray(late) * 1e3
    print(json.dumps({"variant": variant, "load": round(os.getloadavg()[0], 1),
                      "lag_p50_ms": round(float(np.percentile(a, 50)), 3),
                      "lag_p99_ms": round(float(np.percentile(a, 99)), 2),
                      "lag_max_ms": round(float(a.max()), 1), "wakeups": int(a.size)}),
          flush=True)  # fmt: skip
    for t in tasks:
        t.cancel()
    await link.close()
    if sender is not None:
        await asyncio.to_thread(sender.close)


async def one(variant: str, seconds: float) -> dict:
    from humantele.media.config import ExpertVideoConfig
    from humantele.media.receiver import VideoReceiver
    from humantele.signaling.messages import TOKEN_ENV
    from humantele.signaling.server import SignalConfig, SignalingServer
    from humantele.transport import LinkConfig, PeerLink

    server = SignalingServer(SignalConfig(port=0), TOKEN)
    await server.start()
    holder: dict = {}
    expert = PeerLink("expert", LinkConfig(signaling_url=server.url, room="lag", token=TOKEN),
                      media=lambda pc, role: holder["rx"].prepare(pc))  # fmt: skip
    enabled = variant.isdigit()
    holder["rx"] = VideoReceiver(ExpertVideoConfig(enabled=enabled), expert.clock, expert.now)
    child = await asyncio.create_subprocess_exec(
        sys.executable, __file__, "--child", server.url, variant, str(seconds),
        env={**os.environ, TOKEN_ENV: TOKEN}, stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip
    run = asyncio.ensure_future(expert.run())
    out, _ = await child.communicate()
    await expert.close()
    run.cancel()
    await server.stop()
    lines = [line for line in out.decode().splitlines() if line.startswith("{")]
    return json.loads(lines[-1]) if lines else {"variant": variant, "failed": True}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seconds", type=float, default=15.0)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--child", nargs=3, metavar=("URL", "VARIANT", "SECONDS"))
    args = p.parse_args()
    if args.child:
        url, variant, secs = args.child
        asyncio.run(follower(url, variant, float(secs)))
        return
    runs = []
    for _ in range(args.repeats):
        for v in VARIANTS:
            r = asyncio.run(one(v, args.seconds))
            runs.append(r)
            print(json.dumps(r), flush=True)
    for v in VARIANTS:
        mine = [r for r in runs if r.get("variant") == v and "lag_p99_ms" in r]
        if mine:
            med = {k: float(np.median([r[k] for r in mine])) for k in ("lag_p50_ms", "lag_p99_ms")}
            print(f"{v:7s} lag p50 {med['lag_p50_ms']:.3f} ms, p99 {med['lag_p99_ms']:.2f} ms, "
                  f"loads {[r['load'] for r in mine]}")  # fmt: skip


if __name__ == "__main__":
    main()

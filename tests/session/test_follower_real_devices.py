"""The follower on real device backends fed by recorded device data, with no simulator in any
of its processes (issue 18 §1): AHAT frames and rig poses from an hl2ss replay server in its
own process (hl2ss's wire format, the clinic's calibration file), the force board's HID reports
through the real HID reader (a replayed ``hid`` module), US and POV video from files through
the OpenCV source (tests/session/replayed_clinic.py)."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys

import aiohttp
import numpy as np
import pytest
from replayed_clinic import (
    follower_config,
    hold_then_wobble,
    make_recording,
    replay_env,
    start_hl2ss_server,
)

from humantele.follower.sim_world import SimWorld

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

PAIRING = "13572468"  # the headset page's pairing code the follower is given


async def test_follower_on_replayed_devices_places_the_probe_and_loads_no_simulator(tmp_path):
    world = SimWorld()
    rec = make_recording(tmp_path, 3.0, hold_then_wobble(world, 3.0), world)
    env = dict(os.environ, **replay_env(rec.dir), HUMANTELE_PAIRING_CODE=PAIRING)
    server, port = start_hl2ss_server(rec.dir / "ahat.npz")
    follower = None
    try:
        cfg = tmp_path / "follower.toml"
        text = follower_config(rec.dir, port, tmp_path / "state")
        cfg.write_text(
            text.replace(
                "[follower.link]", '[follower.link]\nsignaling_url = "ws://127.0.0.1:9/ws"'
            )
        )
        stats = tmp_path / "stats.json"
        follower = subprocess.Popen(
            [sys.executable, "-m", "humantele", "follower", "--config", str(cfg),
             "--duration", "60", "--stats-file", str(stats)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
            start_new_session=True,
        )  # fmt: skip
        url, probes = None, []
        for _ in range(600):  # the feed's address, once it serves (60 s at most)
            if stats.exists():
                with _suppress():
                    url = json.loads(stats.read_text()).get("feed_url")
            if url or follower.poll() is not None:
                break
            await asyncio.sleep(0.1)
        assert url, f"no feed: {follower.communicate(timeout=10)}"
        async with aiohttp.ClientSession() as s, s.ws_connect(f"{url}?code={PAIRING}") as ws:
            deadline = asyncio.get_running_loop().time() + 60
            while len(probes) < 30 and asyncio.get_running_loop().time() < deadline:
                with _suppress():
                    msg = await ws.receive_json(timeout=5)
                    if msg.get("type") == "probe" and msg.get("tracking") == "tracked":
                        probes.append(msg)
        figures: dict = {}

        def video_flowing() -> bool:  # both tracks captured from the files (as fast as it can)
            video = figures.get("video") or {}
            return all((video.get(k) or {}).get("captured", 0) > 10 for k in ("us", "pov"))

        for _ in range(600):  # the stats file, once the video has flowed (60 s at most)
            with _suppress():
                figures = json.loads(stats.read_text())
            if video_flowing() or follower.poll() is not None:
                break
            await asyncio.sleep(0.1)
    finally:
        for p in (follower, server):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, 15)
        if follower is not None:
            out, err = follower.communicate(timeout=30)
            if not probes:
                print(out, err)
        server.communicate(timeout=10)
    assert len(probes) >= 30, "the follower placed no probe from the replayed devices"
    # Where the probe is, from device data alone (rig pose x extrinsics x tracker), against
    # the recording's truth: the tip position within 2 mm of the nearest true tip (the feed
    # carries no device time; the session test matches recorded poses frame by frame).
    tips = np.array([t.position for t in rec.truth.values()])
    errs = [np.min(np.linalg.norm(tips - np.array(p["position"]), axis=1)) for p in probes]
    assert float(np.median(errs)) < 2e-3, errs
    assert max(np.linalg.norm(p["force"]) for p in probes) > 1.0  # the board's press, read
    assert any(p["contact"] for p in probes)  # contact from the force board
    assert figures["simulator_modules"] == {"daemon": [], "sensing": [], "video": []}
    for track in ("us", "pov"):  # the files through the OpenCV source, in the video process
        assert video_flowing() and figures["video"][track]["errors"] == 0


class _suppress:
    """Ignore a half-written stats file or a feed message that is not JSON."""

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind, exc, tb) -> bool:
        return kind is not None and issubclass(kind, ValueError | TimeoutError | TypeError)

"""The expert and follower daemons as real OS processes over loopback WebRTC: calibration,
a daemon killed and restarted mid-session, clean shutdown."""

import asyncio
import json

import aiohttp
import pytest
from session_helpers import PAIRING_CODE, pid_alive

from humantele.follower.calibration import Calibration


def flowing(e, f, poses=30, states=10):
    return (
        f.get("link_state") == "connected"
        and e.get("link_state") == "connected"
        and f.get("poses_received", 0) >= poses
        and e.get("states_received", 0) >= states
    )


async def latest_virtual_probe(feed_url, timeout=5.0):
    """The latest virtual_probe object the follower's renderer feed gives (wss: self-signed)."""
    url = f"{feed_url}?code={PAIRING_CODE}"
    async with aiohttp.ClientSession() as s, s.ws_connect(url, ssl=False) as ws:
        found = None
        end = asyncio.get_running_loop().time() + timeout
        while found is None or found.get("_n", 0) < 3:
            msg = await ws.receive(timeout=max(0.1, end - asyncio.get_running_loop().time()))
            obj = json.loads(msg.data)
            if obj["type"] == "virtual_probe":
                obj["_n"] = (found or {}).get("_n", 0) + 1
                found = obj
        return found


@pytest.mark.slow
async def test_session_calibrates_survives_kills_and_rejoins(session):
    # 1. Both daemons, a fresh follower: the sim person calibrates, the expert gets the model.
    await session.start("follower")
    await session.start("expert")
    await session.wait(
        "calibration and streams",
        lambda e, f: f.get("calibrated") and e.get("has_model") and flowing(e, f),
        timeout=60,
    )
    f = session.stats("follower")
    assert not f["calibration_reused"] and f["calibration_refusals"] == 0
    saved = Calibration.load(session.state_dir / "calibration.json")
    assert saved is not None
    e = session.stats("expert")
    assert e["models_installed"] == 1 and e["servo_rate_hz"] > 500
    servo_pid = e["servo_pid"]
    assert pid_alive(servo_pid)
    probe = await latest_virtual_probe(f["feed_url"])
    assert probe["stale"] is False and len(probe["position"]) == 3

    # 2. Kill the follower: the expert keeps running and rendering, the link goes down.
    await session.kill("follower")
    ticks_before = session.stats("expert")["uptime_s"]
    await session.wait("expert notices", lambda e, f: e.get("link_state") != "connected")
    noticed = session.stats("expert")["uptime_s"]
    await session.wait("expert runs on", lambda e, f: e["uptime_s"] > noticed)  # next stats
    e = session.stats("expert")
    assert session.procs["expert"].returncode is None and e["uptime_s"] > ticks_before
    assert pid_alive(servo_pid) and e["has_model"] and e["servo_fault"] == ""

    # 3. Restart it: it reuses the saved calibration (no new presses) and rejoins by itself.
    connections = e["connections"]
    await session.start("follower")
    await session.wait(
        "follower rejoins",
        lambda e, f: flowing(e, f, poses=20, states=5) and e.get("connections", 0) > connections,
    )
    f = session.stats("follower")
    assert f["calibrated"] and f["calibration_reused"]
    assert session.stats("expert")["models_installed"] == 1  # the same model again: no change

    # 4. Kill the expert: the follower keeps running and marks the virtual probe stale.
    await session.kill("expert")
    await session.wait("follower notices", lambda e, f: f.get("link_state") != "connected")
    probe = await latest_virtual_probe(session.stats("follower")["feed_url"])
    assert probe["stale"] is True
    assert session.procs["follower"].returncode is None
    # The killed expert's servo process notices its parent is gone and ends (no orphan).
    for _ in range(50):
        if not pid_alive(servo_pid):
            break
        await asyncio.sleep(0.1)
    assert not pid_alive(servo_pid)

    # 5. Restart the expert: it rejoins and gets the saved model from the follower.
    await session.start("expert")
    await session.wait("expert rejoins", lambda e, f: e.get("has_model") and flowing(e, f, 20, 5))
    probe = await latest_virtual_probe(session.stats("follower")["feed_url"])
    assert probe["stale"] is False

    # 6. SIGTERM both: peers say bye, every process ends with code 0, the servo too.
    servo_pid = session.stats("expert")["servo_pid"]
    assert await session.terminate("expert") == 0
    await session.wait("follower hears bye", lambda e, f: f.get("link_state") != "connected", 10)
    assert await session.terminate("follower") == 0
    assert not pid_alive(servo_pid)
    assert session.stats("follower")["dropped"].get("pose:stale", 0) >= 0

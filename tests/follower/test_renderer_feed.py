import asyncio
import json

import aiohttp

from humantele.follower.feed import FeedConfig, RendererFeed


async def test_feed_sends_latest_per_type_and_survives_bad_clients():
    feed = RendererFeed(FeedConfig(port=0))
    await feed.start()
    try:
        feed.publish("calibration", {"step": "xiphoid", "calibrated": False})
        async with aiohttp.ClientSession() as s:
            async with s.ws_connect(feed.url) as ws:
                first = json.loads((await ws.receive(timeout=5)).data)
                assert first == {"type": "calibration", "step": "xiphoid", "calibrated": False}
                # A burst: the client may see fewer than all, but the last one always arrives.
                for i in range(200):
                    feed.publish("virtual_probe", {"seq": i, "position": [0.0, float("nan"), 1.0]})
                seen = []
                while not seen or seen[-1]["seq"] != 199:
                    seen.append(json.loads((await ws.receive(timeout=5)).data))
                assert seen[-1]["position"] == [0.0, None, 1.0]  # NaN never reaches JSON
                assert [m["seq"] for m in seen] == sorted(m["seq"] for m in seen)
                assert len(seen) + feed.coalesced == 200
                await ws.send_str("garbage the feed ignores")
                feed.publish("link", {"state": "connected"})
                msg = json.loads((await ws.receive(timeout=5)).data)
                assert msg["type"] == "link"
            # The client left; publishing still works and does not block.
            await asyncio.sleep(0.05)
            feed.publish("link", {"state": "disconnected"})
            assert not feed.clients
    finally:
        await feed.stop()

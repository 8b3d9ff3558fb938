"""Every frame the expert receives, recorded encoded (issue 21 §1), over real aiortc on
loopback: what the tap records is what aiortc decoded, frame for frame."""

import asyncio

import av
import pytest
from media_helpers import SyncErrorBound, close_video_link, video_follower
from test_video_link import TOKEN, expert_with_video, server  # noqa: F401 - the fixture

from humantele.media.jitter import KEYFRAME_TESTS
from waits import until


@pytest.mark.parametrize("codec", ["vp8", "h264"])
async def test_the_recorded_frames_are_the_ones_aiortc_decoded(server, codec):  # noqa: F811
    recorded: list[tuple[str, float, dict]] = []
    expert, rx = expert_with_video(server, codec, record=lambda *a: recorded.append(a))
    follower, tx = video_follower(server.url, "v", TOKEN)
    sync = SyncErrorBound(rx.clock)
    loop = asyncio.get_running_loop()
    tx.open()
    tx.start(loop)
    tasks = [asyncio.create_task(expert.run()), asyncio.create_task(follower.run())]
    try:
        await expert.wait_state("connected", timeout=30)
        await until(lambda: all(rx.stats_by_track[n].frames >= 20 for n in ("us", "pov")), 30)
    finally:
        await close_video_link(follower, expert, tx, rx, tasks)
    stats = rx.stats()
    for name in ("us", "pov"):
        frames = [(t, p) for topic, t, p in recorded if topic == f"/expert/{name}_video"]
        # every frame the jitter buffer released (the decoder's input) was recorded
        assert len(frames) == stats[name]["jitter"]["frames"] == stats[name]["encoded_recorded"]
        assert all(p["codec"] == codec for _, p in frames)
        assert frames[0][1]["keyframe"]  # the buffer starts on a keyframe
        assert [p["keyframe"] for _, p in frames] == [KEYFRAME_TESTS[codec](p["data"])
                                                      for _, p in frames]  # fmt: skip
        assert sum("t_capture" in p for _, p in frames) >= len(frames) - 3  # once anchored
        # captured before it was received, within the clock sync's error (one clock here)
        late = [p["t_capture"] - t for t, p in frames if "t_capture" in p]
        assert max(late) <= sync.worst_s + 0.005, (max(late), sync.worst_s)
        # the bytes decode on their own, into pictures of the track's size
        dec = av.CodecContext.create(codec, "r")
        pics = [pic for _, p in frames for pic in dec.decode(av.Packet(p["data"]))]
        assert len(pics) >= len(frames) - 2
        assert (pics[-1].width, pics[-1].height) == tuple(stats[name]["size"])

"""The media layer's parts: the frame record on the wire, the latest-frame slot, the POV
degradation policy, the foxglove image channel."""

import asyncio
import os
import struct
import threading

import numpy as np
import pytest

from humantele.media.config import DegradeConfig
from humantele.media.frameinfo import SIZE, FrameInfo, FrameInfoError
from humantele.media.policy import DegradationPolicy, Health
from humantele.media.slot import LatestSlot
from humantele.recording.schemas import CHANNELS, json_schema, make_sample


def test_frame_info_round_trips_and_bad_bytes_are_refused():
    info = FrameInfo("pov", 123456, 9876.54321)
    data = info.encode()
    assert len(data) == SIZE and FrameInfo.decode(data) == info
    nan = struct.pack("<cBBId", b"V", 1, 0, 1, float("nan"))
    wrong_version, wrong_track = data[:1] + b"\x02" + data[2:], data[:2] + b"\x07" + data[3:]
    for bad in (b"", data[:-1], data + b"x", b"X" + data[1:], wrong_version, wrong_track, nan):
        with pytest.raises(FrameInfoError):
            FrameInfo.decode(bad)
    with pytest.raises(FrameInfoError):
        FrameInfo("xray", 1, 0.0).encode()
    with pytest.raises(FrameInfoError):
        FrameInfo("us", -1, 0.0).encode()


async def test_slot_gives_the_newest_frame_never_an_old_one():
    slot: LatestSlot[int] = LatestSlot()
    slot.bind(asyncio.get_running_loop())
    for v in (10, 11, 12):  # three frames before the consumer asks: only the last is taken
        slot.put(v)
    n, item = await slot.get_newer(0)
    assert (n, item) == (3, 12) and slot.overwritten == 2
    waiter = asyncio.ensure_future(slot.get_newer(n))
    await asyncio.sleep(0.01)
    assert not waiter.done()  # nothing newer yet: it waits
    t = threading.Thread(target=slot.put, args=(13,))  # a capture thread puts the next one
    t.start()
    t.join()
    assert await asyncio.wait_for(waiter, 2.0) == (4, 13)


def test_pov_degrades_first_one_level_per_bad_check_and_recovers_slowly():
    p = DegradationPolicy(DegradeConfig(recover_s=5.0))
    good = Health(us_delivery=1.0, loss=0.0, late_ticks_per_s=0.0)
    assert p.update(0.0, good) == 0 and (p.pov_scale, p.pov_rate_factor) == (1.0, 1.0)
    assert p.update(1.0, Health(0.5, 0.0, 0.0)) == 1  # the US encoder falls behind
    assert p.update(2.0, Health(1.0, 0.10, 0.0)) == 2  # 10 % loss
    assert p.update(3.0, Health(1.0, 0.0, 50.0)) == 3  # the follower's loop runs late
    assert p.update(4.0, Health(0.1, 0.5, 99.0)) == 3  # the lowest level: stays
    assert (p.pov_scale, p.pov_rate_factor) == (0.5, 0.25)
    for t in (5.0, 6.0, 9.0):  # good, but not yet for recover_s
        assert p.update(t, good) == 3
    assert p.update(10.0, good) == 2
    assert p.update(12.0, good) == 2 and p.update(15.0, good) == 1
    assert p.update(16.0, Health(0.2, None, 0.0)) == 2  # bad again: down at once
    off = DegradationPolicy(DegradeConfig(enabled=False))
    assert off.update(0.0, Health(0.0, 1.0, 1e3)) == 0
    # unknowns (no frames, no RTCP report yet) are not problems
    assert Health(None, None, 0.0).problems(DegradeConfig()) == []


def test_us_images_are_foxglove_compressed_images():
    import cv2

    spec = CHANNELS["/follower/us_image"]
    assert spec.schema_name == "foxglove.CompressedImage"
    schema = json_schema(spec)
    assert {"timestamp", "frame_id", "data", "format"} <= set(schema["properties"])
    ok, jpeg = cv2.imencode(".jpg", np.full((48, 64, 3), 128, np.uint8))
    sample = make_sample(spec, 12.5, {"data": jpeg.tobytes(), "seq": 7})
    assert sample["format"] == "jpeg" and sample["frame_id"] == "us" and sample["seq"] == 7
    assert sample["timestamp"] == {"sec": 12, "nsec": 500_000_000}
    import base64

    assert base64.b64decode(sample["data"]) == jpeg.tobytes()
    with pytest.raises(ValueError, match="JPEG"):
        make_sample(spec, 1.0, {"data": b"not a jpeg"})


async def test_a_consumer_waiting_before_the_source_starts_still_gets_frames():
    slot: LatestSlot[int] = LatestSlot()
    waiter = asyncio.ensure_future(slot.get_newer(0))  # the track starts first (lazy bind)
    await asyncio.sleep(0.01)
    slot.bind(asyncio.get_running_loop())  # then the source starts and binds the slot
    t = threading.Thread(target=slot.put, args=(5,))
    t.start()
    t.join()
    assert await asyncio.wait_for(waiter, 2.0) == (1, 5)


def _orphaned_video_child(stop) -> None:
    """A video process whose follower is already gone, with a thread that never ends."""
    import threading as th

    from humantele.runtime.child import watch_parent

    th.Thread(target=lambda: th.Event().wait()).start()  # not a daemon thread
    gone = os.getppid() + 1_000_000  # not our parent: the follower is gone
    watch_parent(gone, stop.set, grace_s=0.3).join()


@pytest.mark.e2e  # spawns a video child process (the fast lane leaves it out)
def test_a_video_process_whose_follower_is_gone_ends_itself():
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    stop = ctx.Event()
    p = ctx.Process(target=_orphaned_video_child, args=(stop,))
    p.start()
    p.join(60.0)  # a hang guard: it ends about 0.3 s after it starts
    try:
        assert p.exitcode == 0 and stop.is_set()
    finally:
        if p.is_alive():
            p.kill()

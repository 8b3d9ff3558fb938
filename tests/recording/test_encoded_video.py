"""Every received video frame recorded encoded, as it left the jitter buffer (issue 21 §1):
the tap on the jitter buffer, the receiver's recorded sample (codec, keyframe flag, RTP
timestamp, capture time once anchored) and the file written and read back."""

from __future__ import annotations

import base64
import time

from aiortc.rtp import RtpPacket

from humantele.media.aiortc_hooks import EncodedFrameTap
from humantele.media.config import ExpertVideoConfig
from humantele.media.jitter import BoundedJitterBuffer, vp8_is_keyframe
from humantele.media.receiver import VIDEO_RATE, VideoReceiver
from humantele.recording import Recorder, RecorderConfig, read_recording
from humantele.transport.clocksync import ClockSync, SyncSample

KEY = b"\x10\x02\x00\x9d\x01\x2a" + bytes(20)  # a VP8 key frame's header (RFC 6386 9.1)
DELTA = b"\x31\x02\x00" + bytes(12)


def packets(frames: list[bytes], ts0: int = 1000, seq0: int = 7) -> list[RtpPacket]:
    """One RTP packet per frame, timestamps 4500 (50 ms) apart."""
    out = []
    for i, data in enumerate(frames):
        p = RtpPacket(sequence_number=(seq0 + i) % 65536, timestamp=(ts0 + 4500 * i) % (1 << 32),
                      marker=1)  # fmt: skip
        p._data = data
        out.append(p)
    return out


def test_the_tap_sees_each_released_frame_with_its_rtp_timestamp_and_passes_it_on():
    got: list[tuple[bytes, int]] = []
    buf = BoundedJitterBuffer(vp8_is_keyframe)
    tap = EncodedFrameTap(buf, lambda data, ts: got.append((data, ts)))
    released = [tap.add(p)[1] for p in packets([DELTA, KEY, DELTA])]
    # the first delta frame is dropped by the buffer (it waits for a keyframe): not recorded
    assert [f.data if f else None for f in released] == [None, KEY, DELTA]
    assert got == [(KEY, 5500), (DELTA, 10000)]
    assert tap.counters is buf.counters and tap.counters.frames == 2 and tap.tapped == 2


def test_a_failing_recording_never_stops_the_video():
    def boom(data: bytes, ts: int) -> None:
        raise OSError("disk gone")

    tap = EncodedFrameTap(BoundedJitterBuffer(vp8_is_keyframe), boom)
    frames = [tap.add(p)[1] for p in packets([KEY, DELTA, DELTA])]
    assert all(f is not None for f in frames)
    assert tap.tap_errors == 3 and tap.tapped == 0


class Synced(ClockSync):
    """Clock sync with a fixed estimate: follower clock = expert clock + 100 s."""

    def __init__(self) -> None:
        super().__init__()
        self.best = SyncSample(offset=100.0, rtt=0.001, t_local=0.0)


def test_the_receiver_records_codec_keyframe_rtp_time_and_capture_time_once_anchored():
    recorded: list[tuple[str, float, dict]] = []
    now = [50.0]
    rx = VideoReceiver(
        ExpertVideoConfig(enabled=True),
        Synced(),
        now=lambda: now[0],
        record=lambda topic, t, p: recorded.append((topic, t, p)),
    )
    on_frame = rx._encoded_recorder("us")
    top = (1 << 32) - 4500
    on_frame(KEY, top)  # before the anchor: no capture time
    st = rx.stats_by_track["us"]
    # what _on_frame learns from the first decoded frame: capture (follower clock 150.0 s) at
    # pts 0 (aiortc's pts counts from the first frame)
    st.anchor = int(150.0 * VIDEO_RATE)
    now[0] = 50.1
    on_frame(DELTA, 0)  # the RTP timestamp wrapped: 4500 ticks later, not 2**32 earlier
    (t0, s0, p0), (t1, s1, p1) = [(t, topic, p) for topic, t, p in recorded]
    assert s0 == s1 == "/expert/us_video" and (t0, t1) == (50.0, 50.1)
    assert p0 == {"data": KEY, "codec": "vp8", "keyframe": True, "rtp_timestamp": top}
    assert p1["keyframe"] is False and p1["rtp_timestamp"] == 0
    assert abs(p1["t_capture"] - (150.05 - 100.0)) < 1e-9  # expert clock
    assert st.encoded_recorded == 2 and rx.stats()["us"]["encoded_recorded"] == 2


def test_recorded_frames_read_back_byte_for_byte_and_bad_ones_are_counted(tmp_path):
    path = tmp_path / "e.mcap"
    big = bytes(range(256)) * 40
    with Recorder(path, "expert", config=RecorderConfig(fsync=False)) as rec:
        rec.write("/expert/pov_video", 1.0, {"data": KEY, "codec": "vp8", "keyframe": True,
                                              "rtp_timestamp": 9, "t_capture": 0.95})  # fmt: skip
        rec.write("/expert/pov_video", 1.05, {"data": big, "codec": "vp8", "keyframe": False,
                                               "rtp_timestamp": 4509})  # fmt: skip
        rec.write("/expert/pov_video", 1.1, {"data": b"", "codec": "vp8", "keyframe": False,
                                              "rtp_timestamp": 1})  # fmt: skip
        rec.write("/expert/pov_video", 1.1, {"data": "abc", "codec": "vp9", "keyframe": False,
                                              "rtp_timestamp": 1})  # fmt: skip
    assert rec.stats.dropped_invalid == 2
    r = read_recording(path)
    s = r.samples("/expert/pov_video")
    assert [base64.b64decode(x["data"]) for x in s] == [KEY, big]
    assert [x.get("t_capture") for x in s] == [0.95, None] and s[0]["keyframe"] is True


def test_video_waiting_in_the_queue_is_bounded_in_bytes_and_poses_still_pass(tmp_path):
    """A stalled disk must not let video frames take the memory: beyond ``queue_mb`` they are
    dropped and counted; small samples are still queued."""
    cfg = RecorderConfig(fsync=False, queue_mb=0.05, poll_interval_s=0.1)
    rec = Recorder(tmp_path / "e.mcap", "expert", config=cfg)
    frame = {"data": bytes(10_000), "codec": "vp8", "keyframe": False, "rtp_timestamp": 1}
    accepted = sum(rec.write("/expert/us_video", 1.0, frame) for _ in range(100))
    pose = {"position": [0.0, 0.0, 0.0], "quaternion": [0.0, 0.0, 0.0, 1.0]}
    assert rec.write("/expert/pose", 1.0, pose)
    stats = rec.close()
    assert 5 <= accepted < 50 and stats.dropped_overflow == 100 - accepted
    r = read_recording(tmp_path / "e.mcap")
    assert r.count("/expert/us_video") == accepted and r.count("/expert/pose") == 1
    # once written, the budget is free again
    rec2 = Recorder(tmp_path / "f.mcap", "expert", config=cfg)
    for _ in range(3):
        assert rec2.write("/expert/us_video", 1.0, frame)
        deadline = time.monotonic() + 10.0
        while rec2._bytes_out < rec2._bytes_in and time.monotonic() < deadline:
            time.sleep(0.01)  # the writer thread takes it within its poll interval
    assert sum(rec2.write("/expert/us_video", 1.0, frame) for _ in range(4)) == 4
    rec2.close()

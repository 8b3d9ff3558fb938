"""The US picture's SSIM at the expert from the recordings (humantele.study.quality): each
decoded frame is matched to the follower's recorded capture by its drawn counter; frames
before a keyframe and undecodable ones add nothing; a worse encoding scores lower."""

from __future__ import annotations

import base64
import sys
from pathlib import Path

import cv2
import pytest
from aiortc.codecs.vpx import vp8_depayload

from humantele.media.config import BitrateConfig
from humantele.media.encoders import make_encoder
from humantele.media.jitter import vp8_is_keyframe
from humantele.study.quality import us_ssim

sys.path.insert(0, str(Path(__file__).parents[1] / "media"))
from test_encoders import sim_us_frames  # noqa: E402


@pytest.fixture(scope="module")
def frames():
    return sim_us_frames(24)


def recordings(frames, kbps, record_every=3):
    """What a session records: the expert's encoded frames, the follower's JPEGs (q 80)."""
    enc = make_encoder("video/VP8", BitrateConfig(start_kbps=kbps, min_kbps=kbps, max_kbps=kbps))
    expert, follower = [], []
    for i, (seq, frame) in enumerate(frames):
        payloads, _ = enc.encode(frame)
        data = b"".join(vp8_depayload(p) for p in payloads)
        key = vp8_is_keyframe(data)
        expert.append({"t": i / 20.0, "data": base64.b64encode(data).decode(), "codec": "vp8",
                       "keyframe": key})  # fmt: skip
        if seq % record_every == 0:
            bgr = frame.to_ndarray(format="bgr24")
            ok, buf = cv2.imencode(".jpg", bgr, [int(cv2.IMWRITE_JPEG_QUALITY), 80])
            follower.append({"t": i / 20.0, "data": buf.tobytes(), "seq": seq})
    return expert, follower


def test_each_recorded_capture_is_scored_against_its_decoded_frame(frames):
    expert, follower = recordings(frames, 1500)
    out = us_ssim(expert, follower)
    assert [seq for _, seq, _ in out] == [s["seq"] for s in follower]
    assert all(0.85 < q <= 1.0 for _, _, q in out)
    low = us_ssim(*recordings(frames, 150))
    assert sum(q for *_, q in low) / len(low) < sum(q for *_, q in out) / len(out)


def test_frames_before_a_keyframe_or_undecodable_add_nothing(frames):
    expert, follower = recordings(frames, 1000, record_every=1)
    assert us_ssim(expert[1:], follower) == []  # no keyframe: nothing decodes
    broken = [*expert[:5], {**expert[5], "data": base64.b64encode(b"\x00junk").decode()}]
    assert [seq for _, seq, _ in us_ssim(broken, follower)][:5] == [1, 2, 3, 4, 5]
    assert us_ssim(expert, []) == [] and us_ssim([], follower) == []

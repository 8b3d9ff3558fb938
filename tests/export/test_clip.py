"""The console's cine as an MP4 clip (humantele.export.clip): the frames at their capture
times, the last seconds only, bad JPEGs skipped and counted, never over an existing file."""

from __future__ import annotations

import av
import cv2
import pytest
from video_fixtures import picture

from humantele.export.clip import write_clip
from humantele.video.fidelity import psnr


def jpeg(i: int) -> bytes:
    return cv2.imencode(".jpg", picture(i), [cv2.IMWRITE_JPEG_QUALITY, 92])[1].tobytes()


def test_the_cines_last_seconds_become_an_mp4_of_those_frames(tmp_path):
    frames = [(100.0 + i / 20, jpeg(i)) for i in range(60)]  # 3 s at 20 fps
    frames[30] = (frames[30][0], b"\xff\xd8 not a jpeg")
    info = write_clip(frames, tmp_path / "clip.mp4", seconds=2.0)
    assert info.bad_frames == 1 and info.frames == 40  # the last 2 s: 41 frames, one bad
    assert info.duration_s == pytest.approx(2.0, abs=0.01)
    with av.open(str(tmp_path / "clip.mp4")) as c:
        assert c.streams.video[0].codec_context.name == "h264"
        pics = [f.to_ndarray(format="bgr24") for f in c.decode(video=0)]
    assert len(pics) == 40
    assert psnr(picture(59), pics[-1]) > 30.0 > psnr(picture(40), pics[-1])


def test_nothing_decodable_or_an_existing_file_is_refused(tmp_path):
    with pytest.raises(ValueError, match="no decodable frame"):
        write_clip([(1.0, b"junk")], tmp_path / "a.mp4")
    (tmp_path / "b.mp4").write_bytes(b"keep")
    with pytest.raises(FileExistsError):
        write_clip([(1.0, jpeg(0))], tmp_path / "b.mp4")
    assert (tmp_path / "b.mp4").read_bytes() == b"keep"

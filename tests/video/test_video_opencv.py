"""The opencv backend on a video file written here as the "device", and on missing ones."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from humantele.video.base import VideoSourceError, VideoSourceUnavailable
from humantele.video.counter import draw_counter, read_counter
from humantele.video.opencv_source import OpenCVVideoConfig, OpenCVVideoSource
from humantele.video.sources import make_video_source

N_FRAMES, W, H = 12, 160, 120


@pytest.fixture
def clip(tmp_path):
    """An MJPEG .avi of 12 frames, each with its number in the counter code."""
    path = tmp_path / "us_machine.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (W, H))
    assert writer.isOpened()
    for i in range(N_FRAMES):
        img = np.full((H, W, 3), (40 + 10 * i, 90, 160), dtype=np.uint8)
        draw_counter(img, 100 + i)
        writer.write(img)
    writer.release()
    return path


def test_reads_every_frame_in_order_then_reports_the_stall(clip):
    cfg = OpenCVVideoConfig(device=str(clip), pixel_spacing_mm=(0.3, 0.3), stall_reads=3)
    src = make_video_source(cfg)
    assert isinstance(src, OpenCVVideoSource)
    src.open()
    assert src.size == (W, H) and src.fps == pytest.approx(25.0)
    frames = [src.read() for _ in range(N_FRAMES)]
    assert [read_counter(f.image) for f in frames] == [100 + i for i in range(N_FRAMES)]
    assert [f.seq for f in frames] == list(range(1, N_FRAMES + 1))
    f = frames[3]
    assert f.image.shape == (H, W, 3) and f.image.dtype == np.uint8
    assert f.image.flags["C_CONTIGUOUS"] and f.pixel_spacing_mm == (0.3, 0.3)
    # BGR as written (MJPEG keeps colours to a few levels).
    assert np.allclose(f.image[H - 10, W - 10], (70, 90, 160), atol=8)
    assert all(a.t_capture <= b.t_capture for a, b in zip(frames, frames[1:], strict=False))
    # End of the stream: two reads give None (counted), the third declares the stall.
    assert src.read() is None and src.read() is None
    assert src.counters.dropped == 2
    with pytest.raises(VideoSourceError, match="stopped delivering"):
        src.read()
    with pytest.raises(VideoSourceError):  # and stays stopped
        src.read()
    assert src.counters.frames == N_FRAMES
    src.close()
    src.close()  # twice is fine


def test_reopen_after_a_stall_starts_again(clip):
    src = OpenCVVideoSource(OpenCVVideoConfig(device=str(clip), stall_reads=1))
    with src:
        for _ in range(N_FRAMES):
            assert src.read() is not None
        with pytest.raises(VideoSourceError):
            src.read()
    with src:
        assert read_counter(src.read().image) == 100


@pytest.mark.parametrize("device", ["/nonexistent/capture0", "97"])
def test_missing_device_is_a_clear_error_at_start(device):
    src = OpenCVVideoSource(OpenCVVideoConfig(device=device))
    with pytest.raises(VideoSourceUnavailable) as err:
        src.open()
    msg = str(err.value)
    assert "\n" not in msg and "check" in msg
    assert (device in msg) if not device.isdigit() else ("index 97" in msg)


def test_a_file_that_is_not_a_video_is_a_clear_error(tmp_path):
    path = tmp_path / "garbage.bin"  # (a text file is a video to FFmpeg: its "tty" demuxer)
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 20000, dtype=np.uint8).tobytes())
    with pytest.raises(VideoSourceUnavailable, match="garbage.bin"):
        OpenCVVideoSource(OpenCVVideoConfig(device=str(path))).open()


def test_read_before_open_is_an_error(clip):
    with pytest.raises(VideoSourceError, match="before open"):
        OpenCVVideoSource(OpenCVVideoConfig(device=str(clip))).read()


def test_a_file_plays_at_its_rate_and_loops_when_asked(clip):
    """A file replays a recorded source: at the file's rate (not all at once, as a device
    would not give them) and, with ``loop``, from the start again at its end."""
    import time

    src = OpenCVVideoSource(OpenCVVideoConfig(device=str(clip), loop=True, stall_reads=2))
    src.open()
    t0 = time.monotonic()
    frames = [src.read() for _ in range(2 * N_FRAMES + 3)]
    took = time.monotonic() - t0
    assert took >= (2 * N_FRAMES + 1) / 25.0 * 0.95  # paced: a busy machine is only slower
    numbers = [read_counter(f.image) for f in frames]
    assert numbers == [100 + i % N_FRAMES for i in range(2 * N_FRAMES + 3)]  # looped, in order
    assert src.counters.dropped == 0

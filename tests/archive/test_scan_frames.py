"""A whole scan kept for the archive (expert/console/scan_frames.py): one frame every
1/scan_fps s of the US frames received, memory bounded however long the scan (the frames
halved, the rate halved, the whole scan still spanned), one calibration per image, and each
scan archived once: on request (at its end, or after it) or with ``send_scans`` at its end."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from exam_helpers import frame

from humantele.expert.console.scan_frames import KeptScan, ScanFrames

GEO = (64, 48, (0.3, 0.3), 0.0)


def kept(interval=0.1, max_frames=10_000, max_bytes=1e12) -> KeptScan:
    return KeptScan(1, interval, max_frames, max_bytes)


def feed(k: KeptScan, seconds: float, fps: float = 20.0, size: int = 1000, jitter=0.0, t0=0.0):
    """Frames of a source at ``fps`` (times with uniform jitter, s) offered for ``seconds``."""
    rng = np.random.default_rng(1)
    for i in range(int(seconds * fps)):
        t = t0 + i / fps + (rng.uniform(-jitter, jitter) if jitter and i else 0.0)
        if k.due(t):
            assert k.add(t, bytes(size), GEO)


def test_a_scan_is_kept_at_scan_fps_from_a_faster_jittery_source():
    k = kept(interval=0.1)
    feed(k, 10.0, fps=20.0, jitter=0.01)
    times = np.array([t for t, _ in k.frames])
    assert times[0] == 0.0 and times[-1] >= 9.85
    assert 97 <= len(times) <= 101  # 10 s at 10 fps, not the source's 20 (nor ~6.7 fps)
    assert np.all(np.diff(times) >= 0.05 - 0.02)


def test_a_long_scan_stays_bounded_and_still_spans_the_whole_scan():
    k = kept(interval=0.1, max_frames=100)
    feed(k, 600.0, fps=20.0)  # 10 minutes: 6000 frames at 10 fps
    times = np.array([t for t, _ in k.frames])
    assert len(times) <= 100 and k.halvings == 6  # 6000 / 2**6 = 94 frames
    assert k.interval_s == pytest.approx(0.1 * 2**6)
    assert times[0] == 0.0 and times[-1] >= 600.0 - k.interval_s - 0.05
    assert np.allclose(np.diff(times), k.interval_s, atol=0.051)  # evenly, the whole scan
    assert k.nbytes == 1000 * len(times)


def test_the_byte_cap_halves_too():
    k = kept(interval=0.1, max_bytes=50_000)
    feed(k, 60.0, size=1000)
    assert 25 <= len(k.frames) <= 50 and k.nbytes <= 50_000 and k.halvings >= 4
    assert k.frames[-1][0] >= 60.0 - k.interval_s - 0.05


def test_frames_of_another_geometry_or_after_the_end_are_left_out_and_counted():
    k = kept()
    assert k.due(0.0) and k.add(0.0, b"a", GEO)
    assert k.due(0.1) and not k.add(0.1, b"b", (64, 48, (0.5, 0.5), 0.0))  # depth changed
    assert k.due(0.2) and not k.add(0.2, b"c", (32, 48, (0.3, 0.3), 0.0))  # size changed
    assert k.due(0.3) and k.add(0.3, b"d", GEO)
    assert k.other_geometry == 2 and [j for _, j in k.frames] == [b"a", b"d"]
    k.ended = True
    assert not k.due(0.4)
    assert not k.add(0.4, b"e", GEO) and k.late == 1


class Scans:
    """The session's scan in progress, a send that remembers, the frames of a sim scanner."""

    def __init__(self, auto: bool = False) -> None:
        self.scan: int | None = None
        self.sent: list[tuple[int, list]] = []
        self.t = 100.0
        self.seq = 0
        self.frames = ScanFrames(lambda: self.scan, self._send, fps=10.0, max_frames=1200,
                                 max_mb=60.0, quality=85, auto=auto)  # fmt: skip

    def _send(self, k: KeptScan) -> None:
        self.sent.append((k.scan, list(k.frames)))
        if len(k.frames) >= 2:  # (as the console's: one with fewer is refused, not built)
            k.outcome = "building"

    async def run(self, seconds: float, fps: float = 20.0) -> None:
        for _ in range(int(seconds * fps)):
            self.seq += 1
            img = cv2.resize(frame(self.seq), (64, 48))
            f = SimpleNamespace(seq=self.seq, t_capture=self.t, width=64, height=48, image=img,
                                pixel_spacing_mm=(0.3, 0.3), depth_origin_row=0.0)  # fmt: skip
            self.frames.offer(f)
            await self.frames.idle()  # (each JPEG made before the next frame: no skips)
            self.t += 1.0 / fps


async def test_asked_during_a_scan_it_is_sent_once_at_its_end_with_its_frames():
    s = Scans()
    assert s.frames.request() == (False, "no scan to archive: start one")
    await s.run(1.0)  # no scan: nothing kept
    assert s.frames.status() is None
    s.scan = 1
    await s.run(2.0)
    ok, text = s.frames.request()
    assert ok and "when it stops" in text and s.sent == []
    await s.run(1.0)
    s.scan = None
    s.frames.poll()
    assert [n for n, _ in s.sent] == [1]
    frames = s.sent[0][1]
    assert 29 <= len(frames) <= 31  # 3 s at 10 fps
    times = [t for t, _ in frames]
    assert times[0] == pytest.approx(101.0) and np.allclose(np.diff(times), 0.1)
    for _, j in frames:  # real JPEGs of the frames, the scanner's picture
        assert cv2.imdecode(np.frombuffer(j, np.uint8), cv2.IMREAD_COLOR).shape == (48, 64, 3)
    ok, text = s.frames.request()
    assert not ok and "already building" in text and len(s.sent) == 1
    assert s.frames.status()["running"] is False and s.frames.status()["frames"] == len(frames)


async def test_asked_after_its_end_it_is_sent_then_a_new_scan_lets_it_go():
    s = Scans()
    s.scan = 1
    await s.run(0.05)  # one frame: nothing to make an image of
    s.scan = None
    ok, text = s.frames.request()
    assert not ok and "1 frame(s)" in text and s.sent == []
    s.scan = 2
    await s.run(1.0)
    s.scan = None
    s.frames.poll()
    assert s.sent == []  # not asked for, not sent
    ok, _ = s.frames.request()
    assert ok and [n for n, _ in s.sent] == [2]
    s.frames.last.outcome = "queued"
    s.scan = 3
    s.frames.poll()
    assert s.frames.last is None and s.frames.current.scan == 3 and s.frames.current.frames == []


async def test_send_scans_sends_every_scan_at_its_end():
    s = Scans(auto=True)
    for n in (1, 2):
        s.scan = n
        await s.run(1.0)
        s.scan = None
        await s.run(0.5)
    s.scan = 3  # a scan of which nothing was kept (no console open): offered, refused there
    s.frames.poll()
    s.scan = None
    s.frames.poll()
    assert [(n, len(f)) for n, f in s.sent][2] == (3, 0)
    assert [n for n, _ in s.sent] == [1, 2, 3]
    assert all(9 <= len(f) <= 11 for _, f in s.sent[:2])


async def test_received_frames_are_kept_from_their_decoded_planes():
    """The default video path: the expert's decode of a received frame (planar YUV), made a
    JPEG by libavcodec's MJPEG, the same picture."""
    import av

    kept_scans: list[KeptScan] = []
    scan = {"now": 1}
    keeper = ScanFrames(lambda: scan["now"], kept_scans.append, fps=10.0, auto=True)
    pictures = []
    for i in range(6):
        img = cv2.resize(frame(i), (64, 48))
        pictures.append(img)
        planes = av.VideoFrame.from_ndarray(img, format="bgr24").reformat(format="yuv420p")
        keeper.offer(SimpleNamespace(seq=i + 1, t_capture=10.0 + 0.1 * i, width=64, height=48,
                                     pixel_spacing_mm=None, depth_origin_row=None,
                                     av_frame=planes))  # fmt: skip
        await keeper.idle()
    scan["now"] = None
    keeper.poll()
    (k,) = kept_scans
    assert len(k.frames) == 6 and k.geometry == (64, 48, None, None)
    for (_, j), want in zip(k.frames, pictures, strict=True):
        got = cv2.imdecode(np.frombuffer(j, np.uint8), cv2.IMREAD_COLOR)
        assert np.abs(got.astype(int) - want.astype(int)).mean() < 12.0

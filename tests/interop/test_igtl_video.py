"""The ultrasound image over OpenIGTLink from the video tracks: the follower forwards the frames
it sends the expert (its latest-frame slot), the expert the frames it received; the luma, with
the sim ultrasound's pixel size and ImageToProbe."""

import asyncio
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from igtl_client import by_name, read_messages

from humantele.interop.igtl import IgtlConfig
from humantele.interop.sessions import ExpertIgtl, FollowerIgtl
from humantele.media.capture import CapturedFrame, i420_frame
from humantele.media.slot import LatestSlot
from humantele.video.scan import ScanGeometry
from humantele.video.sim_ultrasound import SimUltrasoundConfig

pytestmark = pytest.mark.asyncio


def us_frame(value: int, t: float, w: int = 640, h: int = 480) -> CapturedFrame:
    bgr = np.full((h, w, 3), value, np.uint8)
    bgr[100:120, 200:260] = 250
    yuv = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420)
    return CapturedFrame(i420_frame(yuv, t), 1, t, w, h)


async def connected(side) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    await side.start()
    reader, writer = await asyncio.open_connection("127.0.0.1", side.server.port)
    while not side.server.clients:
        await asyncio.sleep(0.005)
    return reader, writer


async def images(reader, n: int) -> list:
    got: list = []
    task = asyncio.create_task(read_messages(reader, got))
    while len(by_name(got, "Image")) < n:
        await asyncio.sleep(0.01)
        assert not task.done()
    task.cancel()
    return got


def geometry() -> ScanGeometry:
    c = SimUltrasoundConfig()
    return ScanGeometry(c.probe, c.width, c.height, c.depth_m, c.fov_deg, c.radius_m,
                        c.aperture_m, c.beams, c.samples)  # fmt: skip


async def test_follower_forwards_its_us_track_once_per_frame():
    slot: LatestSlot = LatestSlot()
    f = FollowerIgtl(IgtlConfig(enabled=True, port=0), None, (slot, SimUltrasoundConfig()))
    reader, writer = await connected(f)
    f.tick(1.0, None, None)
    assert f.server.stats()["sent"].get("image") is None  # no frame yet
    slot.put(us_frame(90, 2.0))
    f.tick(2.0, None, None)
    f.tick(2.01, None, None)  # the same frame is not sent twice
    got = await images(reader, 1)
    (im,) = by_name(got, "Image")
    assert im.image.shape == (1, 480, 640)
    assert abs(int(im.image[0, 110, 230]) - 250) <= 2 and abs(int(im.image[0, 5, 5]) - 90) <= 2
    s = geometry().pixel_spacing_mm[0]
    assert np.linalg.norm(im.ijk_to_world_matrix[:3, 0]) == pytest.approx(s, rel=1e-5)
    assert im.timestamp == pytest.approx(f.server.wall(2.0), abs=1e-5)
    (itp,) = by_name(got, "ImageToProbe")[:1]
    assert itp.matrix[0, 3] == pytest.approx(geometry().origin_m[0] * 1e3, abs=1e-3)
    await asyncio.sleep(0.1)
    assert f.server.stats()["sent"]["image"] == 1
    writer.close()
    await f.stop()


async def test_follower_forwards_a_scanner_s_picture_with_its_configured_scale():
    """A capture card's US picture: the configured pixel spacing and row of depth 0 give the
    Image's spacing and ImageToProbe (the face's centre at the top middle)."""
    from humantele.video.opencv_source import OpenCVVideoConfig

    slot: LatestSlot = LatestSlot()
    card = OpenCVVideoConfig(pixel_spacing_mm=(0.25, 0.25), depth_origin_row=40.0)
    f = FollowerIgtl(IgtlConfig(enabled=True, port=0), None, (slot, card))
    reader, writer = await connected(f)
    slot.put(us_frame(90, 2.0, 322, 200))
    f.tick(2.0, None, None)
    f.tick(2.05, None, None)
    got = await images(reader, 1)
    (im,) = by_name(got, "Image")
    assert im.image.shape == (1, 200, 322)
    assert np.linalg.norm(im.ijk_to_world_matrix[:3, 0]) == pytest.approx(0.25, rel=1e-5)
    itp = by_name(got, "ImageToProbe")[-1]
    # pixel (row 40, col 160.5) is the tip's origin: x0 = -160.5 px, z0 = -40 px (0.25 mm)
    assert itp.matrix[0, 3] == pytest.approx(-40.125, abs=1e-6)
    assert itp.matrix[2, 3] == pytest.approx(-10.0, abs=1e-6)
    writer.close()
    await f.stop()


async def test_expert_forwards_the_received_us_frame_with_its_scaled_spacing():
    e = ExpertIgtl(IgtlConfig(enabled=True, port=0))
    reader, writer = await connected(e)
    cf = us_frame(60, 3.0, 320, 240)  # received at half size
    received = SimpleNamespace(frame=cf.frame, width=320, height=240, t_capture=2.9,
                               t_received=3.0, seq=7)  # fmt: skip
    e.tick(3.0, None, None, None, received)
    got = await images(reader, 1)
    (im,) = by_name(got, "Image")
    assert im.image.shape == (1, 240, 320)
    s = geometry().pixel_spacing_mm[0] * 2
    assert np.linalg.norm(im.ijk_to_world_matrix[:3, 0]) == pytest.approx(s, rel=1e-5)
    assert im.timestamp == pytest.approx(e.server.wall(2.9), abs=1e-5)
    writer.close()
    await e.stop()

"""The OpenIGTLink server: frames and units, images, several clients, stalled clients dropped
and counted, reconnection, a taken port."""

import asyncio
import json
import socket

import numpy as np
import pytest
from igtl_client import by_name, read_messages

from humantele.geometry import Pose, quat_from_axis_angle
from humantele.interop.igtl import (
    R_RAS_PATIENT,
    IgtlConfig,
    IgtlServer,
    force_text,
    image_to_probe,
    ras_from_patient,
    world_from_ras,
)
from humantele.video.scan import ScanGeometry
from waits import until


async def started(**kw) -> IgtlServer:
    srv = IgtlServer(IgtlConfig(enabled=True, port=0, **kw))
    assert await srv.start()
    return srv


async def connect(srv: IgtlServer):
    reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
    for _ in range(200):
        if srv.clients:
            break
        await asyncio.sleep(0.005)
    return reader, writer


def test_patient_frame_to_ras():
    # Patient x head->feet, y anterior, z to the patient's right -> R = z, A = y, S = -x.
    T = Pose(np.array([0.01, 0.02, 0.03]), np.array([0.0, 0.0, 0.0, 1.0]))
    m = ras_from_patient(T)
    assert m[:3, 3] == pytest.approx([30.0, 20.0, -10.0])  # mm
    assert np.linalg.det(R_RAS_PATIENT) == pytest.approx(1.0)
    # T_world_RAS @ T_RAS_tip = T_world_tip (mm): the chain Slicer builds.
    T_world_patient = Pose(np.array([0.3, 0.9, -0.1]), quat_from_axis_angle([0, 1, 0], 0.4))
    T_patient_tip = Pose(np.array([0.05, 0.1, -0.02]), quat_from_axis_angle([1, 0, 0], 0.3))
    chain = world_from_ras(T_world_patient) @ ras_from_patient(T_patient_tip)
    want = (T_world_patient @ T_patient_tip).as_matrix()
    assert chain[:3, :3] == pytest.approx(want[:3, :3])
    assert chain[:3, 3] == pytest.approx(want[:3, 3] * 1e3)


def test_image_to_probe_puts_each_pixel_where_the_scan_geometry_says():
    g = ScanGeometry("curvilinear", 320, 240, 0.16)
    s = g.pixel_spacing_mm[0]
    T = image_to_probe(g.origin_m, s)
    for row, col in [(0, 0), (100, 37), (239, 319)]:
        p_img = np.array([col * s, row * s, 0.0, 1.0])  # image frame, mm
        x, z = g.pixel_to_tip(row, col)
        assert (T @ p_img)[:3] == pytest.approx([x * 1e3, 0.0, z * 1e3], abs=1e-9)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


async def test_transforms_reach_a_client_in_mm_with_the_sample_time():
    srv = await started()
    reader, writer = await connect(srv)
    got: list = []
    task = asyncio.create_task(read_messages(reader, got, stop_after=2))
    T = Pose(np.array([0.1, -0.02, 0.3]), quat_from_axis_angle([0, 0, 1], 0.5))
    m = ras_from_patient(T)
    assert srv.publish_transform("ProbeToPatient", m, t=100.0)
    assert not srv.publish_transform("ProbeToPatient", m, t=100.005)  # 60 Hz cap
    srv.publish_string("ProbeForce", force_text(np.array([0.1, 0.2, -2.0]), True), 100.0)
    await asyncio.wait_for(task, 5)
    (tf,) = by_name(got, "ProbeToPatient")
    assert tf.matrix == pytest.approx(m, abs=1e-4)  # float32 on the wire
    assert tf.timestamp == pytest.approx(srv.wall(100.0), abs=1e-6)
    (fs,) = by_name(got, "ProbeForce")
    assert json.loads(fs.string) == {"force_tip_n": [0.1, 0.2, -2.0],
                                     "magnitude_n": pytest.approx(2.0125, abs=1e-3),
                                     "contact": True}  # fmt: skip
    assert srv.stats()["sent"] == {"transform": 1, "string": 1}
    writer.close()
    await srv.stop()


async def test_non_finite_pose_is_dropped_and_counted():
    srv = await started()
    _, writer = await connect(srv)
    m = np.eye(4)
    m[0, 3] = np.nan
    assert not srv.publish_transform("ProbeToPatient", m, 1.0)
    assert srv.stats()["dropped"] == {"bad_pose": 1}
    writer.close()
    await srv.stop()


async def test_image_with_spacing_reaches_the_client():
    srv = await started()
    reader, writer = await connect(srv)
    got: list = []
    task = asyncio.create_task(read_messages(reader, got, stop_after=1))
    img = np.zeros((48, 64, 3), np.uint8)
    img[10:20, 30:40, 1] = 200  # green channel (grey BGR image)
    assert srv.publish_image(img, (0.4, 0.4), t=5.0)
    await asyncio.wait_for(task, 5)
    (im,) = by_name(got, "Image")
    assert im.image.shape == (1, 48, 64)
    assert im.image[0, 15, 35] == 200 and im.image[0, 5, 5] == 0
    assert np.linalg.norm(im.ijk_to_world_matrix[:3, 0]) == pytest.approx(0.4, abs=1e-6)
    assert im.ijk_to_world_matrix[:3, 3] == pytest.approx([0.0, 0.0, 0.0], abs=1e-4)
    assert im.world_coordinate_system == "ras"
    writer.close()
    await srv.stop()


async def test_stalled_client_gets_drops_and_a_live_client_gets_everything():
    srv = await started(max_queued_bytes=200_000, image_rate_hz=60.0)
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # small window; never reads
    stalled.connect(("127.0.0.1", srv.port))
    reader, writer = await connect(srv)
    while srv.clients < 2:
        await asyncio.sleep(0.005)
    got: list = []
    task = asyncio.create_task(read_messages(reader, got))
    img = np.full((480, 640), 90, np.uint8)  # 300 kB per message
    published = 0
    for _ in range(60):
        while srv._image_busy:  # noqa: SLF001 - wait for the packer, not the clients
            await asyncio.sleep(0.001)
        srv._last.clear()  # noqa: SLF001 - no rate cap for the test
        published += srv.publish_image(img, (0.3, 0.3), 1.0)
        await asyncio.sleep(0.02)  # the live client reads
    while srv._image_busy:  # noqa: SLF001
        await asyncio.sleep(0.001)
    await asyncio.sleep(0.3)
    st = srv.stats()
    # The stalled client: what the kernel's socket buffers took, then drops, never a queue
    # beyond the limit (plus the one message an empty queue always takes).
    (slow,) = [c for c in srv._clients if c.sent < published]  # noqa: SLF001
    assert slow.sent + slow.dropped == published and slow.dropped >= 30
    assert slow.writer.transport.get_write_buffer_size() <= 200_000 + img.size + 100
    assert st["dropped"]["image"] == slow.dropped
    assert len(by_name(got, "Image")) == published  # the live one missed nothing
    stalled.close()
    writer.close()
    task.cancel()
    await srv.stop()


async def test_client_that_leaves_and_returns_is_served_again():
    srv = await started(max_clients=1)
    m = np.eye(4)
    for round_ in range(2):
        reader, writer = await connect(srv)
        got: list = []
        task = asyncio.create_task(read_messages(reader, got, stop_after=1))
        srv._last.clear()  # noqa: SLF001
        assert srv.publish_transform("ProbeToPatient", m, 1.0 + round_)
        await asyncio.wait_for(task, 5)
        assert len(got) == 1
        writer.close()
        await writer.wait_closed()
        for _ in range(200):
            if not srv.clients:
                break
            await asyncio.sleep(0.005)
    st = srv.stats()
    assert st["connections"] == 2 and st["evicted"] == 0 and st["clients"] == 0
    assert not srv.publish_transform("ProbeToPatient", m, 9.0)  # nobody listening: no work
    await srv.stop()


async def test_idle_clients_never_keep_slicer_out_the_idlest_gives_way():
    """Four idle connections fill the places; a fifth (Slicer) still gets in and is served:
    the one idle longest is closed. One that sent bytes since is not the idlest."""
    srv = await started(max_clients=4)
    idle = []
    for i in range(4):
        idle.append(await asyncio.open_connection("127.0.0.1", srv.port))
        await until(lambda n=i + 1: srv.clients == n, what=f"{i + 1} clients")
    # The first one speaks (as Slicer's STATUS would): the second is now the idlest.
    idle[0][1].write(b"x" * 58)
    await until(lambda: any(c.bytes_in for c in srv._clients), what="bytes read")  # noqa: SLF001
    slicer_r, slicer_w = await asyncio.open_connection("127.0.0.1", srv.port)
    await until(lambda: srv.stats()["evicted"] == 1, what="an eviction")
    assert await asyncio.wait_for(idle[1][0].read(10), 5) == b""  # the idlest: closed
    got: list = []
    task = asyncio.create_task(read_messages(slicer_r, got, stop_after=1))
    await until(lambda: srv.clients == 4, what="4 clients")
    assert srv.publish_transform("ProbeToPatient", np.eye(4), 1.0)
    await asyncio.wait_for(task, 5)
    assert [m.device_name for _, m in got] == ["ProbeToPatient"]
    for i in (0, 2, 3):  # the others are still served
        assert not idle[i][0].at_eof()
    st = srv.stats()
    assert st["connections"] == 5 and st["evicted"] == 1 and st["clients"] == 4
    for _, w in idle:
        w.close()
    slicer_w.close()
    await srv.stop()


async def test_a_taken_port_is_a_clear_error_not_a_crash(caplog):
    srv = await started()
    other = IgtlServer(IgtlConfig(enabled=True, port=srv.port))
    assert not await other.start()
    assert "cannot listen on 127.0.0.1" in other.error and "PLUS" in caplog.text
    await other.stop()
    await srv.stop()


def test_config_is_off_by_default_and_bad_values_are_refused(tmp_path):
    from humantele.config import ConfigError, load_config
    from humantele.follower.daemon import FollowerConfig

    c = FollowerConfig()
    assert not c.igtl.enabled and (c.igtl.host, c.igtl.port) == ("127.0.0.1", 18944)
    bad = tmp_path / "f.toml"
    bad.write_text("[follower.igtl]\nenabled = true\nport = 70000\n")
    with pytest.raises(ConfigError, match="port"):
        load_config(FollowerConfig, bad, "follower")

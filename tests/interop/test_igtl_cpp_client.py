"""An independent client: a receiver built on the OpenIGTLink C++ library (Debian's
libopenigtlink-dev, compiled here from tests/interop/igtl_receiver.cxx) reads what the
humantele server sends, CRC-checked, with the same numbers."""

import asyncio
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from humantele.geometry import Pose, quat_from_axis_angle
from humantele.interop.igtl import IgtlConfig, IgtlServer, force_text, ras_from_patient

HERE = Path(__file__).parent
INCLUDE = Path("/usr/include/openigtlink")


@pytest.fixture(scope="module")
def receiver(tmp_path_factory) -> str:
    cxx = shutil.which("c++") or shutil.which("g++")
    if cxx is None or not (INCLUDE / "igtlTransformMessage.h").exists():
        pytest.skip(
            "no C++ compiler or no OpenIGTLink C++ library (system packages g++ libopenigtlink-dev)"
        )
    out = tmp_path_factory.mktemp("igtl") / "igtl_receiver"
    subprocess.run([cxx, "-O1", "-o", str(out), str(HERE / "igtl_receiver.cxx"),
                    f"-I{INCLUDE}", "-lOpenIGTLink"], check=True)  # fmt: skip
    return str(out)


@pytest.mark.e2e  # compiles and runs the C++ receiver process (not in the fast lane)
@pytest.mark.asyncio
async def test_cpp_openigtlink_receiver_reads_transform_image_and_string(receiver):
    srv = IgtlServer(IgtlConfig(enabled=True, port=0))
    assert await srv.start()
    proc = await asyncio.create_subprocess_exec(
        receiver, "127.0.0.1", str(srv.port), "3", stdout=asyncio.subprocess.PIPE
    )
    while not srv.clients:
        await asyncio.sleep(0.01)
    T = Pose(np.array([0.12, -0.03, 0.2]), quat_from_axis_angle([0.3, 1, 0.2], 0.7))
    m = ras_from_patient(T)
    assert srv.publish_transform("ProbeToPatient", m, 50.0)
    img = np.zeros((120, 160), np.uint8)
    img[40:60, 10:30] = 180
    assert srv.publish_image(img, (0.35, 0.35), 50.0)
    while srv._image_busy:  # noqa: SLF001 - the worker is packing
        await asyncio.sleep(0.005)
    srv.publish_string("ProbeForce", force_text(np.array([0.0, 0.0, -1.5]), True), 50.0)
    out, _ = await asyncio.wait_for(proc.communicate(), 30)
    await srv.stop()
    lines = {ln.split()[0]: ln.split(maxsplit=4) for ln in out.decode().splitlines()}
    tf = out.decode().splitlines()[0].split()
    assert tf[:3] == ["TRANSFORM", "ProbeToPatient", "1"]  # CRC checked by the library
    assert float(tf[3]) == pytest.approx(srv.wall(50.0), abs=1e-5)
    got = np.array([float(v) for v in tf[4:]]).reshape(3, 4)
    assert got == pytest.approx(m[:3, :], abs=1e-4)
    im = lines["IMAGE"][4].split()
    assert lines["IMAGE"][1:3] == ["Image", "1"]
    assert [int(v) for v in im[:3]] == [160, 120, 1]
    assert [float(v) for v in im[3:5]] == pytest.approx([0.35, 0.35], abs=1e-6)
    assert int(im[6]) == 3 and int(im[7]) == 20 * 20  # uint8; the bright patch only
    assert lines["STRING"][1:3] == ["ProbeForce", "1"]
    assert json.loads(lines["STRING"][4])["magnitude_n"] == pytest.approx(1.5)

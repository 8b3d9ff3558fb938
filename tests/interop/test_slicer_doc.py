"""docs/slicer.md's scripting example, run as written (only the port is the test's) against a
follower's OpenIGTLink server before any calibration: ``ProbeToWorld`` comes with each tracked
frame from the start, ``ProbeToPatient`` only once calibrated (issue 20 item 6)."""

from __future__ import annotations

import asyncio
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from igtl_client import by_name, read_messages

from humantele.geometry import Pose, quat_from_axis_angle
from humantele.interop.igtl import IgtlConfig
from humantele.interop.sessions import FollowerIgtl

DOC = Path(__file__).resolve().parents[2] / "docs" / "slicer.md"


def doc_example() -> str:
    """The Python block under "## Scripting (Python)"."""
    text = DOC.read_text()
    section = text[text.index("## Scripting (Python)") :]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def run_python(code: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout_s
    )


def test_the_example_reads_the_documented_device_on_the_default_port():
    code = doc_example()
    assert '"127.0.0.1", 18944' in code and "wait_for_message(" in code and ".matrix" in code


@pytest.mark.slow
@pytest.mark.e2e
async def test_the_doc_example_runs_against_an_uncalibrated_follower(session, tmp_path):
    cfg = tmp_path / "follower.toml"
    # Never calibrated: the sim patient is 0.16 m wide, so its side landmark is refused and
    # the sim novice keeps pressing landmarks with the (tracked) probe.
    cfg.write_text(
        "[follower.calibration]\nmin_half_width_m = 0.3\n[follower.video]\nenabled = false\n"
    )
    await session.start("follower", "--config", str(cfg), "--igtl-port", "0")
    await session.wait(
        "OpenIGTLink served and the probe tracked",
        lambda e, f: (
            (f.get("igtl") or {}).get("port")
            and f.get("measurements", 0) > f.get("tracking_lost", 0) + 10
        ),
        timeout=120,
    )
    port = session.stats("follower")["igtl"]["port"]
    code = doc_example().replace("18944", str(port))
    done = await asyncio.to_thread(run_python, code)
    assert done.returncode == 0, f"the example failed:\n{done.stdout}\n{done.stderr}"
    rows = re.findall(r"\[([-\d.e+\s]+)\]", done.stdout)
    m = np.array([[float(v) for v in row.split()] for row in rows[-4:]])
    assert m.shape == (4, 4) and m[3] == pytest.approx([0, 0, 0, 1])
    assert m[:3, :3] @ m[:3, :3].T == pytest.approx(np.eye(3), abs=1e-4)  # a rotation
    assert 100.0 < np.linalg.norm(m[:3, 3]) < 5000.0  # mm: the probe is in the room
    # ProbeToPatient needs the calibration: none comes before it (as the page says).
    code = doc_example().replace("18944", str(port)).replace('"ProbeToWorld"', '"ProbeToPatient"')
    code = code.replace("print(msg.matrix)", "print('none' if msg is None else msg.matrix)")
    done = await asyncio.to_thread(run_python, code)
    assert done.returncode == 0 and done.stdout.strip() == "none", done.stdout + done.stderr
    assert not session.stats("follower")["calibrated"]
    assert await session.terminate("follower") == 0


async def test_probe_to_world_from_the_first_frame_and_probe_to_patient_once_calibrated():
    f = FollowerIgtl(IgtlConfig(enabled=True, port=0, image=False))
    await f.start()
    reader, writer = await asyncio.open_connection("127.0.0.1", f.server.port)
    while not f.server.clients:
        await asyncio.sleep(0.005)
    got: list = []
    task = asyncio.create_task(read_messages(reader, got))
    tip = Pose(np.array([0.4, 0.9, -0.2]), quat_from_axis_angle([0, 1, 0], 0.7))
    m = SimpleNamespace(T_world_tip=tip, force_tip=None, contact=False)
    f.on_measurement(1.0, None, m)  # not calibrated: the world pose only
    cal = SimpleNamespace(
        T_world_patient=Pose(np.array([0.3, 0.8, -0.1]), quat_from_axis_angle([0, 1, 0], 0.3))
    )
    f.on_measurement(2.0, cal, m)
    f.tick(2.0, cal, None)  # PatientToWorld
    while len(by_name(got, "PatientToWorld")) < 1:
        await asyncio.sleep(0.01)
        assert not task.done()
    world = by_name(got, "ProbeToWorld")
    assert len(world) == 2 and len(by_name(got, "ProbeToPatient")) == 1
    assert world[0].matrix[:3, 3] == pytest.approx(tip.position * 1e3, abs=1e-3)  # mm
    # inverse(PatientToWorld) @ ProbeToWorld = ProbeToPatient, as docs/slicer.md says.
    (p2w,) = by_name(got, "PatientToWorld")
    (probe,) = by_name(got, "ProbeToPatient")
    chain = np.linalg.inv(p2w.matrix.astype(float)) @ world[1].matrix.astype(float)
    assert chain == pytest.approx(probe.matrix, abs=1e-3)
    task.cancel()
    writer.close()
    await f.stop()

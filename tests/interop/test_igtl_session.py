"""OpenIGTLink during a loopback session: a client on each daemon receives the poses, the force
and the ultrasound image, and the probe pose it receives is the one the follower recorded."""

import asyncio
import json
import time

import numpy as np
import pytest
from igtl_client import by_name, read_messages

from humantele.geometry import Pose
from humantele.interop.igtl import ras_from_patient
from humantele.recording import read_recording, role_path

pytestmark = [pytest.mark.asyncio, pytest.mark.slow]


async def collect(port: int, enough, timeout: float = 90.0) -> list:
    """Messages from the server at ``port`` until ``enough(messages)`` (or ``timeout``)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    got: list = []
    task = asyncio.create_task(read_messages(reader, got))
    t_end = time.monotonic() + timeout
    while not enough(got) and time.monotonic() < t_end and not task.done():
        await asyncio.sleep(0.1)
    writer.close()
    task.cancel()
    return got


def counts(*wanted: tuple[str, int]):
    return lambda got: all(len(by_name(got, n)) >= k for n, k in wanted)


async def test_slicer_client_gets_the_session_in_mm_matching_the_recording(session, tmp_path):
    base = tmp_path / "i.mcap"
    rec = ["--record", str(role_path(base, "follower")), "--session-id", "i01"]
    # The probe measured as the simulated truth and no WebRTC video: what is checked here is
    # what OpenIGTLink sends (the image then comes from its own sim ultrasound process; the
    # video-track path is tested in test_igtl_video.py), not the IR tracker or the video
    # link, and it keeps the session light on 2 cores.
    cfg = tmp_path / "follower.toml"
    cfg.write_text('[follower]\nprobe_source = "truth"\n[follower.video]\nenabled = false\n')
    e_cfg = tmp_path / "expert.toml"
    e_cfg.write_text("[expert.video]\nenabled = false\n")
    session.save_calibration()  # calibrating: tests/browser/test_headset_session.py
    await session.start("follower", "--config", str(cfg), "--igtl-port", "0", *rec)
    await session.start("expert", "--config", str(e_cfg), "--igtl-port", "0")
    await session.wait(
        "calibrated, connected, following",
        lambda e, f: f.get("calibrated") and f.get("link_state") == "connected"
        and e.get("states_received", 0) > 50 and (f.get("igtl") or {}).get("port")
        and (e.get("igtl") or {}).get("port"),
        timeout=120,
    )  # fmt: skip
    f_port = session.stats("follower")["igtl"]["port"]
    e_port = session.stats("expert")["igtl"]["port"]
    f_msgs, e_msgs = await asyncio.gather(
        collect(f_port, counts(("ProbeToPatient", 60), ("Image", 5), ("VirtProbeToPatient", 5))),
        collect(e_port, counts(("StylusToPatient", 20), ("ProbeToPatient", 20))),
    )
    await session.wait("both served", lambda e, f: f["igtl"]["connections"] >= 1
                       and e["igtl"]["connections"] >= 1)  # fmt: skip
    assert await session.terminate("expert") == 0
    assert await session.terminate("follower") == 0

    names = {m.device_name for _, m in f_msgs}
    assert {"ProbeToPatient", "VirtProbeToPatient", "PatientToWorld", "ProbeForce",
            "ImageToProbe", "Image"} <= names, names  # fmt: skip
    assert {"StylusToPatient", "ProbeToPatient", "ProbeForce"} <= {m.device_name for _, m in e_msgs}

    # The probe pose received equals the pose the follower recorded at that frame (mm, RAS).
    r = read_recording(role_path(base, "follower"), ["/follower/probe_pose"])
    samples = [s for s in r.samples("/follower/probe_pose") if s["tracked"]]
    t_rec = np.array([s["t"] for s in samples])
    offset = time.time() - time.monotonic()  # same clocks as the follower's (one machine)
    probe = by_name(f_msgs, "ProbeToPatient")
    assert len(probe) >= 40
    matched = 0
    for msg in probe:
        i = int(np.argmin(np.abs(t_rec - (msg.timestamp - offset))))
        assert abs(t_rec[i] - (msg.timestamp - offset)) < 0.002
        s = samples[i]
        want = ras_from_patient(Pose(np.array(s["position"]), np.array(s["quaternion"])))
        assert msg.matrix[:3, 3] == pytest.approx(want[:3, 3], abs=1e-3)  # mm (float32)
        assert msg.matrix[:3, :3] == pytest.approx(want[:3, :3], abs=1e-6)
        matched += 1
    assert matched == len(probe)
    # Millimetres: the probe is on the abdomen, tens to hundreds of mm from the xiphoid.
    assert 5.0 < np.linalg.norm(probe[-1].matrix[:3, 3]) < 600.0

    images = by_name(f_msgs, "Image")
    assert len(images) >= 5
    im = images[-1]
    assert im.image.shape == (1, 480, 640) and im.image.dtype == np.uint8
    spacing = np.linalg.norm(im.ijk_to_world_matrix[:3, 0])
    assert 0.1 < spacing < 1.0  # mm per pixel of a 16 cm deep sector on 480 rows
    assert im.image.max() > 50  # the probe is on the patient: echoes, not a blank frame
    force = json.loads(by_name(f_msgs, "ProbeForce")[-1].string)
    assert set(force) == {"force_tip_n", "magnitude_n", "contact"}

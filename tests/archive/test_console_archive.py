"""The console with ``[expert.archive]`` on, against a pynetdicom archive in the test process:
the patient entered on the page (a POST, never a URL), a capture before it refused with the
reason, the capture, its clip, a caliper and a note archived as DICOM, the page told
"archived N of N"; and the patient's identity appears in no log line, recording, capture side
file or stats, only in the objects and their queue."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import aiohttp
import pytest
from exam_helpers import PATIENT, SECRET_NAME
from scp_helpers import ArchiveSCP

from humantele.archive.config import ArchiveConfig
from humantele.expert.console import ConsoleConfig, ConsoleServer
from humantele.expert.console.archive_routes import ConsoleArchive
from humantele.recording import Recorder

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "expert"))
from test_console_server import FakeClock, ManualFrames, Session, next_message  # noqa: E402

from waits import until


@pytest.fixture
def scp():
    s = ArchiveSCP().start()
    yield s
    s.stop()


async def test_the_exam_from_the_console_reaches_the_archive_and_nowhere_else(
    tmp_path, scp, caplog
):
    caplog.set_level(logging.DEBUG)
    clock = FakeClock()
    frames = ManualFrames(clock)
    rec = Recorder(tmp_path / "s.expert.mcap", "expert")
    session = Session(recorder=rec)
    server = ConsoleServer(ConsoleConfig(port=0, captures_dir=str(tmp_path / "captures")),
                           frames, session, clock=clock)  # fmt: skip
    cfg = ArchiveConfig(enabled=True, port=scp.port, called_ae=scp.aet,
                        queue_dir=str(tmp_path / "queue"), retry_min_s=0.1)  # fmt: skip
    server.archive = ConsoleArchive(cfg, server.key, scan=lambda: session.scan)
    await server.start()
    headers = {"X-Console-Key": server.key}
    base = server.address.rstrip("/")
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            async with http.get(f"{base}/archive/status") as r:
                assert r.status == 401  # no key, nothing
            for _ in range(4):
                f = frames.next("us")
                await next_message(ws, lambda k, d, s=f.seq: k == "frame" and d[0]["seq"] == s)
                clock.t += 0.05
            # a capture before the patient: saved on disk, not archived, the page says why
            await ws.send_json({"type": "capture", "seq": 1, "clip_s": 0})
            await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
            await until(lambda: "enter the patient" in server.archive.last)
            bad = {**PATIENT.model_dump(mode="json"), "sex": "X"}
            async with http.post(f"{base}/archive/exam", json=bad, headers=headers) as r:
                assert r.status == 400 and "sex" in (await r.json())["error"]
            body = PATIENT.model_dump(mode="json")
            async with http.post(f"{base}/archive/exam", json=body, headers=headers) as r:
                assert r.status == 200
            session.scan = 1
            await ws.send_json({"type": "caliper", "seq": 4, "a": [10, 20], "b": [40, 60]})
            await ws.send_json({"type": "annotation", "seq": 4, "at": [50, 50], "text": "cyst"})
            await ws.send_json({"type": "capture", "seq": 4, "clip_s": 5})
            await until(lambda: len(scp.kept) == 4)  # image, clip, SR, presentation state
            await ws.send_json({"type": "caliper", "seq": 4, "a": [0, 0], "b": [30, 40]})
            await until(lambda: len(scp.kept) == 6)  # a new SR and presentation state
            await until(lambda: server.archive.status()["archived"] == 6)  # (its answers)
            async with http.get(f"{base}/archive/status", headers=headers) as r:
                status = await r.json()
            assert status["text"] == "archived 6 of 6" and status["exam"]
            # a full queue: the capture is saved on disk, its archiving refused with the reason
            server.archive.archive.queue.max_bytes = 1
            await ws.send_json({"type": "capture", "seq": 3, "clip_s": 0})
            r = await next_message(ws, lambda k, d: k == "json" and d["type"] == "result")
            assert r["ok"]  # (the still itself is saved)
            await until(lambda: "queue_max_mb" in server.archive.last)
            assert server.archive.status()["not_archived"] == {"no_exam": 1, "queue_full": 1}
            stats = json.dumps(server.stats())
    finally:
        await server.stop()
        rec.close()
    kinds = sorted(str(d.SOPClassUID.name) for d in scp.kept.values())
    assert kinds == sorted(["Ultrasound Image Storage", "Ultrasound Multi-frame Image Storage"]
                           + ["Comprehensive 3D SR Storage"] * 2
                           + ["Color Softcopy Presentation State Storage"] * 2)  # fmt: skip
    assert all(d.PatientID == PATIENT.patient_id for d in scp.kept.values())
    assert set(scp.stores.values()) == {1}
    # identity: nowhere but in the objects and the queue's folder
    assert SECRET_NAME not in caplog.text and PATIENT.patient_id not in caplog.text
    assert SECRET_NAME not in stats and PATIENT.patient_id not in stats
    for path in (tmp_path / "captures").iterdir():
        assert SECRET_NAME.encode() not in path.read_bytes(), path
    recording = (tmp_path / "s.expert.mcap").read_bytes()
    for secret in (SECRET_NAME, PATIENT.patient_id, PATIENT.accession_number):
        assert secret.encode() not in recording


async def test_the_expert_daemon_s_console_says_whether_the_archive_is_on(tmp_path):
    from types import SimpleNamespace

    from humantele.expert.console.hook import DaemonConsole

    expert = SimpleNamespace(scan=None, clock=lambda: 0.0)
    for enabled in (True, False):
        cfg = ArchiveConfig(enabled=enabled, queue_dir=str(tmp_path / "q"))
        host = DaemonConsole(ConsoleConfig(port=0, video="none"), None, cfg)
        await host.start(expert)
        try:
            url = f"{host.server.address}archive/status"
            async with (
                aiohttp.ClientSession() as http,
                http.get(url, headers={"X-Console-Key": host.server.key}) as r,
            ):
                assert r.status == 200  # (never a 404: the page's console stays clean)
                status = await r.json()
                assert status["enabled"] is enabled
                if enabled:
                    assert status["text"] == "archived 0 of 0"
                else:
                    assert set(status) == {"enabled"}
        finally:
            await host.stop()


async def test_a_whole_scan_asked_for_on_the_console_reaches_the_archive(tmp_path, scp, caplog):
    """'Archive scan' during a scan: at its end the US frames the console received, one every
    1/scan_fps s, go as one Ultrasound Multi-frame Image into the scan's series (its frame
    times the capture times' intervals, its pixels the scanner's), through the same queue, the
    page told; asked again: refused, never sent twice; dciodvfy finds no error in it."""
    import shutil
    import subprocess

    import cv2
    import numpy as np
    from pydicom.encaps import generate_frames
    from pydicom.uid import UltrasoundImageStorage, UltrasoundMultiFrameImageStorage

    from humantele.archive.queue import to_bytes

    caplog.set_level(logging.DEBUG)
    clock = FakeClock()
    frames = ManualFrames(clock)
    session = Session()
    server = ConsoleServer(ConsoleConfig(port=0, captures_dir=str(tmp_path / "captures")),
                           frames, session, clock=clock)  # fmt: skip
    cfg = ArchiveConfig(enabled=True, port=scp.port, called_ae=scp.aet, scan_fps=10,
                        queue_dir=str(tmp_path / "queue"), retry_min_s=0.1)  # fmt: skip
    server.archive = ConsoleArchive(cfg, server.key, scan=lambda: session.scan)
    await server.start()
    headers = {"X-Console-Key": server.key}
    base = server.address.rstrip("/")
    shown: dict[float, np.ndarray] = {}  # capture time -> the scanner's picture

    async def scan_frames(n: int) -> None:
        for _ in range(n):
            f = frames.next("us")
            shown[f.t_capture] = f.image
            await next_message(ws, lambda k, d, s=f.seq: k == "frame" and d[0]["seq"] == s)
            await ws.send_json({"type": "drawn", "track": "us", "seq": f.seq,
                                "draw_to_send_ms": 1.0})  # fmt: skip
            await server.archive.scans.idle()
            clock.t += 0.05  # 20 fps

    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(server.ws_url) as ws:
            async with http.post(f"{base}/archive/scan") as r:
                assert r.status == 401
            async with http.post(f"{base}/archive/scan", headers=headers) as r:
                assert r.status == 409 and "enter the patient" in (await r.json())["error"]
            async with http.post(f"{base}/archive/exam", json=PATIENT.model_dump(mode="json"),
                                 headers=headers) as r:  # fmt: skip
                assert r.status == 200
            await scan_frames(4)  # before the scan: not kept
            session.scan = 1
            await scan_frames(40)
            last = frames.latest("us")
            await ws.send_json({"type": "capture", "seq": last.seq, "clip_s": 0})
            async with http.post(f"{base}/archive/scan", headers=headers) as r:
                assert r.status == 200 and "when it stops" in (await r.json())["text"]
            await scan_frames(20)
            await until(lambda: len(scp.kept) == 1)  # the still; the scan waits for its end
            session.scan = None  # (noticed with no frame coming)
            await until(lambda: len(scp.kept) == 2)
            await until(lambda: server.archive.status()["archived"] == 2)
            async with http.get(f"{base}/archive/status", headers=headers) as r:
                status = await r.json()
            assert status["text"] == "archived 2 of 2" and status["made"]["scan"] == 1
            assert status["scan_archive"]["outcome"] == "queued"
            assert status["scan_archive"]["frames"] == 30 and "queued" in status["last"]
            async with http.post(f"{base}/archive/scan", headers=headers) as r:
                assert r.status == 409 and "already queued" in (await r.json())["error"]
            stats = json.dumps(server.stats())
    finally:
        await server.stop()
    by_class = {str(d.SOPClassUID): d for d in scp.kept.values()}
    image, scan = by_class[UltrasoundImageStorage], by_class[UltrasoundMultiFrameImageStorage]
    assert set(scp.stores.values()) == {1}
    assert scan.SeriesInstanceUID == image.SeriesInstanceUID  # one series per scan
    assert scan.StudyInstanceUID == image.StudyInstanceUID and scan.PatientID == "HT-0042"
    assert scan.NumberOfFrames == 30  # 3 s of a 20 fps scanner, kept at 10 fps
    assert scan.FrameTimeVector[0] == 0 and all(
        abs(v - 100.0) < 0.01 for v in scan.FrameTimeVector[1:])  # fmt: skip
    region = scan.SequenceOfUltrasoundRegions[0]
    spacing = frames.frames["us"].pixel_spacing_mm
    assert region.PhysicalDeltaY == pytest.approx(spacing[0] / 10)
    first = min(t for t in shown if t >= 100.0 + 4 * 0.05 - 1e-9)
    kept_times = [first + 0.1 * k for k in range(30)]
    for k, jpeg in enumerate(generate_frames(scan.PixelData, number_of_frames=30)):
        if k % 7:
            continue
        picture = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        want = shown[min(shown, key=lambda t, k=k: abs(t - kept_times[k]))]
        assert np.abs(picture.astype(int) - want.astype(int)).mean() < 4.0, k
    assert SECRET_NAME not in caplog.text and PATIENT.patient_id not in caplog.text
    assert SECRET_NAME not in stats and PATIENT.patient_id not in stats
    if shutil.which("dciodvfy") is not None:  # (CI has it: Debian dicom3tools)
        path = tmp_path / "scan.dcm"
        path.write_bytes(to_bytes(scan))
        out = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True)
        errors = [x for x in (out.stdout + out.stderr).splitlines() if x.startswith("Error")]
        assert errors == [], out.stdout + out.stderr

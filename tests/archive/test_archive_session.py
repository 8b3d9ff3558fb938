"""Privacy with the real expert daemon: an exam with a known patient is entered on the
console, a still, its clip, a caliper and the whole scan they were taken in ("Archive scan")
reach the archive (a pynetdicom archive in the test process); then every log, stats file,
capture file and the session's recording is read: the patient's name, ID and accession
number are in none of them, only in the archived objects.
One daemon (the expert, sim video on its console), a few seconds."""

import asyncio
import json
import sys
from pathlib import Path

import aiohttp
import pytest
from exam_helpers import PATIENT, SECRET_NAME
from scp_helpers import ArchiveSCP

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "session"))
from session_helpers import CONSOLE_KEY, session  # noqa: E402, F401 - the fixture

from humantele.expert.console.messages import parse_header  # noqa: E402

SECRETS = (SECRET_NAME, PATIENT.given_name, PATIENT.patient_id, PATIENT.accession_number)


@pytest.fixture
def scp():
    s = ArchiveSCP().start()
    yield s
    s.stop()


@pytest.mark.slow
async def test_the_patient_is_in_the_archive_and_in_no_log_or_recording(session, scp, tmp_path):  # noqa: F811, E501
    cfg = tmp_path / "expert.toml"
    cfg.write_text(
        "[expert.console]\n"
        'video = "sim"\n'
        f"captures_dir = {json.dumps(str(tmp_path / 'captures'))}\n"
        "[expert.archive]\n"
        "enabled = true\n"
        f"port = {scp.port}\n"
        f'called_ae = "{scp.aet}"\n'
        f"queue_dir = {json.dumps(str(tmp_path / 'queue'))}\n"
        "retry_min_s = 0.5\n"
    )
    await session.start("expert", "--config", str(cfg), "--console-port", "0",
                        "--record", str(tmp_path / "p.expert.mcap"), "--session-id", "p01",
                        "--sonographer-id", "S1", "--follower-id", "F1")  # fmt: skip
    url = None
    for _ in range(600):
        url = (session.stats("expert").get("console") or {}).get("url")
        if url:
            break
        await asyncio.sleep(0.1)
    assert url, session.logs()
    headers = {"X-Console-Key": CONSOLE_KEY}
    ws_url = url.replace("http", "ws", 1) + f"ws?key={CONSOLE_KEY}&transport=jpeg"
    async with aiohttp.ClientSession() as http:
        body = PATIENT.model_dump(mode="json")
        async with http.post(f"{url}archive/exam", json=body, headers=headers) as r:
            assert r.status == 200
        async with http.ws_connect(ws_url) as ws:
            await ws.send_json({"type": "scan", "action": "start", "id": 1})
            seqs = []
            while len(seqs) < 20:  # a second of sim ultrasound in the cine
                msg = await ws.receive(timeout=60)
                if msg.type == aiohttp.WSMsgType.BINARY:
                    h = parse_header(msg.data)
                    if h["track"] == "us":
                        seqs.append(h["seq"])
                        await ws.send_json({"type": "drawn", "track": "us", "seq": h["seq"],
                                            "draw_to_send_ms": 0.1})  # fmt: skip
                assert msg.type != aiohttp.WSMsgType.CLOSED, session.logs()
            seq = seqs[-2]
            await ws.send_json({"type": "caliper", "seq": seq, "a": [10, 10], "b": [60, 90]})
            await ws.send_json({"type": "capture", "seq": seq, "clip_s": 1})
            async with http.post(f"{url}archive/scan", headers=headers) as r:
                assert r.status == 200, await r.text()  # (the scan archived at its end)
            await ws.send_json({"type": "scan", "action": "stop", "id": 2})
            status = {}
            for _ in range(600):
                async with http.get(f"{url}archive/status", headers=headers) as r:
                    status = await r.json()
                if status["total"] >= 5 and status["archived"] == status["total"]:
                    break
                await asyncio.sleep(0.1)
            assert status.get("text") == "archived 5 of 5", (status, session.logs())
            assert status["scan_archive"]["scan"] == 1, status
    assert await session.terminate("expert") == 0
    assert all(str(d.PatientName).startswith(SECRET_NAME) for d in scp.kept.values())
    assert len(scp.kept) == 5 and set(scp.stores.values()) == {1}
    multi = [d for d in scp.kept.values() if "Multi-frame" in str(d.SOPClassUID.name)]
    assert len(multi) == 2  # the capture's clip and the whole scan, both in scan 1's series
    assert len({d.SeriesInstanceUID for d in multi}) == 1
    read = 0
    for path in tmp_path.rglob("*"):
        if not path.is_file() or "queue" in path.relative_to(tmp_path).parts:
            continue
        data = path.read_bytes()
        read += 1
        for secret in SECRETS:
            assert secret.encode() not in data, f"{secret!r} in {path}"
    assert read >= 4  # the log, the stats, the recording, the captured still (and more)

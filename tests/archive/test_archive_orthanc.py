"""The exam against a real archive: Orthanc (Debian package ``orthanc``, ``orthanc-dicomweb``),
one instance for the module, started with a temporary configuration on free loopback ports.
The captures arrive under the right patient, study and series (its REST API), the images it
renders are the ones the sonographer saw, the SR's measurement references them; STOW-RS
does the same; an outage and a refused object lose nothing and send nothing twice."""

import io
import json

import cv2
import numpy as np
import pytest
from exam_helpers import PATIENT, frame, jpeg
from pydicom import dcmread
from pydicom.uid import generate_uid

from humantele.archive import objects as obj
from humantele.archive.config import ArchiveConfig
from humantele.archive.orthanc import OrthancError, OrthancServer
from humantele.archive.send import make_sender
from humantele.archive.service import ExamArchive

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not OrthancServer.available(),
                       reason="Orthanc (Debian package orthanc) is not installed; CI installs it"),
]  # fmt: skip

REFUSED_SCAN = "refuse"
SCALE = obj.Scale((0.2, 0.2), 0.0)


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture(scope="module")
def pacs():
    server = OrthancServer(refuse_series=f"tele-ultrasound {REFUSED_SCAN}")
    try:
        server.start()
    except OrthancError as exc:
        pytest.skip(str(exc))
    yield server
    server.close()


@pytest.fixture
def empty(pacs):
    if pacs.proc is None:
        pacs.start()
    pacs.clear()
    return pacs


def archive(tmp_path, pacs, clock, **kw) -> ExamArchive:
    cfg = ArchiveConfig(enabled=True, port=pacs.dicom_port, called_ae=pacs.aet,
                        queue_dir=str(tmp_path), retry_min_s=2, retry_max_s=30, **kw)  # fmt: skip
    return ExamArchive(cfg, unix_offset_s=1.79e9, sender=make_sender(cfg), clock=clock)


def sends(tmp_path) -> dict[int, int]:
    out: dict[int, int] = {}
    for line in (tmp_path / "journal.jsonl").read_text().splitlines():
        ev = json.loads(line)
        if ev["ev"] == "sending":
            out[ev["n"]] = out.get(ev["n"], 0) + 1
    return out


def test_the_session_s_captures_arrive_under_the_patient_study_and_series(tmp_path, empty):
    a = archive(tmp_path, empty, Clock(), performing_physician="Expert^Sam")
    a.begin(PATIENT)
    still = jpeg(3)
    clip = [(10.0 + 0.05 * k, jpeg(k)) for k in range(6)]
    items = a.capture(3, still, 10.25, SCALE, "scan 1", clip=clip)
    items += a.capture(9, jpeg(9), 20.0, SCALE, "scan 2")
    items += a.mark(3, caliper=obj.Caliper((100, 240), (300, 240), 40.0), scan="scan 1")
    items.append(a.scan("scan 1", [(11.0 + 0.1 * k, jpeg(k)) for k in range(8)], SCALE))
    assert [i.kind for i in items] == ["image", "clip", "image", "sr", "pr", "scan"]
    assert a.forwarder.step() is None
    assert a.status()["text"] == "archived 6 of 6"

    patients = empty.get("/patients")
    assert len(patients) == 1
    p = empty.get(f"/patients/{patients[0]}")
    assert p["MainDicomTags"]["PatientID"] == PATIENT.patient_id
    assert p["MainDicomTags"]["PatientName"] == PATIENT.dicom_name
    (study_id,) = p["Studies"]
    study = empty.get(f"/studies/{study_id}")
    assert study["MainDicomTags"]["StudyInstanceUID"] == a.exams.exam.study_instance_uid
    assert study["MainDicomTags"]["AccessionNumber"] == PATIENT.accession_number
    series = {s["MainDicomTags"]["SeriesInstanceUID"]: s for s in empty.get(
        f"/studies/{study_id}/series?expand")}  # fmt: skip
    assert {a.exams.series_for(k)[0] for k in ("scan 1", "scan 2", "reports")} == set(series)
    scan1 = series[a.exams.series_for("scan 1")[0]]
    assert len(scan1["Instances"]) == 3 and scan1["MainDicomTags"]["Modality"] == "US"

    # the image Orthanc renders is the one the sonographer saw
    inst = json.loads(empty.request("POST", "/tools/lookup", items[0].sop.encode()))[0]
    png = empty.get_bytes(f"/instances/{inst['ID']}/preview")
    shown = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE).astype(float)
    seen = cv2.imdecode(np.frombuffer(still, np.uint8), cv2.IMREAD_GRAYSCALE).astype(float)
    assert shown.shape == seen.shape
    assert np.abs(shown - seen).mean() < 2.0  # two JPEG decoders, the same picture
    other = cv2.cvtColor(frame(9), cv2.COLOR_BGR2GRAY).astype(float)
    assert np.abs(shown - other).mean() > 10.0  # (a different frame is not "the same")

    clip_inst = json.loads(empty.request("POST", "/tools/lookup", items[1].sop.encode()))[0]
    tags = empty.get(f"/instances/{clip_inst['ID']}/simplified-tags")
    assert int(tags["NumberOfFrames"]) == 6

    # the whole scan, in the scan's series: each frame Orthanc renders is the one received
    scan_inst = json.loads(empty.request("POST", "/tools/lookup", items[5].sop.encode()))[0]
    tags = empty.get(f"/instances/{scan_inst['ID']}/simplified-tags")
    assert int(tags["NumberOfFrames"]) == 8
    times = [float(v) for v in tags["FrameTimeVector"].split("\\")]
    assert times == pytest.approx([0.0] + [100.0] * 7)  # ms, from the capture times
    for k in (0, 5):
        png = empty.get_bytes(f"/instances/{scan_inst['ID']}/frames/{k}/preview")
        shown = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE).astype(float)
        seen = cv2.cvtColor(frame(k), cv2.COLOR_BGR2GRAY).astype(float)
        assert np.abs(shown - seen).mean() < 4.0, k  # (JPEG q88 and two decoders)

    # the SR's measurement references the image, as the archive holds it
    sr_inst = json.loads(empty.request("POST", "/tools/lookup", items[3].sop.encode()))[0]
    sr = dcmread(io.BytesIO(empty.get_bytes(f"/instances/{sr_inst['ID']}/file")))
    import highdicom as hd

    group = hd.sr.Comprehensive3DSR.from_dataset(sr).content.get_planar_roi_measurement_groups()[0]
    assert group.get_measurements()[0].value == pytest.approx(40.0)
    ref = group.roi.ContentSequence[0].ReferencedSOPSequence[0].ReferencedSOPInstanceUID
    assert ref == items[0].sop
    assert sr.PatientID == PATIENT.patient_id

    # asked after an interruption, the archive says it holds an instance (C-FIND)
    conn = a.forwarder.sender.connect()
    try:
        assert conn.has(items[0]) is True
        items[0].sop = generate_uid()  # a valid UID (<= 64 characters) it never got
        assert conn.has(items[0]) is False
    finally:
        conn.close()


def test_an_outage_then_a_refusal_nothing_lost_nothing_twice(tmp_path, empty):
    clock = Clock()
    a = archive(tmp_path, empty, clock)
    a.begin(PATIENT)
    first = a.capture(1, jpeg(1), 1.0, SCALE, "scan 1")
    assert a.forwarder.step() is None
    empty.stop()  # the archive goes down during the session
    during = []
    for k in range(2, 5):
        during += a.capture(k, jpeg(k), float(k), SCALE, "scan 1")
        clock.t += 1.0
        a.forwarder.step()
    status = a.status()
    assert status["unreachable"] and "3 waiting" in status["text"]
    refused = a.capture(5, jpeg(5), 5.0, SCALE, REFUSED_SCAN)
    empty.start()
    clock.t += 60.0
    a.forwarder.step()
    st = a.status()
    assert st["archived"] == 4 and st["refused"] == 1, st
    assert st["refused_items"][0]["n"] == refused[0].n
    assert st["refused_items"][0]["reason"] == "status 0xA700: Refused: Out of Resources"
    uids = {i.sop for i in first + during}
    stored = {empty.get(f"/instances/{i}")["MainDicomTags"]["SOPInstanceUID"]
              for i in empty.get("/instances")}  # fmt: skip
    assert stored == uids
    n_sent = sends(tmp_path)
    assert all(n_sent[i.n] == 1 for i in first + during)  # none twice
    assert a.queue.path(refused[0]).exists()  # kept until the archive accepts it


def test_stow_rs_stores_the_same_objects(tmp_path, empty):
    cfg_kw = {"protocol": "stow", "stow_url": empty.dicomweb_url}
    a = archive(tmp_path, empty, Clock(), **cfg_kw)
    a.begin(PATIENT)
    items = a.capture(1, jpeg(1), 1.0, SCALE, "scan 1", clip=[(0.9, jpeg(0)), (1.0, jpeg(1))])
    assert a.forwarder.step() is None
    assert a.status()["text"] == "archived 2 of 2"
    stored = {empty.get(f"/instances/{i}")["MainDicomTags"]["SOPInstanceUID"]
              for i in empty.get("/instances")}  # fmt: skip
    assert stored == {i.sop for i in items}
    conn = a.forwarder.sender.connect()
    assert conn.has(items[0]) is True

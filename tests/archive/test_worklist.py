"""The Modality Worklist: a pynetdicom worklist SCP in the test process answers the C-FIND
as a department's RIS does; the console's pick carries the order's Study Instance UID and
Accession Number into the exam, and a malformed entry is left out and counted."""

import datetime as dt

import pytest
from pydicom.dataset import Dataset
from pynetdicom import AE, evt
from pynetdicom.sop_class import ModalityWorklistInformationFind

from humantele.archive.config import ArchiveConfig
from humantele.archive.exam import ExamStore
from humantele.archive.orthanc import free_port
from humantele.archive.send import Unreachable
from humantele.archive.worklist import find


def entry(pid, name, acc, uid, modality="US", born="19600102"):
    ds = Dataset()
    ds.PatientID, ds.PatientName, ds.PatientBirthDate, ds.PatientSex = pid, name, born, "M"
    ds.AccessionNumber, ds.StudyInstanceUID = acc, uid
    ds.RequestedProcedureDescription = "Abdomen US"
    step = Dataset()
    step.Modality = modality
    step.ScheduledStationAETitle = "HUMANTELE"
    step.ScheduledProcedureStepStartDate = dt.date.today().strftime("%Y%m%d")
    step.ScheduledProcedureStepStartTime = "0930"
    step.ScheduledProcedureStepDescription = "liver"
    ds.ScheduledProcedureStepSequence = [step]
    return ds


ENTRIES = [
    entry("W-1", "Able^Ann", "A1", "1.2.3.4.1"),
    entry("W-2", "Baker^Bob", "A2", "1.2.3.4.2", modality="CT"),  # not ours
    entry("W-3", "Cole^Cy", "A3", "1.2.3.4.3", born="notadate"),  # malformed
]


@pytest.fixture
def mwl():
    queries = []

    def on_find(event):
        q = event.identifier
        queries.append(q)
        want = q.ScheduledProcedureStepSequence[0]
        for e in ENTRIES:
            step = e.ScheduledProcedureStepSequence[0]
            if step.Modality == want.Modality and (
                not want.ScheduledStationAETitle
                or want.ScheduledStationAETitle == step.ScheduledStationAETitle
            ):
                yield 0xFF00, e
        yield 0x0000, None

    ae = AE(ae_title="RIS")
    ae.add_supported_context(ModalityWorklistInformationFind)
    server = ae.start_server(("127.0.0.1", 0), block=False,
                             evt_handlers=[(evt.EVT_C_FIND, on_find)])  # fmt: skip
    yield server.server_address[1], queries
    server.shutdown()


def test_the_worklist_s_us_entries_become_patients_and_the_exam_keeps_the_order(mwl, tmp_path):
    port, queries = mwl
    cfg = ArchiveConfig(enabled=True, identity="worklist", worklist_port=port, worklist_ae="RIS",
                        station_ae="HUMANTELE", queue_dir=str(tmp_path))  # fmt: skip
    items, bad = find(cfg)
    assert [i.patient.patient_id for i in items] == ["W-1"] and bad == 1
    q = queries[0].ScheduledProcedureStepSequence[0]
    assert q.Modality == "US" and q.ScheduledStationAETitle == "HUMANTELE"
    p = items[0].patient
    assert (p.family_name, p.given_name, p.birth_date) == ("Able", "Ann", dt.date(1960, 1, 2))
    assert items[0].description == "liver"
    exam = ExamStore(tmp_path).begin(p, 1.79e9)
    assert exam.study_instance_uid == "1.2.3.4.1" and exam.patient.accession_number == "A1"


def test_an_absent_worklist_is_said(tmp_path):
    cfg = ArchiveConfig(enabled=True, worklist_port=free_port(), queue_dir=str(tmp_path),
                        timeout_s=5)  # fmt: skip
    with pytest.raises(Unreachable, match="worklist"):
        find(cfg)

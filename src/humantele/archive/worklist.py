"""The department's Modality Worklist: C-FIND (pynetdicom, Modality Worklist Information Model)
for today's scheduled ultrasound exams, as an ultrasound machine asks; each answer becomes a
:class:`~humantele.archive.exam.Patient` the console can pick (its Study Instance UID and
Accession Number kept, so the archive files the exam under the order)."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

from pydicom.dataset import Dataset

from humantele.archive.config import ArchiveConfig
from humantele.archive.exam import Patient
from humantele.archive.send import Unreachable


@dataclass(frozen=True)
class WorklistItem:
    patient: Patient
    scheduled: str  # the step's start (DICOM date + time, as sent)
    description: str

    def __repr__(self) -> str:
        return "WorklistItem(<identity withheld>)"


def query(cfg: ArchiveConfig, day: dt.date | None = None) -> Dataset:
    """The C-FIND identifier: US steps scheduled ``day`` (today) for this station."""
    day = day or dt.date.today()
    q = Dataset()
    q.PatientName, q.PatientID, q.PatientBirthDate, q.PatientSex = "", "", "", ""
    q.AccessionNumber = ""
    q.StudyInstanceUID = ""
    q.RequestedProcedureDescription = ""
    step = Dataset()
    step.Modality = "US"
    step.ScheduledStationAETitle = cfg.station_ae or ""
    step.ScheduledProcedureStepStartDate = day.strftime("%Y%m%d")
    step.ScheduledProcedureStepStartTime = ""
    step.ScheduledProcedureStepDescription = ""
    q.ScheduledProcedureStepSequence = [step]
    return q


def _patient(ds: Dataset) -> Patient | None:
    name = str(ds.get("PatientName", "") or "")
    family, _, given = name.partition("^")
    born = str(ds.get("PatientBirthDate", "") or "")
    try:
        return Patient(
            patient_id=str(ds.get("PatientID", "")),
            family_name=family,
            given_name=given.split("^")[0],
            birth_date=dt.datetime.strptime(born, "%Y%m%d").date() if born else None,
            sex=str(ds.get("PatientSex", "") or "") if ds.get("PatientSex") in "MFO" else "",
            accession_number=str(ds.get("AccessionNumber", "") or ""),
            requested_procedure=str(ds.get("RequestedProcedureDescription", "") or "")[:64],
            study_instance_uid=str(ds.get("StudyInstanceUID", "") or "") or None,
        )
    except ValueError:
        return None  # an entry that is not a usable patient (counted by the caller)


def find(cfg: ArchiveConfig, day: dt.date | None = None) -> tuple[list[WorklistItem], int]:
    """Today's scheduled US exams from ``[expert.archive]``'s worklist SCP, and how many
    answers were unusable. Unreachable when it cannot be asked."""
    from pynetdicom import AE
    from pynetdicom.sop_class import ModalityWorklistInformationFind

    ae = AE(ae_title=cfg.calling_ae)
    ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = cfg.timeout_s
    ae.add_requested_context(ModalityWorklistInformationFind)
    host, port = cfg.worklist_host or cfg.host, cfg.worklist_port or cfg.port
    try:
        assoc = ae.associate(host, port, ae_title=cfg.worklist_ae or cfg.called_ae)
    except OSError as exc:
        raise Unreachable(f"worklist {host}:{port}: {exc}") from exc
    if not assoc.is_established:
        raise Unreachable(f"worklist {host}:{port}: no association")
    items, bad = [], 0
    try:
        for status, ident in assoc.send_c_find(query(cfg, day), ModalityWorklistInformationFind):
            if not status:
                raise Unreachable("worklist: association lost")
            if status.Status in (0xFF00, 0xFF01) and ident is not None:
                p = _patient(ident)
                if p is None:
                    bad += 1
                    continue
                step = (ident.get("ScheduledProcedureStepSequence") or [Dataset()])[0]
                when = f"{step.get('ScheduledProcedureStepStartDate', '')} " \
                       f"{step.get('ScheduledProcedureStepStartTime', '')}".strip()  # fmt: skip
                desc = str(step.get("ScheduledProcedureStepDescription", "") or "")
                items.append(WorklistItem(p, when, desc))
            elif status.Status != 0x0000:
                raise Unreachable(f"worklist: C-FIND status 0x{status.Status:04X}")
    finally:
        if assoc.is_established:
            assoc.release()
    return items, bad

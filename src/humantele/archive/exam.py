"""The patient and the exam the objects belong to, and the UIDs made once for it.

:class:`Patient` is what the console asks for (or picks from the Modality Worklist): patient
ID, name, birth date, sex, accession number. Its ``repr`` hides the values, so a stray log
line cannot print them. :class:`ExamStore` keeps the exam in progress (the patient, the Study
Instance UID, one Series Instance UID per scan, the instance counter) in ``exam.json`` in the
queue's folder, written atomically: a restart of the expert continues the same study. Nothing
here is ever logged, recorded or put in a URL.
"""

from __future__ import annotations

import datetime as dt
import json
import re
import threading
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator
from pydicom.uid import generate_uid

from humantele.archive.files import atomic_write

_CONTROL = re.compile(r"[\x00-\x1f\x7f\\]")


def _text(v: str, what: str, n: int) -> str:
    v = " ".join(str(v).split())
    if _CONTROL.search(v):
        raise ValueError(f"{what}: no control characters or backslash")
    if len(v) > n:
        raise ValueError(f"{what}: at most {n} characters")
    return v


class Patient(BaseModel):
    """Who is scanned and which order the exam fills (DICOM Patient and Study identity)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    patient_id: str = Field(..., description="Patient ID (LO, 1-64)")
    family_name: str = Field("", description="name: family part")
    given_name: str = Field("", description="name: given part")
    birth_date: dt.date | None = None
    sex: str = Field("", pattern=r"^(M|F|O|)$", description="M, F, O or '' (unknown)")
    accession_number: str = Field("", description="the order's Accession Number (SH, <= 16)")
    requested_procedure: str = Field("", description="from the worklist (LO)")
    study_instance_uid: str | None = Field(
        None, description="the worklist's Study Instance UID (None: one is made)"
    )

    @field_validator("patient_id")
    @classmethod
    def _id(cls, v: str) -> str:
        v = _text(v, "patient_id", 64)
        if not v:
            raise ValueError("patient_id: required")
        return v

    @field_validator("family_name", "given_name", "requested_procedure")
    @classmethod
    def _name(cls, v: str, info: Any) -> str:
        v = _text(v, info.field_name, 64)
        if "^" in v or "=" in v:
            raise ValueError(f"{info.field_name}: no '^' or '='")
        return v

    @field_validator("accession_number")
    @classmethod
    def _acc(cls, v: str) -> str:
        return _text(v, "accession_number", 16)

    @field_validator("birth_date")
    @classmethod
    def _born(cls, v: dt.date | None) -> dt.date | None:
        if v is not None and not dt.date(1880, 1, 1) <= v <= dt.date.today():
            raise ValueError("birth_date: not a plausible date of birth")
        return v

    @field_validator("study_instance_uid")
    @classmethod
    def _uid(cls, v: str | None) -> str | None:
        if v is not None and not re.match(r"^[0-9]+(\.[0-9]+)*$", v) or (v and len(v) > 64):
            raise ValueError("study_instance_uid: not a DICOM UID")
        return v

    @property
    def dicom_name(self) -> str:
        """Patient's Name as a DICOM PN: ``Family^Given``."""
        return f"{self.family_name}^{self.given_name}".rstrip("^")

    def __repr__(self) -> str:  # never the values (a log line must not print them)
        return "Patient(<identity withheld>)"

    __str__ = __repr__


class Exam(BaseModel):
    """The exam in progress: its patient and the UIDs made once for it."""

    model_config = ConfigDict(extra="forbid")

    patient: Patient
    study_instance_uid: str
    study_id: str
    started_unix: float = Field(..., description="the exam's start, Unix time (s)")
    series: dict[str, str] = Field(default_factory=dict, description="scan -> Series UID")
    series_numbers: dict[str, int] = Field(default_factory=dict)
    instances: int = 0  # instances made so far (the next Instance Number is this + 1)

    def __repr__(self) -> str:
        return f"Exam(study_id={self.study_id!r}, series={len(self.series)})"

    __str__ = __repr__


class ExamStore:
    """The exam in progress, kept in ``directory/exam.json`` (atomic writes, mode 0600)."""

    def __init__(self, directory: Path) -> None:
        self.path = Path(directory) / "exam.json"
        self._lock = threading.Lock()
        self.exam: Exam | None = None
        if self.path.exists():
            try:
                self.exam = Exam.model_validate_json(self.path.read_bytes())
            except ValueError:  # a broken file: a new exam must be entered (said on the page)
                self.exam = None

    def begin(self, patient: Patient, now_unix: float) -> Exam:
        """A new exam of ``patient`` (a new study unless the worklist gave its UID)."""
        with self._lock:
            study_id = dt.datetime.fromtimestamp(now_unix, dt.UTC).strftime("%y%m%d%H%M")
            self.exam = Exam(
                patient=patient,
                study_instance_uid=patient.study_instance_uid or generate_uid(),
                study_id=study_id,
                started_unix=now_unix,
            )
            self._save()
            return self.exam

    def end(self) -> None:
        """No exam in progress (the next capture needs a patient)."""
        with self._lock:
            self.exam = None
            try:
                self.path.unlink()
            except FileNotFoundError:
                pass

    def series_for(self, scan: str) -> tuple[str, int]:
        """The Series Instance UID and number of ``scan`` (made once, kept)."""
        with self._lock:
            exam = self._need()
            if scan not in exam.series:
                exam.series[scan] = generate_uid()
                exam.series_numbers[scan] = len(exam.series_numbers) + 1
                self._save()
            return exam.series[scan], exam.series_numbers[scan]

    def next_instance(self) -> int:
        """The next Instance Number of the exam (kept across restarts)."""
        with self._lock:
            exam = self._need()
            exam.instances += 1
            self._save()
            return exam.instances

    def _need(self) -> Exam:
        if self.exam is None:
            raise LookupError("no exam: enter the patient first")
        return self.exam

    def _save(self) -> None:
        assert self.exam is not None
        data = json.dumps(self.exam.model_dump(mode="json"), indent=1).encode()
        atomic_write(self.path, data, mode=0o600)

"""Senders to the archive: C-STORE (pynetdicom) or STOW-RS (dicomweb-client).

A sender's :meth:`connect` opens a connection (a DICOM association, or a DICOMweb client)
or raises :class:`Unreachable`; the connection's ``store(path)`` sends one object and returns
the archive's answer for that instance (:class:`Answer`), or raises :class:`Unreachable`
when the connection is lost before the answer; ``has(item)`` asks whether the archive holds
an instance (True/False; None when it cannot say), which the queue uses after a send whose
answer never came.
"""

from __future__ import annotations

import contextlib
import logging
import ssl
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from pydicom import dcmread
from pydicom.dataset import Dataset
from pydicom.uid import (
    ColorSoftcopyPresentationStateStorage,
    Comprehensive3DSRStorage,
    ExplicitVRLittleEndian,
    GrayscaleSoftcopyPresentationStateStorage,
    ImplicitVRLittleEndian,
    JPEGBaseline8Bit,
    UltrasoundImageStorage,
    UltrasoundMultiFrameImageStorage,
)

from humantele.archive.config import ArchiveConfig
from humantele.archive.queue import Item

# pynetdicom logs whole datasets at DEBUG (a worklist answer's patient names among them): its
# loggers stay at WARNING whatever the daemon's --log-level (no identity in logs).
logging.getLogger("pynetdicom").setLevel(logging.WARNING)

# Status codes a C-STORE SCP answers with that mean "stored" (PS3.4 B.2.3): success and the
# warnings (coerced, elements discarded, does not match the SOP class).
STORED = {0x0000, 0xB000, 0xB006, 0xB007}


class Unreachable(Exception):
    """The archive cannot be reached, or the connection was lost before its answer."""


@dataclass(frozen=True)
class Answer:
    """The archive's answer for one instance: stored or not, and why."""

    stored: bool
    reason: str = ""
    status: int | None = None


class Connection(Protocol):
    def store(self, path: Path) -> Answer: ...
    def has(self, item: Item) -> bool | None: ...
    def close(self) -> None: ...


class Sender(Protocol):
    def connect(self) -> Connection: ...


def _tls_context(cfg: ArchiveConfig) -> ssl.SSLContext:
    ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=cfg.tls_ca_file)
    if cfg.tls_cert_file and cfg.tls_key_file:
        ctx.load_cert_chain(cfg.tls_cert_file, cfg.tls_key_file)
    return ctx


class CStoreSender:
    """C-STORE to ``[expert.archive]`` host:port, called_ae, as calling_ae (optional TLS)."""

    CONTEXTS = (
        (UltrasoundImageStorage, [JPEGBaseline8Bit]),
        (UltrasoundMultiFrameImageStorage, [JPEGBaseline8Bit]),
        (Comprehensive3DSRStorage, [ExplicitVRLittleEndian, ImplicitVRLittleEndian]),
        (ColorSoftcopyPresentationStateStorage, [ExplicitVRLittleEndian, ImplicitVRLittleEndian]),
        (GrayscaleSoftcopyPresentationStateStorage, [ExplicitVRLittleEndian]),
    )

    def __init__(self, cfg: ArchiveConfig) -> None:
        self.cfg = cfg

    def connect(self) -> _Association:
        from pynetdicom import AE
        from pynetdicom.sop_class import StudyRootQueryRetrieveInformationModelFind

        cfg = self.cfg
        ae = AE(ae_title=cfg.calling_ae)
        ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = cfg.timeout_s
        ae.connection_timeout = cfg.timeout_s
        for sop, syntaxes in self.CONTEXTS:
            ae.add_requested_context(sop, syntaxes)
        ae.add_requested_context(StudyRootQueryRetrieveInformationModelFind)
        tls = (_tls_context(cfg), cfg.host) if cfg.tls else None
        try:
            assoc = ae.associate(cfg.host, cfg.port, ae_title=cfg.called_ae, tls_args=tls)
        except (OSError, ssl.SSLError) as exc:
            raise Unreachable(f"{cfg.host}:{cfg.port}: {exc}") from exc
        if not assoc.is_established:
            if assoc.is_rejected:
                why = "association rejected (check the AE titles)"
            elif assoc.is_aborted:
                why = "no association (connection refused or aborted)"
            else:
                why = "no answer"
            raise Unreachable(f"{cfg.called_ae}@{cfg.host}:{cfg.port}: {why}")
        return _Association(assoc)


class _Association:
    def __init__(self, assoc: Any) -> None:
        self.assoc = assoc

    def _lost(self) -> bool:
        return not self.assoc.is_established

    def store(self, path: Path) -> Answer:
        ds = dcmread(path)
        try:
            status = self.assoc.send_c_store(ds)
        except ValueError as exc:  # no accepted presentation context for it
            return Answer(False, f"the archive does not take this object: {exc}")
        except (RuntimeError, OSError) as exc:
            raise Unreachable(f"association lost: {exc}") from exc
        if not status or "Status" not in status:
            raise Unreachable("association lost before the archive's answer")
        code = int(status.Status)
        if code in STORED:
            return Answer(True, "" if code == 0 else f"stored with warning 0x{code:04X}", code)
        comment = str(status.get("ErrorComment", "")).strip() or _meaning(code)
        return Answer(False, f"status 0x{code:04X}" + (f": {comment}" if comment else ""), code)

    def has(self, item: Item) -> bool | None:
        from pynetdicom.sop_class import StudyRootQueryRetrieveInformationModelFind

        q = Dataset()
        q.QueryRetrieveLevel = "IMAGE"
        q.StudyInstanceUID, q.SeriesInstanceUID = item.study, item.series
        q.SOPInstanceUID = item.sop
        found = False
        try:
            for status, ident in self.assoc.send_c_find(
                q, StudyRootQueryRetrieveInformationModelFind
            ):
                if not status:
                    raise Unreachable("association lost during C-FIND")
                if status.Status in (0xFF00, 0xFF01) and ident is not None:
                    found = found or str(ident.get("SOPInstanceUID", "")) == item.sop
                elif status.Status != 0x0000:
                    return None
        except ValueError:  # C-FIND not accepted: the archive cannot say
            return None
        except (RuntimeError, OSError) as exc:
            raise Unreachable(f"association lost: {exc}") from exc
        return found

    def close(self) -> None:
        with contextlib.suppress(Exception):
            if self.assoc.is_established:
                self.assoc.release()


class StowSender:
    """STOW-RS to ``[expert.archive] stow_url`` (dicomweb-client)."""

    def __init__(self, cfg: ArchiveConfig) -> None:
        self.cfg = cfg

    def connect(self) -> _Stow:
        import requests
        from dicomweb_client.api import DICOMwebClient

        session = requests.Session()
        if self.cfg.tls_ca_file:
            session.verify = self.cfg.tls_ca_file
        if self.cfg.tls_cert_file:
            session.cert = (self.cfg.tls_cert_file, self.cfg.tls_key_file)
        client = DICOMwebClient(url=self.cfg.stow_url, session=session)
        return _Stow(client, self.cfg.timeout_s)


class _Stow:
    def __init__(self, client: Any, timeout_s: float) -> None:
        self.client = client
        self.timeout_s = timeout_s

    def store(self, path: Path) -> Answer:
        import requests

        ds = dcmread(path)
        try:
            resp = self.client.store_instances([ds])
        except requests.exceptions.HTTPError as exc:
            code = exc.response.status_code if exc.response is not None else None
            if code is None or code >= 500 or code in (401, 403, 404, 408, 429):
                raise Unreachable(f"STOW-RS HTTP {code}") from exc
            return Answer(False, f"STOW-RS HTTP {code}: {_failure(exc.response)}", code)
        except requests.exceptions.RequestException as exc:
            raise Unreachable(f"STOW-RS: {exc}") from exc
        for ref in resp.get("ReferencedSOPSequence", []) or []:
            if str(ref.get("ReferencedSOPInstanceUID", "")) == str(ds.SOPInstanceUID):
                return Answer(True)
        for f in resp.get("FailedSOPSequence", []) or []:
            if str(f.get("ReferencedSOPInstanceUID", "")) == str(ds.SOPInstanceUID):
                code = int(f.get("FailureReason", 0xC000))
                return Answer(False, f"failure reason 0x{code:04X}", code)
        return Answer(False, "the archive's STOW-RS answer does not name this instance")

    def has(self, item: Item) -> bool | None:
        import requests

        try:
            found = self.client.search_for_instances(
                study_instance_uid=item.study, series_instance_uid=item.series,
                search_filters={"SOPInstanceUID": item.sop},
            )  # fmt: skip
        except requests.exceptions.HTTPError:
            return None
        except requests.exceptions.RequestException as exc:
            raise Unreachable(f"QIDO-RS: {exc}") from exc
        return any(item.sop in str(f.get("00080018", {}).get("Value", [])) for f in found)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.client._session.close()


def _meaning(code: int) -> str:
    """The standard's words for a C-STORE status (pynetdicom's table), '' if unknown."""
    from pynetdicom.status import STORAGE_SERVICE_CLASS_STATUS

    for c in (code, code & 0xFF00):
        if c in STORAGE_SERVICE_CLASS_STATUS:
            return STORAGE_SERVICE_CLASS_STATUS[c][1]
    return ""


def _failure(response: Any) -> str:
    try:
        return response.text[:200]
    except Exception:  # noqa: BLE001
        return "(no reason given)"


def make_sender(cfg: ArchiveConfig) -> Sender:
    """The sender ``[expert.archive] protocol`` names."""
    return StowSender(cfg) if cfg.protocol == "stow" else CStoreSender(cfg)

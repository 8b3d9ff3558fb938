"""A small archive in the test process: a pynetdicom Storage SCP (and C-FIND SCP over what it
stored) that counts every C-STORE per SOP Instance UID, refuses chosen ones as a PACS does
(a failure status with an Error Comment), and can abort the association on a chosen store
(before or after keeping the object), or hold a store until told."""

from __future__ import annotations

import threading
import time
from collections import Counter

from pydicom.dataset import Dataset
from pynetdicom import AE, AllStoragePresentationContexts, evt
from pynetdicom.sop_class import StudyRootQueryRetrieveInformationModelFind

from humantele.archive.send import CStoreSender


class ArchiveSCP:
    def __init__(self, aet: str = "TESTPACS") -> None:
        self.aet = aet
        self.stores: Counter[str] = Counter()  # C-STOREs received, per SOP Instance UID
        self.kept: dict[str, Dataset] = {}  # what it holds
        self.order: list[str] = []
        self.refuse: set[str] = set()
        self.abort_on: dict[int, str] = {}  # the k-th store (1-based) -> 'before' | 'after'
        self.hold = threading.Event()
        self.hold.set()
        self.in_store = threading.Event()
        self.server = None
        self.port = 0

    def _store(self, event):
        n = sum(self.stores.values()) + 1
        ds = event.dataset
        ds.file_meta = event.file_meta
        uid = str(ds.SOPInstanceUID)
        self.stores[uid] += 1
        self.in_store.set()
        self.hold.wait(30)
        how = self.abort_on.pop(n, None)
        if how == "after":
            self._keep(uid, ds)
        if how is not None:
            event.assoc.abort()
            return 0xC000
        if uid in self.refuse:
            status = Dataset()
            status.Status = 0xA900
            status.ErrorComment = "SOP instance refused by test"
            return status
        self._keep(uid, ds)
        return 0x0000

    def _keep(self, uid: str, ds: Dataset) -> None:
        if uid not in self.kept:
            self.order.append(uid)
        self.kept[uid] = ds

    def _find(self, event):
        q = event.identifier
        uid = str(q.get("SOPInstanceUID", ""))
        if uid in self.kept:
            r = Dataset()
            r.QueryRetrieveLevel = "IMAGE"
            r.SOPInstanceUID = uid
            r.StudyInstanceUID = self.kept[uid].StudyInstanceUID
            r.SeriesInstanceUID = self.kept[uid].SeriesInstanceUID
            yield 0xFF00, r
        yield 0x0000, None

    def start(self, port: int = 0, ssl_context=None) -> ArchiveSCP:
        ae = AE(ae_title=self.aet)
        for cx in AllStoragePresentationContexts:
            ae.add_supported_context(cx.abstract_syntax, ALL_SYNTAXES)
        ae.add_supported_context(StudyRootQueryRetrieveInformationModelFind)
        self.server = ae.start_server(
            ("127.0.0.1", port), block=False, ssl_context=ssl_context,
            evt_handlers=[(evt.EVT_C_STORE, self._store), (evt.EVT_C_FIND, self._find)],
        )  # fmt: skip
        self.port = self.server.server_address[1]
        return self

    def stop(self) -> None:
        if self.server is not None:
            self.hold.set()
            self.server.shutdown()
            self.server = None

    def wait_stores(self, n: int, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while sum(self.stores.values()) < n and time.monotonic() < deadline:
            time.sleep(0.01)


ALL_SYNTAXES = [
    "1.2.840.10008.1.2",
    "1.2.840.10008.1.2.1",
    "1.2.840.10008.1.2.4.50",
]

__all__ = ["ArchiveSCP", "CStoreSender"]

"""The store-and-forward queue on disk: every object is written here first, then sent.

``directory/objects/NNNNNNNN.dcm`` holds each object (Part 10 file, written atomically:
a crash leaves the whole file or none); ``directory/journal.jsonl`` is the queue's history,
one JSON line per event, flushed to the disk before the step it records is taken:

- ``queued``: the file is there (written before the line);
- ``sending``: a C-STORE / STOW-RS of it is about to start;
- ``archived``: the archive said it holds it (its per-instance answer), or a restart found it
  there; the file is then removed;
- ``refused``: the archive answered it with a failure (its reason); it stays and is tried
  again after a back-off.

At start the journal is read again: an object whose last event is ``sending`` was maybe
received by the archive before a crash; it is ``uncertain`` and the sender asks the archive
whether it holds that SOP Instance UID before sending it again, so nothing is sent twice
(and an archive receiving the same UID again keeps one instance, DICOM's rule). A torn last
line (a crash while appending) is ignored. The journal holds UIDs, kinds, times and the
archive's answers: never the patient's identity (that is inside the objects only).

``max_bytes`` bounds the queue's files: :meth:`put` refuses beyond it, or when the disk is
full, with :class:`QueueFull` (nothing half written stays).
"""

from __future__ import annotations

import errno
import json
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydicom.dataset import Dataset
from pydicom.filebase import DicomBytesIO

from humantele.archive.files import atomic_write


class QueueFull(OSError):
    """The queue cannot take an object: its budget or the disk is full (the message says)."""


@dataclass
class Item:
    """One object in the queue (``n`` orders them)."""

    n: int
    sop: str
    study: str
    series: str
    kind: str  # 'image', 'clip', 'scan', 'sr', 'pr'
    size: int
    state: str = "waiting"  # waiting, sending, uncertain, archived, refused
    attempts: int = 0
    reason: str = ""
    not_before: float = 0.0  # (the queue's clock) a refused object waits until then
    queued_unix: float = 0.0
    archived_unix: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def done(self) -> bool:
        return self.state == "archived"


def to_bytes(ds: Dataset) -> bytes:
    """A dataset as a DICOM Part 10 file."""
    with DicomBytesIO() as buf:
        ds.save_as(buf, enforce_file_format=True)
        return buf.getvalue()


class DiskQueue:
    """The queue in ``directory`` (made if needed); ``clock`` for the back-off times."""

    def __init__(self, directory: Path, max_bytes: float = 2e9, clock=time.monotonic) -> None:
        self.dir = Path(directory).expanduser()
        self.objects = self.dir / "objects"
        self.objects.mkdir(parents=True, exist_ok=True)
        os.chmod(self.dir, 0o700)
        self.max_bytes = max_bytes
        self.clock = clock
        self.journal_path = self.dir / "journal.jsonl"
        self._lock = threading.RLock()
        self.items: dict[int, Item] = {}
        self.torn_lines = 0
        self.missing = 0  # objects the journal has as waiting whose file is gone (counted)
        self._replay()
        self._journal = open(self.journal_path, "a", encoding="utf-8")  # noqa: SIM115

    # --- the journal -----------------------------------------------------------------------

    def _replay(self) -> None:
        if not self.journal_path.exists():
            return
        for line in self.journal_path.read_text(encoding="utf-8").splitlines():
            try:
                ev = json.loads(line)
                n, what = int(ev["n"]), ev["ev"]
            except (ValueError, KeyError, TypeError):
                self.torn_lines += 1
                continue
            if what == "queued":
                self.items[n] = Item(n, ev["sop"], ev["study"], ev["series"], ev["kind"],
                                     int(ev.get("size", 0)), queued_unix=ev.get("t", 0.0),
                                     extra=ev.get("extra", {}))  # fmt: skip
                continue
            item = self.items.get(n)
            if item is None:
                self.torn_lines += 1
                continue
            item.state = what
            if what == "sending":
                item.attempts += 1
            elif what == "refused":
                item.reason = ev.get("reason", "")
            elif what == "archived":
                item.archived_unix = ev.get("t")
                item.reason = ev.get("reason", "")
        for item in self.items.values():
            if item.state == "sending":  # a crash mid-send: maybe received
                item.state = "uncertain"
            if not item.done and not self.path(item).exists():
                self.missing += 1
                item.state = "archived"  # nothing left to send (counted in ``missing``)
                item.reason = "file missing from the queue"
            if item.done:  # a crash between the line and the unlink
                self._unlink(item)

    def _log(self, n: int, what: str, **fields: Any) -> None:
        line = json.dumps({"n": n, "ev": what, "t": round(time.time(), 3), **fields})
        self._journal.write(line + "\n")
        self._journal.flush()
        os.fsync(self._journal.fileno())

    def close(self) -> None:
        with self._lock:
            self._journal.close()

    # --- objects in --------------------------------------------------------------------------

    def path(self, item: Item) -> Path:
        return self.objects / f"{item.n:08d}.dcm"

    def bytes_queued(self) -> int:
        return sum(i.size for i in self.items.values() if not i.done)

    def put(self, ds: Dataset, kind: str, extra: dict[str, Any] | None = None) -> Item:
        """Write ``ds`` into the queue (then it is sent in its turn). QueueFull when the
        budget or the disk cannot take it: nothing of it stays."""
        data = to_bytes(ds)
        with self._lock:
            if self.bytes_queued() + len(data) > self.max_bytes:
                raise QueueFull(
                    errno.ENOSPC,
                    f"the archive queue holds {self.bytes_queued() / 1e6:.0f} MB of its "
                    f"{self.max_bytes / 1e6:g} MB budget (queue_max_mb): the archive has not "
                    "taken them yet",
                )
            n = max(self.items, default=0) + 1
            item = Item(n, str(ds.SOPInstanceUID), str(ds.StudyInstanceUID),
                        str(ds.SeriesInstanceUID), kind, len(data), queued_unix=time.time(),
                        extra=dict(extra or {}))  # fmt: skip
            try:
                atomic_write(self.path(item), data)
                self._log(n, "queued", sop=item.sop, study=item.study, series=item.series,
                          kind=kind, size=len(data), extra=item.extra)  # fmt: skip
            except OSError as exc:
                self._unlink(item)
                if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                    raise QueueFull(exc.errno, f"the archive queue's disk is full: {exc}") from exc
                raise
            self.items[n] = item
            return item

    # --- the sender's side -------------------------------------------------------------------

    def pending(self) -> list[Item]:
        """The objects not yet archived, oldest first."""
        with self._lock:
            return [self.items[n] for n in sorted(self.items) if not self.items[n].done]

    def sending(self, item: Item) -> None:
        with self._lock:
            self._log(item.n, "sending")
            item.state = "sending"
            item.attempts += 1

    def archived(self, item: Item, reason: str = "") -> None:
        with self._lock:
            self._log(item.n, "archived", reason=reason)
            item.state, item.reason, item.archived_unix = "archived", reason, time.time()
            self._unlink(item)

    def refused(self, item: Item, reason: str, retry_s: float) -> None:
        with self._lock:
            self._log(item.n, "refused", reason=reason)
            item.state, item.reason = "refused", reason
            item.not_before = self.clock() + retry_s

    def interrupted(self, item: Item) -> None:
        """A send cut short (the association lost): maybe received, asked before resending."""
        with self._lock:
            item.state = "uncertain"

    def _unlink(self, item: Item) -> None:
        try:
            self.path(item).unlink()
        except FileNotFoundError:
            pass

    def counts(self) -> dict[str, int]:
        with self._lock:
            out = {"total": len(self.items), "archived": 0, "waiting": 0, "refused": 0}
            for i in self.items.values():
                key = "archived" if i.done else "refused" if i.state == "refused" else "waiting"
                out[key] += 1
            return out

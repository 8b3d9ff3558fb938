"""The exam's archive in the expert: captures and marks in, DICOM objects queued and sent.

:class:`ExamArchive` is what the console calls (from a thread: it encodes and writes):
:meth:`begin` the exam of a patient, :meth:`capture` a still (and its clip), :meth:`scan` a
whole scan's frames, :meth:`mark` a caliper or note on a frame. Every object goes into the
queue on disk first, then the :class:`~humantele.archive.forwarder.Forwarder` sends it.
Capture times are on the expert's clock (s); ``unix_offset_s`` moves them to Unix time (as
the recording's ``clock_unix_offset_s``).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydicom.dataset import Dataset

from humantele.archive import objects as obj
from humantele.archive.config import ArchiveConfig
from humantele.archive.exam import ExamStore, Patient
from humantele.archive.forwarder import Forwarder
from humantele.archive.queue import DiskQueue, Item, QueueFull
from humantele.archive.send import Sender, make_sender

IMAGES_KEPT = 500  # captured images whose marks may still come (their headers only)


@dataclass
class _Captured:
    header: Dataset  # the image without its pixels (what an SR / PR references)
    calipers: list[obj.Caliper] = field(default_factory=list)
    notes: list[obj.Note] = field(default_factory=list)


class NoExam(LookupError):
    """A capture before the patient is entered."""


class ExamArchive:
    """The archive side of a session (``cfg``: ``[expert.archive]``)."""

    def __init__(
        self, cfg: ArchiveConfig, unix_offset_s: float | None = None,
        sender: Sender | None = None, clock=time.monotonic,
    ) -> None:  # fmt: skip
        self.cfg = cfg
        self.unix_offset_s = time.time() - time.monotonic() if unix_offset_s is None else (
            unix_offset_s)  # fmt: skip
        directory = Path(cfg.queue_dir).expanduser()
        self.queue = DiskQueue(directory, cfg.queue_max_mb * 1e6, clock=clock)
        self.exams = ExamStore(directory)
        self.forwarder = Forwarder(
            self.queue, sender or make_sender(cfg), cfg.retry_min_s, cfg.retry_max_s, clock
        )
        self.equipment = obj.Equipment(
            station_name=cfg.station_name, institution=cfg.remote_site or cfg.institution,
            operator=cfg.operator, performing_physician=cfg.performing_physician,
        )  # fmt: skip
        self._captured: OrderedDict[int, _Captured] = OrderedDict()  # seq -> image
        self._marks: OrderedDict[int, _Captured] = OrderedDict()  # marks before a capture
        self._lock = threading.Lock()
        self._task: asyncio.Task | None = None
        self.made: dict[str, int] = {"image": 0, "clip": 0, "scan": 0, "sr": 0, "pr": 0}
        self.queued_at: dict[int, float] = {}  # item -> when queued (expert clock), figures

    # --- the exam ------------------------------------------------------------------------

    @property
    def patient(self) -> Patient | None:
        return None if self.exams.exam is None else self.exams.exam.patient

    def begin(self, patient: Patient) -> None:
        with self._lock:
            self.exams.begin(patient, time.time())
            self._captured.clear()
            self._marks.clear()

    def end(self) -> None:
        with self._lock:
            self.exams.end()
            self._captured.clear()
            self._marks.clear()

    def _place(self, scan: str, description: str = "") -> obj.Placement:
        if self.exams.exam is None:
            raise NoExam("no patient: enter the patient (or pick from the worklist) first")
        try:
            uid, number = self.exams.series_for(scan)
            instance = self.exams.next_instance()
        except OSError as exc:  # the exam's file beside the queue: the same disk
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise QueueFull(exc.errno, f"the archive queue's disk is full: {exc}") from exc
            raise
        return obj.Placement(self.exams.exam, uid, number, instance, description)

    def unix(self, t: float) -> float:
        return t + self.unix_offset_s

    # --- objects in -----------------------------------------------------------------------

    def capture(
        self, seq: int, jpeg: bytes, t_capture: float, scale: obj.Scale, scan: str,
        clip: list[tuple[float, bytes]] | None = None,
    ) -> list[Item]:  # fmt: skip
        """A captured still (and its clip: (t, jpeg) oldest first) as objects in the queue,
        with the marks already made on its frame. NoExam without a patient; QueueFull when
        the queue cannot take them; ValueError for a frame that is not a JPEG."""
        with self._lock:
            where = self._place(scan, _series_text(scan))
            image = obj.us_image(jpeg, self.unix(t_capture), scale, where, self.equipment)
            items = [self._put(image, "image", seq)]
            self.forwarder.kick()  # the still goes while its clip is encoded
            if clip and len(clip) >= 2:
                cw = self._place(scan, _series_text(scan))
                frames = obj.us_multiframe(
                    [j for _, j in clip], [self.unix(t) for t, _ in clip], scale, cw,
                    self.equipment,
                )  # fmt: skip
                items.append(self._put(frames, "clip", seq))
            header = _header(image)
            cap = self._marks.pop(seq, None) or _Captured(header)
            cap.header = header
            self._captured[seq] = cap
            while len(self._captured) > IMAGES_KEPT:
                self._captured.popitem(last=False)
            if cap.calipers or cap.notes:
                items += self._reports(cap, scan)
        self.forwarder.kick()
        return items

    def scan(self, scan: str, frames: list[tuple[float, bytes]], scale: obj.Scale) -> Item:
        """A whole scan (``frames``: (t, jpeg) oldest first, on the expert's clock) as an
        Ultrasound Multi-frame Image in the scan's series, into the queue. NoExam without a
        patient; QueueFull when the queue cannot take it; ValueError for frames that make
        no multi-frame (fewer than 2, not JPEGs, of different sizes, times not increasing)."""
        with self._lock:
            where = self._place(scan, _series_text(scan))
        # (built outside the lock: a long scan's encapsulation takes a moment; captures go on)
        ds = obj.us_multiframe([j for _, j in frames], [self.unix(t) for t, _ in frames], scale,
                               where, self.equipment)  # fmt: skip
        with self._lock:
            item = self._put(ds, "scan", None)
        self.forwarder.kick()
        return item

    def mark(self, seq: int, caliper: obj.Caliper | None = None, note: obj.Note | None = None,
             scan: str = "captures") -> list[Item]:  # fmt: skip
        """A caliper or note on frame ``seq``: an SR and a presentation state now if the frame
        was captured in this exam, else kept for its capture."""
        with self._lock:
            cap = self._captured.get(seq)
            pending = cap is None
            if pending:
                cap = self._marks.setdefault(seq, _Captured(Dataset()))
                while len(self._marks) > IMAGES_KEPT:
                    self._marks.popitem(last=False)
            if caliper is not None:
                cap.calipers.append(caliper)
            if note is not None:
                cap.notes.append(note)
            if pending or self.exams.exam is None:
                return []
            items = self._reports(cap, scan, new_caliper=caliper is not None)
        self.forwarder.kick()
        return items

    def _reports(self, cap: _Captured, scan: str, new_caliper: bool = True) -> list[Item]:
        out = []
        if cap.calipers and new_caliper:
            where = self._place("reports", "measurements")
            sr = obj.measurement_report(
                [cap.header], [(0, c) for c in cap.calipers], where, self.equipment
            )
            out.append(self._put(sr, "sr", None))
        where = self._place("reports", "measurements")
        pr = obj.presentation_state(cap.header, cap.calipers, cap.notes, where, self.equipment)
        out.append(self._put(pr, "pr", None))
        return out

    def _put(self, ds: Dataset, kind: str, seq: int | None) -> Item:
        item = self.queue.put(ds, kind, extra={} if seq is None else {"seq": seq})
        self.made[kind] += 1
        self.queued_at[item.n] = self.forwarder.clock()
        return item

    # --- running ---------------------------------------------------------------------------

    async def start(self) -> None:
        if self._task is None:
            self._task = asyncio.ensure_future(self.forwarder.run())

    async def stop(self) -> None:
        """Stop sending: a send in progress is let finish (its answer journaled, up to the
        association's timeout), then the journal is closed."""
        if self._task is not None:
            self._task.cancel()
            self.forwarder.kick()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task
            self._task = None
        busy = self.forwarder._busy
        if await asyncio.to_thread(busy.acquire, True, self.cfg.timeout_s + 5.0):
            busy.release()
        self.queue.close()

    def status(self) -> dict[str, Any]:
        """For the console and the stats: counts and the archive's state, no identity."""
        lat = self.latencies_s()
        p50, p95 = (None, None) if not lat else (float(np.percentile(lat, 50)),
                                                 float(np.percentile(lat, 95)))  # fmt: skip
        return {**self.forwarder.status(), "exam": self.exams.exam is not None,
                "made": dict(self.made), "queued_to_archived_p50_s": p50,
                "queued_to_archived_p95_s": p95}  # fmt: skip

    def latencies_s(self) -> list[float]:
        """Queued to archived (s) of each object archived this run."""
        done = self.forwarder.archived_at
        return [done[n] - t for n, t in self.queued_at.items() if n in done]


def _series_text(scan: str) -> str:
    return "captures" if scan == "captures" else f"tele-ultrasound {scan}"


def _header(image: Dataset) -> Dataset:
    """The image without its pixel data (kept to reference it from SR and PR)."""
    h = Dataset()
    for elem in image:
        if elem.tag != 0x7FE00010:
            h.add(elem)
    h.file_meta = image.file_meta
    return h

"""The queue's sender: in order, with back-off, until the archive has each object.

:meth:`Forwarder.step` is one pass (blocking; the expert runs it in a thread): if the archive
is due, open one connection and send every due object in order. The archive's per-instance
answer decides: stored -> ``archived`` (file removed); refused -> kept, tried again after its
own back-off while the others go on (the page shows the reason); the connection lost or
refused -> the whole queue waits ``retry_min_s``, doubling to ``retry_max_s``. An object
whose answer never came (a crash, an abort) is first asked for (``has``), sent only if the
archive does not hold it. :meth:`status` is what the console shows.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from typing import Any

from pydicom.errors import InvalidDicomError

from humantele.archive.queue import DiskQueue
from humantele.archive.send import Answer, Sender, Unreachable

log = logging.getLogger(__name__)


class Forwarder:
    """Sends ``queue``'s objects through ``sender``; times on ``clock`` (s)."""

    def __init__(
        self, queue: DiskQueue, sender: Sender, retry_min_s: float = 2.0,
        retry_max_s: float = 60.0, clock=time.monotonic,
    ) -> None:  # fmt: skip
        self.queue = queue
        self.sender = sender
        self.retry_min_s = retry_min_s
        self.retry_max_s = retry_max_s
        self.clock = clock
        self.failures = 0  # connection failures in a row
        self.retry_at = 0.0  # the archive is not tried before (clock)
        self.unreachable = ""  # why the last connection failed ('' when it worked)
        self.sent = 0  # stores answered 'stored'
        self.found = 0  # uncertain objects the archive already had (not sent again)
        self.refusals = 0
        self.archived_at: dict[int, float] = {}  # item -> when archived (clock), for figures
        self.wake = threading.Event()
        self._busy = threading.Lock()

    def backoff(self, k: int) -> float:
        return min(self.retry_max_s, self.retry_min_s * 2.0 ** max(0, k - 1))

    def due(self, now: float) -> list:
        if now < self.retry_at:
            return []
        return [i for i in self.queue.pending() if i.state != "refused" or i.not_before <= now]

    def step(self) -> float | None:
        """One pass; the seconds until something is due again (None: nothing waits)."""
        with self._busy:
            now = self.clock()
            items = self.due(now)
            if items:
                self._send(items)
            return self.next_due()

    def next_due(self) -> float | None:
        pending = self.queue.pending()
        if not pending:
            return None
        now = self.clock()
        if now < self.retry_at:
            return self.retry_at - now
        ready = [0.0 if i.state != "refused" else max(0.0, i.not_before - now) for i in pending]
        return min(ready)

    def _send(self, items: list) -> None:
        try:
            conn = self.sender.connect()
        except Unreachable as exc:
            self._failed(str(exc))
            return
        item = None
        try:
            for item in items:
                if item.state == "uncertain":
                    held = conn.has(item)
                    if held:
                        self.queue.archived(item, "found in the archive after an interruption")
                        self.found += 1
                        self.archived_at[item.n] = self.clock()
                        continue
                self.queue.sending(item)
                try:
                    answer = conn.store(self.queue.path(item))
                except (OSError, ValueError, InvalidDicomError) as exc:  # its file, not the link
                    answer = Answer(False, f"cannot be read from the queue: {exc}"[:200])
                if answer.stored:
                    self.queue.archived(item, answer.reason)
                    self.sent += 1
                    self.archived_at[item.n] = self.clock()
                else:
                    self.refusals += 1
                    retry = self.backoff(item.attempts)
                    self.queue.refused(item, answer.reason, retry)
                    log.warning("archive: object %d (%s) refused: %s", item.n, item.kind,
                                answer.reason)  # fmt: skip
            self.failures, self.unreachable, self.retry_at = 0, "", 0.0
        except Unreachable as exc:
            if item is not None and item.state == "sending":
                self.queue.interrupted(item)
            self._failed(str(exc))
        finally:
            conn.close()

    def _failed(self, why: str) -> None:
        self.failures += 1
        delay = self.backoff(self.failures)
        self.retry_at = self.clock() + delay
        if why != self.unreachable:
            log.warning("archive unreachable (%s): retrying in %.0f s", why, delay)
        self.unreachable = why

    async def run(self) -> None:
        """Send until cancelled: a pass when something is due or :meth:`kick` is called (a
        pass that fails unexpectedly is logged and tried again later, never ends sending)."""
        while True:
            try:
                delay = await asyncio.to_thread(self.step)
            except Exception:  # noqa: BLE001 - e.g. the journal's disk: said, tried again
                log.exception("archive: sending failed; trying again in %.0f s", self.retry_max_s)
                delay = self.retry_max_s
            self.wake.clear()
            wait = 3600.0 if delay is None else max(0.05, delay)
            await asyncio.to_thread(self.wake.wait, wait)

    def kick(self) -> None:
        """Something new is queued: send now (unless the archive is in its back-off)."""
        self.wake.set()

    def status(self) -> dict[str, Any]:
        """What the console shows: counts, whether the archive is reachable, refusals."""
        c = self.queue.counts()
        now = self.clock()
        waiting = c["total"] - c["archived"]
        refused = [
            {"n": i.n, "kind": i.kind, "reason": i.reason}
            for i in self.queue.pending() if i.state == "refused"
        ]  # fmt: skip
        retry = round(max(0.0, self.retry_at - now), 1) if waiting else None
        out = {**c, "sent": self.sent, "found": self.found, "refusals": self.refusals,
               "unreachable": bool(self.unreachable), "refused_items": refused[:20],
               "retry_in_s": retry}  # fmt: skip
        if self.unreachable and waiting:
            out["text"] = (f"archive unreachable: {waiting} waiting "
                           f"(retrying in {max(0.0, self.retry_at - now):.0f} s)")  # fmt: skip
        else:
            out["text"] = f"archived {c['archived']} of {c['total']}"
        out["error"] = self.unreachable[:200] if self.unreachable else ""
        return out

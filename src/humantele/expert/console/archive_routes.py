"""The console's side of the hospital's archive (``[expert.archive]``): the patient and the
exam entered on the page (or picked from the Modality Worklist), the captures and marks
turned into DICOM objects, what has reached the archive.

Routes (each needs the console's key in the ``X-Console-Key`` header; identity travels in
request and response bodies only, never in a URL):

- ``GET /archive/status``: "archived 4 of 4", "archive unreachable: 3 waiting (retrying in
  30 s)", refused objects with the archive's reason, whether a patient is entered, the last
  capture's outcome;
- ``GET /archive/exam``, ``POST /archive/exam`` (JSON: patient_id, family_name,
  given_name, birth_date, sex, accession_number), ``DELETE /archive/exam`` (the exam ends);
- ``GET /archive/worklist``: today's scheduled US exams (C-FIND);
- ``POST /archive/scan``: archive the whole scan, the one in progress (at its end) or the
  last one ended (now), as an Ultrasound Multi-frame Image (:mod:`.scan_frames`); with
  ``send_scans`` every scan is, at its end.

The server calls :meth:`ConsoleArchive.capture` and :meth:`ConsoleArchive.mark`, and hands
each ultrasound frame to :attr:`ConsoleArchive.scans`; the work (JPEG of clip and scan frames,
DICOM encoding, the queue's writes) runs in a thread.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from aiohttp import web
from pydantic import ValidationError

from humantele.expert.console.scan_frames import KeptScan, ScanFrames
from humantele.web.credential import Credential, Verdict

# (humantele.archive, pydicom and highdicom are imported only when the archive is on)

log = logging.getLogger(__name__)
MAX_BODY = 4096


def add_routes(app: web.Application, archive: ConsoleArchive | None) -> None:
    """The archive's routes; with the archive off, only its status saying so (the page's
    panel then stays hidden, and asks nothing more)."""
    if archive is not None:
        archive.add_routes(app)
    else:
        app.router.add_get("/archive/status", _off)


async def _off(request: web.Request) -> web.Response:
    return web.json_response({"enabled": False}, headers={"Cache-Control": "no-store"})


class ConsoleArchive:
    """The archive behind the console (``cfg``: ``[expert.archive]``; ``key``: the console's;
    ``scan()``: the scan in progress, None when none)."""

    def __init__(self, cfg: Any, key: str, scan: Any = None, archive: Any = None) -> None:
        from humantele.archive.service import ExamArchive

        self.cfg = cfg
        self.archive = archive or ExamArchive(cfg)
        self._key = Credential(key, throttle=False)
        self.scan = scan or (lambda: None)
        self.last = ""  # the last capture's outcome, for the page
        self.refused: dict[str, int] = {}
        self._tasks: set[asyncio.Task] = set()
        self._watch: asyncio.Task | None = None
        self.scans = ScanFrames(  # the whole scans (PageVideo offers it the US frames)
            self.scan, self._send_scan, cfg.scan_fps, cfg.scan_max_frames, cfg.scan_max_mb,
            cfg.clip_quality, auto=cfg.send_scans,
        )  # fmt: skip

    # --- the server's hooks ------------------------------------------------------------------

    def add_routes(self, app: web.Application) -> None:
        app.router.add_get("/archive/status", self._status)
        app.router.add_get("/archive/exam", self._get_exam)
        app.router.add_post("/archive/exam", self._post_exam)
        app.router.add_delete("/archive/exam", self._end_exam)
        app.router.add_get("/archive/worklist", self._worklist)
        app.router.add_post("/archive/scan", self._post_scan)

    async def start(self) -> None:
        await self.archive.start()
        self._watch = asyncio.ensure_future(self._watch_scans())

    async def stop(self) -> None:
        if self._watch is not None:
            self._watch.cancel()
        await self.scans.idle()
        self.scans.poll()
        self.scans.end()  # a scan still on: archived as far as it went, if it was asked for
        if self._tasks:
            await asyncio.wait(list(self._tasks), timeout=20.0)
        await self.archive.stop()

    async def _watch_scans(self, period_s: float = 0.5) -> None:
        """A scan's end is noticed with no frame coming (a scripted scan, a closed page)."""
        while True:
            await asyncio.sleep(period_s)
            self.scans.poll()

    def capture(self, f: Any, clip: list[Any]) -> None:
        """A still the console saved (and its clip's cine frames) into the archive's queue."""
        from humantele.archive import objects as obj

        scan = self.scan()
        scale = obj.Scale(f.pixel_spacing_mm, f.depth_origin_row)

        def work() -> str:
            frames = [(g.t_capture, g.image_jpeg()) for g in clip] if len(clip) >= 2 else None
            items = self.archive.capture(f.seq, f.jpeg, f.t_capture, scale,
                                         "captures" if scan is None else f"scan {scan}",
                                         clip=frames)  # fmt: skip
            return f"frame {f.seq}: {len(items)} DICOM object(s) queued for the archive"

        self._spawn(work, f"frame {f.seq}")

    def request_scan(self) -> tuple[bool, str]:
        """The sonographer's "Archive scan": the scan in progress (at its end) or the last
        one ended (now); (done, what to say)."""
        if self.archive.patient is None:
            return False, "enter the patient first: the archive files the scan under them"
        ok, text = self.scans.request()
        self.last = text
        return ok, text

    def _send_scan(self, k: KeptScan) -> None:
        """Build scan ``k``'s Ultrasound Multi-frame Image and queue it (in a thread)."""
        from humantele.archive import objects as obj

        if len(k.frames) < 2:
            self._refuse("no_frames", f"scan {k.scan} not archived: {len(k.frames)} frame(s) "
                         "kept of it (they are kept while the console is open)")  # fmt: skip
            return
        k.outcome = "building"
        frames = list(k.frames)
        _, _, px_spacing, depth0_px = k.geometry  # (set with its first frame)
        scale = obj.Scale(px_spacing, depth0_px)
        span = frames[-1][0] - frames[0][0]
        left_out = f"; {k.other_geometry} of another size or scale left out" if (
            k.other_geometry) else ""  # fmt: skip

        def work() -> str:
            self.archive.scan(f"scan {k.scan}", frames, scale)
            return (f"scan {k.scan}: the whole scan ({len(frames)} frames over {span:.0f} s"
                    f"{left_out}) queued for the archive")  # fmt: skip

        def queued() -> None:  # (on the loop) its frames are in the queue's file: let go
            k.sent_frames, k.frames, k.nbytes = len(frames), [], 0
            k.outcome = "queued"

        def failed() -> None:
            k.outcome = ""  # (it may be asked for again: the patient entered, room made)

        self._spawn(work, f"scan {k.scan}", failed, queued)

    def mark(self, f: Any, caliper: tuple | None = None, note: tuple | None = None) -> None:
        """A caliper ((a, b) px, mm) or note ((x, y) px, text) on a frame: with its capture,
        an SR and a presentation state."""
        from humantele.archive import objects as obj

        scan = self.scan()
        name = "captures" if scan is None else f"scan {scan}"
        c = None if caliper is None else obj.Caliper(tuple(caliper[0]), tuple(caliper[1]),
                                                     float(caliper[2]))  # fmt: skip
        n = None if note is None else obj.Note(tuple(note[0]), str(note[1]))

        def work() -> str:
            items = self.archive.mark(f.seq, caliper=c, note=n, scan=name)
            return f"frame {f.seq}: {len(items)} report object(s) queued" if items else ""

        self._spawn(work, f"frame {f.seq}")

    def _spawn(self, work: Any, what: str, failed: Any = None, done: Any = None) -> None:
        from humantele.archive.queue import QueueFull
        from humantele.archive.service import NoExam

        async def run() -> None:
            try:
                text = await asyncio.to_thread(work)
            except NoExam as exc:
                self._refuse("no_exam", f"{what} not archived: {exc}")
            except QueueFull as exc:
                self._refuse("queue_full", f"{what} not archived: {exc.strerror}")
            except (OSError, ValueError) as exc:
                self._refuse("failed", f"{what} not archived: {exc}")
            else:
                if done is not None:
                    done()
                if text:
                    self.last = text
                return
            if failed is not None:
                failed()

        task = asyncio.ensure_future(run())
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _refuse(self, why: str, text: str) -> None:
        self.refused[why] = self.refused.get(why, 0) + 1
        self.last = text
        log.warning("console: %s", text)  # (no identity in it: frame numbers and reasons)

    def status(self) -> dict[str, Any]:
        return {**self.archive.status(), "enabled": True, "last": self.last,
                "not_archived": dict(self.refused), "identity": self.cfg.identity,
                "scan_archive": self.scans.status()}  # fmt: skip

    # --- routes ------------------------------------------------------------------------------

    def _check(self, request: web.Request) -> None:
        verdict = self._key.check(request.headers.get("X-Console-Key"), request.remote or "?")
        if verdict is not Verdict.OK:
            raise web.HTTPUnauthorized(text="this console's key is missing or wrong\n")

    async def _status(self, request: web.Request) -> web.Response:
        self._check(request)
        return web.json_response(self.status(), headers={"Cache-Control": "no-store"})

    async def _get_exam(self, request: web.Request) -> web.Response:
        self._check(request)
        p = self.archive.patient
        body = None if p is None else p.model_dump(mode="json")
        return web.json_response({"patient": body}, headers={"Cache-Control": "no-store"})

    async def _post_exam(self, request: web.Request) -> web.Response:
        from humantele.archive.exam import Patient

        self._check(request)
        if (request.content_length or 0) > MAX_BODY:
            raise web.HTTPRequestEntityTooLarge(MAX_BODY, request.content_length or 0)
        try:
            data = await request.json()
            patient = Patient.model_validate(data)
        except ValidationError as exc:
            errors = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}"
                               for e in exc.errors())  # fmt: skip
            return web.json_response({"ok": False, "error": errors}, status=400)
        except ValueError:
            return web.json_response({"ok": False, "error": "not JSON"}, status=400)
        await asyncio.to_thread(self.archive.begin, patient)
        self.last = "exam started"
        return web.json_response({"ok": True})

    async def _end_exam(self, request: web.Request) -> web.Response:
        self._check(request)
        await asyncio.to_thread(self.archive.end)
        self.last = "exam ended"
        return web.json_response({"ok": True})

    async def _post_scan(self, request: web.Request) -> web.Response:
        self._check(request)
        ok, text = self.request_scan()
        if not ok:
            return web.json_response({"ok": False, "error": text}, status=409)
        return web.json_response({"ok": True, "text": text})

    async def _worklist(self, request: web.Request) -> web.Response:
        from humantele.archive.send import Unreachable
        from humantele.archive.worklist import find

        self._check(request)
        try:
            items, bad = await asyncio.to_thread(find, self.cfg)
        except Unreachable as exc:
            return web.json_response({"ok": False, "error": str(exc)}, status=502)
        out = [{"patient": i.patient.model_dump(mode="json"), "scheduled": i.scheduled,
                "description": i.description} for i in items]  # fmt: skip
        return web.json_response({"ok": True, "items": out, "unusable": bad},
                                 headers={"Cache-Control": "no-store"})  # fmt: skip

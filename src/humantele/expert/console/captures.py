"""Captured frames on disk: the JPEG the sonographer saw and a JSON side file with its pose,
and, when asked, a clip of the cine's last seconds (``....mp4``, H.264) beside them.

:class:`Captures` is the console's Capture button: the rate cap and the disk budget, the
files, the clip written off the loop, the session's list (:class:`SessionItems`) and the
page's reads of the files (with the run's key).

Files are named by the capture's wall-clock time (UTC) and frame number, never by anything
about the patient: ``capture-20261123T101500Z-000123.jpg``, ``....json`` and ``....mp4``. A
file that exists is never overwritten (a numbered suffix is added). Each is written whole or
not at all (:mod:`humantele.runtime.files`): a capture is its JPEG and its JSON, or nothing;
the JSON names the clip only once the clip is there whole (:func:`name_clip`). On a full disk
a capture leaves no file, and :class:`FailureLog` says it once, not once a capture.

:class:`SessionItems` is the session's list of captures and measurements (calipers, notes)
that the console page shows, so the sonographer reviews them before the session ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

from aiohttp import web

from humantele.expert.console.cine import CineBuffer, CineFrame
from humantele.expert.console.config import ConsoleConfig
from humantele.expert.console.messages import Capture
from humantele.expert.console.protocol import clean, result
from humantele.expert.console.session import ConsoleSession
from humantele.runtime.files import replace_whole, write_new
from humantele.web.credential import Credential, Verdict
from humantele.web.guard import MessageBudget
from humantele.web.pagesocket import PageClient, PageSockets

log = logging.getLogger(__name__)
MAX_ITEMS = 500  # the list the page is sent keeps the newest
CAPTURE_BURST = 10  # captures at once before captures_per_minute applies
CLIP_FINISH_S = 20.0  # at stop, a clip being written gets this long to finish
POSE_FIELDS = ("position", "quaternion", "virtual_position", "virtual_quaternion")


def save_capture(directory: Path, seq: int, jpeg: bytes, info: dict[str, Any]) -> Path:
    """Write ``jpeg`` and ``info`` (its JSON side file) into ``directory`` (made if needed),
    both whole or neither; the JPEG's path. OSError when they cannot be written (nothing
    left)."""
    directory.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    base = f"capture-{stamp}-{seq:06d}"
    side = json.dumps(info, indent=1).encode()
    for n in range(1000):
        name = base if n == 0 else f"{base}-{n}"
        path = directory / f"{name}.jpg"
        if path.with_suffix(".json").exists():
            continue
        try:
            write_new(path, jpeg)
        except FileExistsError:
            continue
        try:
            write_new(path.with_suffix(".json"), side)
        except OSError:
            with contextlib.suppress(OSError):
                path.unlink()
            raise
        return path
    raise OSError(f"no free capture file name for {base} in {directory}")


def name_clip(still: Path, clip: Any) -> Any:
    """Name the clip written whole beside ``still`` in the still's JSON (``clip``: file,
    frames), replaced in one step; ``clip`` (an export.clip.ClipInfo) returned. OSError when
    it cannot be (the clip removed: a capture's files are whole and named, or not there)."""
    side = still.with_suffix(".json")
    try:
        info = json.loads(side.read_text(encoding="utf-8"))
        info["clip"] = {"file": clip.path.name, "frames": clip.frames}
        replace_whole(side, json.dumps(info, indent=1).encode())
    except (OSError, ValueError) as exc:
        with contextlib.suppress(OSError):
            clip.path.unlink()
        raise OSError(f"clip not named in {side.name}: {exc}") from exc
    return clip


def clip_path(still: Path) -> Path:
    """Where the clip of a capture goes: beside its JPEG, ``.mp4``."""
    return still.with_suffix(".mp4")


class FailureLog:
    """Says a run of failures (captures or clips not saved: a full disk) once: the first at
    ERROR, the ones after it at DEBUG, and at INFO when one succeeds again, with the count.
    ``failed`` counts them all (the stats have them)."""

    def __init__(self, logger: logging.Logger, what: str) -> None:
        self.log = logger
        self.what = what
        self.failed = 0
        self._in_a_row = 0

    def failure(self, detail: object) -> None:
        self.failed += 1
        self._in_a_row += 1
        if self._in_a_row == 1:
            self.log.error("console: %s not saved: %s (said once until one is saved again)",
                           self.what, detail)  # fmt: skip
        else:
            self.log.debug("console: %s not saved: %s", self.what, detail)

    def success(self) -> None:
        if self._in_a_row > 1:
            self.log.info("console: %s saved again after %d not saved", self.what,
                          self._in_a_row)  # fmt: skip
        self._in_a_row = 0


class SessionItems:
    """The session's captures and measurements, newest last: dicts with ``n`` (1, 2, ...),
    ``kind`` (``capture``, ``caliper``, ``note``), ``seq`` and ``t_capture`` (s, the expert's
    clock) of the frame, and the kind's fields (``file``, ``clip``; ``mm``; ``text``)."""

    def __init__(self, max_items: int = MAX_ITEMS) -> None:
        self.max_items = max_items
        self._items: list[dict[str, Any]] = []
        self._n = 0

    def add(self, kind: str, seq: int, t_capture: float, **fields: Any) -> dict[str, Any]:
        """A new item (returned: a clip written later is added to it in place)."""
        self._n += 1
        item = {"n": self._n, "kind": kind, "seq": seq, "t_capture": t_capture, **fields}
        self._items.append(item)
        del self._items[: -self.max_items]
        return item

    def list(self) -> list[dict[str, Any]]:
        return [dict(i) for i in self._items]

    def clip_names(self) -> set[str]:
        return {i["clip"] for i in self._items if i.get("clip")}


class Captures:
    """The console's captures and the session's list. ``record(event, payload)``: onto
    ``/expert/console`` when the session records; ``key``: the run's key (the files' reads)."""

    def __init__(
        self,
        config: ConsoleConfig,
        cine: CineBuffer,
        session: ConsoleSession,
        pages: PageSockets,
        refused: Counter[str],
        events: Counter[str],
        record: Callable[[str, dict[str, Any]], None],
        key: str,
    ) -> None:
        self.config = config
        self.cine = cine
        self.session = session
        self.pages = pages
        self.refused = refused
        self.events = events
        self.record = record
        self.budget = MessageBudget(config.captures_per_minute / 60.0, CAPTURE_BURST)
        self.bytes: int | None = None  # in captures_dir, counted at the first capture
        self.saved: list[str] = []
        self.items = SessionItems()  # captures and measurements, listed on the page
        self.clips_writing = 0
        self._clips: set[asyncio.Task] = set()  # clips being written
        self._file_key = Credential(key, throttle=False)  # the captured files' reads
        self.archive: Any = None  # the exam's archive (archive_routes.ConsoleArchive), if on
        self.capture_log = FailureLog(log, "capture")  # a full disk said once, not per capture
        self.clip_log = FailureLog(log, "clip")

    @property
    def refused_count(self) -> int:
        return self.refused["capture_rate"] + self.refused["capture_disk"]

    async def finish(self) -> None:
        """At stop: a clip being written is finished (and recorded), not cut short."""
        if self._clips:
            await asyncio.wait(list(self._clips), timeout=CLIP_FINISH_S)

    async def capture(self, client: PageClient, f: CineFrame, base: dict, m: Capture) -> None:
        """Capture frame ``f``, once it is a JPEG (made in a thread, off the loop)."""
        if f.jpeg is None:
            try:
                await asyncio.to_thread(f.image_jpeg)
            except ValueError as exc:
                self.refused["capture_failed"] += 1
                result(client, "capture", False, f"not saved: {exc}", id=m.id)
                return
        self._capture(client, f, base, m)

    def _refusal(self, directory: Path, size: int) -> str | None:
        """Why a capture of ``size`` bytes is refused now (counted), or None."""
        if self.bytes is None:
            self.bytes = _dir_bytes(directory)
        budget = self.config.captures_max_mb * 1e6
        if self.bytes + size > budget:
            self.refused["capture_disk"] += 1
            return (
                f"not saved: the captures folder holds {self.bytes / 1e6:.0f} MB of its "
                f"{self.config.captures_max_mb:g} MB budget (captures_max_mb); move some away"
            )
        if not self.budget.take():
            self.refused["capture_rate"] += 1
            return (
                f"not saved: more than {self.config.captures_per_minute:g} captures a minute "
                "(captures_per_minute); wait a moment"
            )
        return None

    def _clip_frames(self, f: CineFrame, seconds: float) -> list[CineFrame]:
        """The cine's frames of the ``seconds`` up to ``f`` (oldest first)."""
        out = []
        for seq, t in self.cine.index():
            if seq <= f.seq and f.t_capture - t <= seconds:
                g = self.cine.get(seq)
                if g is not None:
                    out.append(g)
        return out

    def _capture(self, client: PageClient, f: CineFrame, base: dict[str, Any], m: Capture) -> None:
        directory = Path(self.config.captures_dir).expanduser()
        assert f.jpeg is not None
        clip_s = min(m.clip_s, self.config.clip_seconds)
        clip = self._clip_frames(f, clip_s) if clip_s > 0 else []
        clip = clip if len(clip) >= 2 else []
        # The clip's size is bounded by its frames' JPEGs (its H.264 is smaller; a frame not
        # yet a JPEG counts as the still's size): the budget holds it.
        size = len(f.jpeg) + 1024 + sum(len(g.jpeg or f.jpeg) for g in clip)
        refusal = self._refusal(directory, size)
        if refusal is not None:
            n = self.refused_count
            result(client, "capture", False, f"{refusal} ({n} refused this run)", id=m.id)
            return
        pose = self.session.pose_at(f.t_capture)
        info: dict[str, Any] = {
            "seq": f.seq,
            "t_capture_s": f.t_capture,
            "pixel_spacing_mm": f.pixel_spacing_mm,
            "width": f.width,
            "height": f.height,
            "frame": "T_patient_probe: patient frame, m; quaternion (x, y, z, w)",
            "pose": pose,
        }
        rec = self.session.recorder
        if rec is not None:
            info["session_id"] = rec.metadata.get("session_id")
        try:
            path = save_capture(directory, f.seq, f.jpeg, clean(info))
        except OSError as exc:
            self.refused["capture_failed"] += 1
            self.capture_log.failure(exc)
            result(client, "capture", False, f"not saved: {exc.strerror or exc}", id=m.id)
            return
        self.capture_log.success()
        self.events["capture"] += 1
        self.saved.append(str(path))
        self.bytes = (self.bytes or 0) + _file_bytes(path)
        payload = {**base, "file": path.name}
        if pose is not None:
            payload.update({k: v for k, v in pose.items() if k in POSE_FIELDS})
        self.record("capture", payload)
        if rec is not None and hasattr(rec, "attach"):
            rec.attach(path.name, "image/jpeg", f.jpeg, f.t_capture)
        item = self.add_item("capture", f, file=path.name, clip=None, clip_pending=bool(clip))
        detail = path.name + (f" and a {clip_s:g} s clip (writing)" if clip else "")
        if self.archive is not None:  # the same still and clip, as DICOM, to the PACS
            self.archive.capture(f, clip)
        result(client, "capture", True, detail, seq=f.seq, file=str(path), id=m.id)
        if clip:
            task = asyncio.create_task(self._write_clip(client, path, clip, item, m.id))
            self._clips.add(task)
            task.add_done_callback(self._clips.discard)

    async def _write_clip(
        self, client: PageClient, still: Path, frames: list[CineFrame], item: dict,
        cmd_id: int | None,
    ) -> None:  # fmt: skip
        """The clip beside the still ``still`` (off the loop: ~6 ms a frame); the item and
        the page told when it is there, or why not."""
        from humantele.export.clip import write_clip

        path = clip_path(still)
        self.clips_writing += 1
        try:
            info = await asyncio.to_thread(  # (frames not yet JPEGs are made there too)
                lambda: name_clip(
                    still, write_clip([(g.t_capture, g.image_jpeg()) for g in frames], path)
                )
            )
        except (OSError, ValueError) as exc:
            self.refused["clip_failed"] += 1
            self.clip_log.failure(exc)
            item["clip_error"] = str(exc)[:200]
            result(client, "clip", False, f"clip not saved: {exc}", id=cmd_id)
        else:
            self.clip_log.success()
            self.events["clip"] += 1
            self.bytes = (self.bytes or 0) + _size(path)
            item.update(clip=path.name, clip_s=round(info.duration_s, 2), clip_frames=info.frames)
            self.record("clip", {"file": path.name, "still": still.name, "frames": info.frames,
                                 "duration_s": info.duration_s})  # fmt: skip
            result(client, "clip", True, f"{path.name} ({info.duration_s:.1f} s, "
                   f"{info.frames} frames)", file=str(path), id=cmd_id)  # fmt: skip
        finally:
            self.clips_writing -= 1
            item["clip_pending"] = False
        self.pages.post("items", self.items_message())

    def add_item(self, kind: str, f: CineFrame, **fields: Any) -> dict[str, Any]:
        """One more capture or measurement in the session's list (the page is sent it)."""
        item = self.items.add(kind, f.seq, f.t_capture, **fields)
        self.pages.post("items", self.items_message())
        return item

    def items_message(self) -> str:
        return json.dumps(clean({"type": "items", "items": self.items.list()}))

    async def serve_file(self, request: web.Request) -> web.StreamResponse:
        """A still or clip captured this run, for the page's list (with the run's key)."""
        verdict = self._file_key.check(request.query.get("key"), request.remote or "?")
        name = request.match_info["name"]
        known = {Path(c).name for c in self.saved} | self.items.clip_names()
        if verdict is not Verdict.OK:
            self.refused["unauthorized"] += 1
            raise web.HTTPUnauthorized(text="this console's key is missing or wrong\n")
        if name not in known:
            raise web.HTTPNotFound()
        path = Path(self.config.captures_dir).expanduser() / name
        if not path.is_file():
            raise web.HTTPNotFound()
        return web.FileResponse(path, headers={"Cache-Control": "no-store"})


def _file_bytes(jpeg: Path) -> int:
    """Bytes of a capture on disk: its JPEG and its JSON side file."""
    total = 0
    for p in (jpeg, jpeg.with_suffix(".json")):
        try:
            total += p.stat().st_size
        except OSError:
            pass
    return total


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _dir_bytes(directory: Path) -> int:
    """Bytes of the capture files already in ``directory`` (0 if there is none)."""
    try:
        return sum(p.stat().st_size for p in directory.iterdir() if p.name.startswith("capture-"))
    except OSError:
        return 0

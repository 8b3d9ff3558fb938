"""The console's ultrasound tools, on the frames of the cine buffer: freeze and the cine loop,
calipers (mm, from the frame's own pixel spacing) and annotations; Capture goes to
:class:`~humantele.expert.console.captures.Captures`. Each is recorded on
``/expert/console`` when the session records (docs/console.md, "Ultrasound tools")."""

from __future__ import annotations

import asyncio
import json
import math
from collections import Counter
from collections.abc import Callable
from typing import Any

from humantele.expert.console.captures import Captures
from humantele.expert.console.cine import CineBuffer, CineFrame
from humantele.expert.console.messages import (
    Annotation,
    Caliper,
    Capture,
    frame_header,
    outside_image,
)
from humantele.expert.console.protocol import result
from humantele.web.pagesocket import PageClient, PageSockets


class UltrasoundTools:
    """Freeze, cine, caliper, annotation and capture on ``cine``'s frames. ``spawn``: runs a
    coroutine as the server's task; ``record(event, payload)``: onto the recording."""

    def __init__(
        self,
        cine: CineBuffer,
        captures: Captures,
        pages: PageSockets,
        refused: Counter[str],
        events: Counter[str],
        record: Callable[[str, dict[str, Any]], None],
        spawn: Callable[[Any], None],
    ) -> None:
        self.cine = cine
        self.captures = captures
        self.pages = pages
        self.refused = refused
        self.events = events
        self.record = record
        self.spawn = spawn

    def freeze(self, on: bool) -> None:
        """Freeze (the cine loop kept as it is, sent to the pages) or back to live."""
        if on:
            self.cine.freeze()
        else:
            self.cine.resume()
        self.events["freeze" if on else "live"] += 1
        newest = self.cine.newest()
        self.record(
            "freeze" if on else "live",
            {} if newest is None else {"seq": newest.seq, "t_capture": newest.t_capture},
        )
        if on:
            self.pages.post("cine", self.cine_index())

    def cine_index(self) -> str:
        """The ``cine`` message: the loop's frame numbers and times (s, from the newest)."""
        t0 = self.cine.newest().t_capture if len(self.cine) else 0.0
        frames = [[seq, round(t - t0, 4)] for seq, t in self.cine.index()]
        return json.dumps({"type": "cine", "frozen": self.cine.frozen, "frames": frames})

    def send_cine(self, client: PageClient, seq: int) -> None:
        """Frame ``seq`` of the loop to the page (a JPEG made off the loop if need be)."""
        f = self.cine.get(seq)
        if f is None:
            self.refused["unknown_frame"] += 1
            result(client, "cine", False, f"frame {seq} is no longer in the cine buffer")
            return
        self.spawn(self._send_cine(client, f))

    async def _send_cine(self, client: PageClient, f: CineFrame) -> None:
        try:
            jpeg = f.jpeg if f.jpeg is not None else await asyncio.to_thread(f.image_jpeg)
        except ValueError as exc:
            self.refused["bad_frame"] += 1
            result(client, "cine", False, f"frame {f.seq}: {exc}")
            return
        header = frame_header(
            "us", f.seq, f.t_capture, f.pixel_spacing_mm, f.width, f.height, cine=True,
            depth0=f.depth_origin_row,
        )  # fmt: skip
        client.post("frame:cine", header + jpeg)

    def use(self, client: PageClient, m: Caliper | Annotation | Capture) -> None:
        """A caliper, an annotation or a capture on frame ``m.seq``."""
        f = self.cine.get(m.seq)
        if f is None:
            self.refused["unknown_frame"] += 1
            result(client, m.type, False, f"frame {m.seq} is no longer in the cine buffer",
                   id=m.id)  # fmt: skip
            return
        base = {"seq": f.seq, "t_capture": f.t_capture}
        at = [m.a, m.b] if isinstance(m, Caliper) else [m.at] if isinstance(m, Annotation) else []
        off = outside_image(at, f.width, f.height)
        if off is not None:
            self.refused["outside_image"] += 1
            result(client, m.type, False, off, id=m.id)
            return
        if isinstance(m, Caliper):
            if f.pixel_spacing_mm is None:
                result(
                    client, "caliper", False,
                    "no pixel spacing for this image: set [expert.console] us_pixel_spacing_mm",
                    id=m.id,
                )  # fmt: skip
                return
            row, col = f.pixel_spacing_mm
            mm = math.hypot((m.b[0] - m.a[0]) * col, (m.b[1] - m.a[1]) * row)
            self.events["caliper"] += 1
            self.record("caliper", {**base, "mm": mm, "a_px": m.a, "b_px": m.b})
            result(client, "caliper", True, f"{mm:.1f} mm", mm=mm, seq=f.seq, id=m.id)
            self.captures.add_item("caliper", f, mm=round(mm, 2), text=f"{mm:.1f} mm")
            if self.captures.archive is not None:
                self.captures.archive.mark(f, caliper=(m.a, m.b, mm))
        elif isinstance(m, Annotation):
            text = " ".join(m.text.split())
            if not text:
                result(client, "annotation", False, "empty text", id=m.id)
                return
            self.events["annotation"] += 1
            self.record("annotation", {**base, "text": text, "a_px": m.at})
            result(client, "annotation", True, text, seq=f.seq, id=m.id)
            self.captures.add_item("note", f, text=text)
            if self.captures.archive is not None:
                self.captures.archive.mark(f, note=(m.at, text))
        else:
            self.spawn(self.captures.capture(client, f, base, m))

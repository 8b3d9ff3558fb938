"""What the console page and the expert daemon say to each other over the console's WebSocket.

To the page
    Binary: one video frame, a 32-byte little-endian header then the JPEG bytes, or (flag 2)
    the encoded frame as the expert received it (VP8 or H.264, for the page's WebCodecs
    decoder; flag 4: a keyframe)::

        u8 version (2) | u8 track (0 us, 1 pov) | u8 flags (1: a cine frame, not live;
        2: encoded, not JPEG; 4: a keyframe; 8: H.264, else VP8) | u8 0
        u32 seq | f64 t_capture (s, the expert's clock) | f32 spacing_row_mm |
        f32 spacing_col_mm (0 when unknown) | u16 width | u16 height |
        f32 depth_origin_row (px: the row of depth 0 on a US image; NaN when unknown)

    Text: JSON objects with a ``type``: ``state`` (the session at a glance, about 20 times a
    second, with ``t``, the expert's clock when it was taken), ``cine`` (the frozen loop's
    frame numbers and times), ``result`` (what became of a click: a scan started, a
    measurement, a saved capture, or why not; with the click's ``id``), ``pong`` (the answer
    to a ``ping``: ``n`` and ``t``, the expert's clock, s), ``captures`` (the session's
    captures and measurements so far), ``hello`` (the page's settings: the console's limits
    and the track names).

From the page (:data:`PageMessage`; anything else is refused and counted)
    ``drawn`` (a frame was drawn: latency echo), ``ping`` (heartbeat), ``scan``
    (start/stop), ``clutch`` (on/off), ``freeze`` (on/off), ``cine`` (send frame ``seq`` of
    the frozen loop), ``caliper`` (two points on a frame, image px), ``annotation`` (a text
    at a point of a frame), ``capture`` (save a frame with its pose, and a clip of the cine
    before it), ``keyframe`` (the page's decoder of a track needs one). Clicks may carry
    an ``id``, returned in their ``result``. Points are image pixels (x right, y down, from
    the top-left corner of the image the header describes).
"""

from __future__ import annotations

import math
import struct
import unicodedata
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, TypeAdapter

FRAME_VERSION = 2
TRACK_IDS = {"us": 0, "pov": 1}
FLAG_CINE = 1
FLAG_ENCODED = 2
FLAG_KEYFRAME = 4
FLAG_H264 = 8
_HEADER = struct.Struct("<BBBBIdffHHf")
HEADER_SIZE = _HEADER.size  # 32
MAX_PAGE_MESSAGE = 16384  # bytes: the longest, an annotation (text up to 200 characters), is far
# under it


def frame_header(
    track: str,
    seq: int,
    t_capture: float,
    spacing_mm: tuple[float, float] | None,
    width: int,
    height: int,
    cine: bool = False,
    depth0: float | None = None,
    flags: int = 0,
) -> bytes:
    """The 32-byte header of a frame message (see the module docstring)."""
    row, col = spacing_mm if spacing_mm is not None else (0.0, 0.0)
    return _HEADER.pack(
        FRAME_VERSION, TRACK_IDS[track], (FLAG_CINE if cine else 0) | flags, 0,
        seq & 0xFFFFFFFF, t_capture, row, col, width, height,
        math.nan if depth0 is None else depth0,
    )  # fmt: skip


def parse_header(data: bytes) -> dict:
    """The header's fields (for tests and tools)."""
    v, track, flags, _, seq, t, row, col, w, h, depth0 = _HEADER.unpack_from(data)
    names = {i: n for n, i in TRACK_IDS.items()}
    return {
        "version": v, "track": names[track], "cine": bool(flags & FLAG_CINE), "seq": seq,
        "encoded": bool(flags & FLAG_ENCODED), "keyframe": bool(flags & FLAG_KEYFRAME),
        "t_capture": t, "spacing_mm": (row, col), "width": w, "height": h,
        "depth_origin_row": None if math.isnan(depth0) else depth0,
    }  # fmt: skip


class _Msg(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)


Px = Annotated[float, Field(ge=-1e5, le=1e5, allow_inf_nan=False)]
Point = tuple[Px, Px]
Seq = Annotated[int, Field(ge=0, le=0xFFFFFFFF)]


def plain_text(text: str) -> str:
    """``text`` as it may be shown, recorded and listed: control characters (line breaks,
    tabs: a space) and the invisible format ones (bidirectional overrides such as U+202E,
    which reverse what follows on screen; zero-width characters) dropped, and runs of spaces
    made one (Unicode categories Cc, Cf, Co, Cs, Cn)."""
    kept = (
        " " if ch.isspace() else ch
        for ch in text
        if ch.isspace() or not unicodedata.category(ch).startswith("C")
    )
    return " ".join("".join(kept).split())


def outside_image(points: list[tuple[float, float]], width: int, height: int) -> str | None:
    """Why points (image px, x right, y down; the pixel grid's edges 0 and width/height)
    cannot be on a ``width`` x ``height`` image, or None when they all are."""
    for x, y in points:
        if not (0.0 <= x <= width and 0.0 <= y <= height):
            return f"point ({x:.0f}, {y:.0f}) px is outside the {width} x {height} image"
    return None


class Drawn(_Msg):
    """Frame ``seq`` of ``track`` was drawn (first time), and this was sent
    ``draw_to_send_ms`` after the draw call; ``counter``: the frame counter
    (:mod:`humantele.video.counter`, 24 bits) the page read back from the canvas it drew,
    None when it did not read."""

    type: Literal["drawn"]
    track: Literal["us", "pov"]
    seq: Seq
    draw_to_send_ms: float = Field(ge=0.0, le=10_000.0, allow_inf_nan=False)
    counter: Annotated[int, Field(ge=0, le=0xFFFFFF)] | None = None


CommandId = Annotated[int, Field(ge=0, le=0x7FFFFFFF)]


class _Command(_Msg):
    """A click: ``id`` (the page's number for it) comes back in the ``result`` that says
    what became of it, so the page can say a click was not acknowledged."""

    id: CommandId | None = None


class Ping(_Msg):
    """The page's heartbeat: answered at once with ``pong`` (same ``n``, the expert's clock
    ``t``, s), which measures how late the daemon answers and maps its clock to the page's.
    ``behind_ms``: how late the page reads what it is sent (the least lag of the messages it
    read in the last 2 s, from their ``t``; None: not known)."""

    type: Literal["ping"]
    n: CommandId
    behind_ms: float | None = Field(None, ge=0.0, le=3.6e6, allow_inf_nan=False)


class ScanCommand(_Command):
    type: Literal["scan"]
    action: Literal["start", "stop"]


class ClutchCommand(_Command):
    type: Literal["clutch"]
    on: bool


class Freeze(_Command):
    """Freeze the ultrasound (``on``) or go back to live."""

    type: Literal["freeze"]
    on: bool


class CineRequest(_Msg):
    """Send frame ``seq`` of the frozen loop."""

    type: Literal["cine"]
    seq: Seq


class Caliper(_Command):
    """A distance between ``a`` and ``b`` (image px) on ultrasound frame ``seq``."""

    type: Literal["caliper"]
    seq: Seq
    a: Point
    b: Point


class Annotation(_Command):
    """``text`` at ``at`` (image px) on ultrasound frame ``seq``."""

    type: Literal["annotation"]
    seq: Seq
    at: Point
    text: Annotated[str, Field(min_length=1, max_length=200), AfterValidator(plain_text)]


class Capture(_Command):
    """Save ultrasound frame ``seq`` with its pose and, with ``clip_s`` > 0, a clip of the
    cine's last ``clip_s`` seconds up to that frame (MP4) beside it."""

    type: Literal["capture"]
    seq: Seq
    clip_s: float = Field(0.0, ge=0.0, le=60.0, allow_inf_nan=False)


class KeyframeRequest(_Msg):
    """The page's decoder of ``track`` lost its place (an error, a backlog): a keyframe."""

    type: Literal["keyframe"]
    track: Literal["us", "pov"]


PageMessage = Annotated[
    Drawn
    | Ping
    | ScanCommand
    | ClutchCommand
    | Freeze
    | CineRequest
    | Caliper
    | Annotation
    | Capture
    | KeyframeRequest,
    Field(discriminator="type"),
]
PAGE_MESSAGE = TypeAdapter(PageMessage)

"""Reading recordings, including files cut short by a crash (no MCAP footer).

The file is read sequentially (mcap's stream reader, chunk CRCs checked); a truncated or
corrupt tail ends the reading and is reported in :attr:`Recording.problem`, keeping every
complete chunk before it. High-rate topics arrive as columnar batches and are kept that way
(fast to turn into arrays); :meth:`Recording.samples` gives one dict per sample for any topic.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Channel, Footer, Message, Metadata
from mcap.stream_reader import StreamReader
from numpy.typing import NDArray

from humantele.recording.schemas import SESSION_METADATA


@dataclass
class Recording:
    """What a recording file holds: session metadata and, per topic, its messages in the order
    written: sample dicts ``{"t": ...}`` or columnar batches ``{"t": [...], ...}``.
    ``complete`` is False for a file without footer (the daemon was killed); ``problem`` says
    what ended the reading early, if anything."""

    path: Path
    session: dict[str, str] = field(default_factory=dict)
    messages: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    complete: bool = False
    problem: str | None = None
    bad_messages: int = 0

    @property
    def topics(self) -> list[str]:
        return sorted(self.messages)

    def samples(self, topic: str) -> list[dict[str, Any]]:
        """One dict per sample of ``topic`` (batches unpacked), in order."""
        out: list[dict[str, Any]] = []
        for m in self.messages.get(topic, []):
            if isinstance(m["t"], list):
                keys = list(m)
                out.extend(
                    dict(zip(keys, vals, strict=True)) for vals in zip(*m.values(), strict=True)
                )
            else:
                out.append(m)
        return out

    def count(self, topic: str) -> int:
        return sum(
            len(m["t"]) if isinstance(m["t"], list) else 1 for m in self.messages.get(topic, [])
        )

    def times(self, topic: str) -> NDArray[np.float64]:
        """The ``t`` of every sample of ``topic`` (s, recording daemon's clock)."""
        return self.column(topic, "t").astype(float)

    def column(self, topic: str, name: str, default: Any = np.nan) -> NDArray[Any]:
        """Field ``name`` of every sample of ``topic`` as an array, ``default`` where absent."""
        parts: list[NDArray[Any] | int] = []  # an int: that many samples lack the field
        width: tuple[int, ...] = ()
        for m in self.messages.get(topic, []):
            batch = isinstance(m["t"], list)
            if name in m:
                a = np.asarray(m[name] if batch else [m[name]])
                width = width or a.shape[1:]
                parts.append(a)
            else:
                parts.append(len(m["t"]) if batch else 1)
        arrays = [np.full((p, *width), default) if isinstance(p, int) else p for p in parts]
        return np.concatenate(arrays) if arrays else np.empty((0, *width))


class RecordingReadError(OSError):
    """A file that is not a recording at all (missing, unreadable, not MCAP)."""


def read_recording(path: str | Path, topics: Iterable[str] | None = None) -> Recording:
    """Read every complete message in ``path`` (only ``topics`` if given: others are not
    decoded); a crash-truncated tail is tolerated and reported in ``problem``."""
    path = Path(path)
    wanted = set(topics) if topics is not None else None
    rec = Recording(path=path)
    channels: dict[int, str | None] = {}
    try:
        stream = open(path, "rb")  # noqa: SIM115
    except OSError as exc:
        raise RecordingReadError(f"{path}: cannot read recording: {exc.strerror or exc}") from exc
    decode = json.JSONDecoder().decode
    with stream:
        records = StreamReader(stream, validate_crcs=True).records
        try:
            first = next(records)
        except Exception as exc:  # noqa: BLE001 - any failure here means "not MCAP"
            why = str(exc) or type(exc).__name__
            raise RecordingReadError(f"{path}: not an MCAP recording ({why})") from None
        try:
            for record in _chain([first], records):
                if isinstance(record, Message):
                    topic = channels.get(record.channel_id, "")
                    if topic is None:
                        continue  # not wanted
                    try:
                        msg = decode(record.data.decode())
                        ok = isinstance(msg, dict) and _well_formed(msg)
                    except (UnicodeDecodeError, ValueError):
                        ok = False
                    if not ok or not topic:
                        rec.bad_messages += 1
                        continue
                    rec.messages.setdefault(topic, []).append(msg)
                elif isinstance(record, Channel):
                    keep = wanted is None or record.topic in wanted
                    channels[record.id] = record.topic if keep else None
                elif isinstance(record, Metadata) and record.name == SESSION_METADATA:
                    rec.session = dict(record.metadata)
                elif isinstance(record, Footer):
                    rec.complete = True
        except Exception as exc:  # noqa: BLE001 - a torn tail after a crash: keep what is read
            detail = str(exc)
            rec.problem = f"reading stopped early ({type(exc).__name__}{': ' if detail else ''}"
            rec.problem += f"{detail})"
    if not rec.complete and rec.problem is None:
        rec.problem = "no footer (the recording was not closed)"
    return rec


def _well_formed(msg: dict[str, Any]) -> bool:
    t = msg.get("t")
    if isinstance(t, list):  # a columnar batch: every column as long as t
        return all(isinstance(v, list) and len(v) == len(t) for v in msg.values())
    return isinstance(t, int | float)


def _chain(first: list[Any], rest: Any) -> Any:
    yield from first
    yield from rest

"""Reading recordings, including files cut short by a crash (no MCAP footer).

The file is read sequentially (mcap's stream reader, chunk CRCs checked); a truncated or
corrupt tail ends the reading and is reported in :attr:`Recording.problem`, keeping every
complete chunk before it. Packed high-rate messages are unpacked into samples.
"""

from __future__ import annotations

import json
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
    """What a recording file holds: session metadata and the samples of each topic, in the
    order written. ``complete`` is False for a file without footer (the daemon was killed);
    ``problem`` says what ended the reading early, if anything."""

    path: Path
    session: dict[str, str] = field(default_factory=dict)
    samples: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    complete: bool = False
    problem: str | None = None
    bad_messages: int = 0

    @property
    def topics(self) -> list[str]:
        return sorted(self.samples)

    def times(self, topic: str) -> NDArray[np.float64]:
        """The ``t`` of every sample of ``topic`` (s, recording daemon's clock)."""
        return np.array([s["t"] for s in self.samples.get(topic, [])], dtype=float)

    def column(self, topic: str, name: str, default: Any = np.nan) -> NDArray[Any]:
        """Field ``name`` of every sample of ``topic`` as an array (``default`` if absent)."""
        rows = self.samples.get(topic, [])
        return np.array([s.get(name, default) for s in rows])


class RecordingReadError(OSError):
    """A file that is not a recording at all (missing, unreadable, not MCAP)."""


def read_recording(path: str | Path) -> Recording:
    """Read every complete sample in ``path``; a crash-truncated tail is tolerated."""
    path = Path(path)
    rec = Recording(path=path)
    channels: dict[int, str] = {}
    try:
        stream = open(path, "rb")  # noqa: SIM115
    except OSError as exc:
        raise RecordingReadError(f"{path}: cannot read recording: {exc.strerror or exc}") from exc
    decode = json.JSONDecoder().decode
    with stream:
        reader = StreamReader(stream, validate_crcs=True)
        records = reader.records
        try:
            first = next(records)
        except Exception as exc:  # noqa: BLE001 - any failure here means "not MCAP"
            why = str(exc) or type(exc).__name__
            raise RecordingReadError(f"{path}: not an MCAP recording ({why})") from None
        pending = [first]
        try:
            for record in _chain(pending, records):
                if isinstance(record, Message):
                    topic = channels.get(record.channel_id)
                    if topic is None:
                        rec.bad_messages += 1
                        continue
                    try:
                        msg = decode(record.data.decode())
                    except (UnicodeDecodeError, ValueError):
                        rec.bad_messages += 1
                        continue
                    out = rec.samples.setdefault(topic, [])
                    if isinstance(msg, dict) and "samples" in msg and "t" not in msg:
                        out.extend(s for s in msg["samples"] if isinstance(s, dict) and "t" in s)
                    elif isinstance(msg, dict) and "t" in msg:
                        out.append(msg)
                    else:
                        rec.bad_messages += 1
                elif isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Metadata) and record.name == SESSION_METADATA:
                    rec.session = dict(record.metadata)
                elif isinstance(record, Footer):
                    rec.complete = True
        except Exception as exc:  # noqa: BLE001 - a torn tail after a crash: keep what is read
            rec.problem = f"reading stopped early ({type(exc).__name__}: {exc})".replace(": )", ")")
    if not rec.complete and rec.problem is None:
        rec.problem = "no footer (the recording was not closed)"
    return rec


def _chain(first: list[Any], rest: Any) -> Any:
    yield from first
    yield from rest

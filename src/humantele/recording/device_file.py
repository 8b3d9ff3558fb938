"""The device recording file: what a clinic's devices delivered, in one MCAP, and its reader.

``humantele devices record`` (:mod:`humantele.devices.record`) writes it; the ``replay``
backends (tracker camera, force sensor, video) and the hl2ss replay server read it.

File: MCAP with header profile ``humantele.devices`` and a metadata record
``humantele.device_recording`` (format version, start time, what was recorded). Chunks are
zstd-compressed (mcap depends on ``zstandard``). Each message is one device sample in the
encoding ``humantele.blobs/v1``: a ``<I`` length, that many bytes of UTF-8 JSON (the fields;
the schema, ``jsonschema``, describes them) whose ``blobs`` list names the binary parts that
follow in order (name, dtype, shape, bytes). Log times are the recorder's receive time
(``time.monotonic``, ns).

Topics (:data:`TOPICS`):

- ``/ahat/calibration`` (once, before any frame): hl2ss's mode-2 bytes (blob ``calibration``).
- ``/ahat/frame``: one AHAT packet as hl2ss sent it: ``timestamp`` (100 ns ticks, the
  headset's clock), ``sensor_ticks``, ``t_receive`` (s), blobs ``depth`` and ``ab`` ((512,
  512) ``<u2``, raw: not undistorted) and ``pose`` ((4, 4) ``<f4``, row-vector, translation in
  the last row, as hl2ss sends it; absent in mode 0).
- ``/force/hid_report``: one raw HID report as read, before parsing (blob ``report``), with
  ``t_receive`` (s).
- ``/video/us``, ``/video/pov``: one frame as JPEG (blob ``jpeg``) with ``t_capture`` (s),
  ``seq``, ``width``, ``height`` and the source's ``pixel_spacing_mm``/``depth_origin_row``.

Reading (:class:`DeviceRecording`): a file that is not MCAP, or an MCAP that is not a device
recording (a session recording, another program's), is refused with one line
(:class:`DeviceRecordingError`). A file cut short (no footer: the recorder was killed, the
copy was cut) is read up to its torn tail: :attr:`DeviceRecording.problem` says so and the
readers log it once.
"""

from __future__ import annotations

import json
import logging
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.reader import make_reader
from mcap.records import Channel, Footer, Header, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

log = logging.getLogger("humantele.devices.replay")

PROFILE = "humantele.devices"
METADATA_NAME = "humantele.device_recording"
FORMAT_VERSION = "1"
MESSAGE_ENCODING = "humantele.blobs/v1"
SCHEMA_ENCODING = "jsonschema"
MAGIC = b"\x89MCAP0\r\n"

AHAT_CALIBRATION = "/ahat/calibration"
AHAT_FRAME = "/ahat/frame"
HID_REPORT = "/force/hid_report"
VIDEO = {"us": "/video/us", "pov": "/video/pov"}

_LEN = struct.Struct("<I")
_BLOB = {
    "type": "object",
    "description": "a binary part after the JSON: name, dtype, shape, bytes",
    "properties": {
        "name": {"type": "string"},
        "dtype": {"type": "string"},
        "shape": {"type": "array"},
        "bytes": {"type": "integer"},
    },
}


def _schema(title: str, props: dict[str, Any], blobs: str) -> dict[str, Any]:
    return {
        "title": title,
        "type": "object",
        "description": f"binary parts: {blobs}",
        "properties": {**props, "blobs": {"type": "array", "items": _BLOB}},
    }


_NUM = {"type": "number"}
_INT = {"type": "integer"}
TOPICS: dict[str, tuple[str, dict[str, Any]]] = {
    AHAT_CALIBRATION: (
        "humantele.devices.AhatCalibration",
        _schema(
            "hl2ss AHAT calibration (mode 2 bytes)",
            {"t_receive": _NUM, "source": {"type": "string"}},
            "calibration (hl2ss's _Mode2Layout_RM_DEPTH_AHAT, float32)",
        ),
    ),
    AHAT_FRAME: (
        "humantele.devices.AhatFrame",
        _schema(
            "hl2ss AHAT frame (RAW)",
            {"t_receive": _NUM, "timestamp": _INT, "sensor_ticks": _INT, "seq": _INT},
            "depth (512x512 <u2, mm), ab (512x512 <u2), pose (4x4 <f4 as hl2ss sends it; mode 1)",
        ),
    ),
    HID_REPORT: (
        "humantele.devices.HidReport",
        _schema("force board HID report, raw", {"t_receive": _NUM}, "report (the bytes read)"),
    ),
    **{
        topic: (
            "humantele.devices.VideoFrame",
            _schema(
                f"{name} video frame",
                {
                    "t_capture": _NUM,
                    "seq": _INT,
                    "width": _INT,
                    "height": _INT,
                    "pixel_spacing_mm": {"type": ["array", "null"]},
                    "depth_origin_row": {"type": ["number", "null"]},
                },
                "jpeg (the frame, BGR encoded as JPEG)",
            ),
        )
        for name, topic in VIDEO.items()
    },
}


class DeviceRecordingError(ValueError):
    """A file that is not a device recording, or holds nothing of what is asked: one line."""


def encode_message(fields: dict[str, Any], blobs: dict[str, bytes | np.ndarray]) -> bytes:
    """``fields`` (JSON) and the binary ``blobs`` (arrays keep their dtype and shape)."""
    parts, desc = [], []
    for name, value in blobs.items():
        if isinstance(value, np.ndarray):
            a = np.ascontiguousarray(value)
            data = a.tobytes()
            desc.append(
                {"name": name, "dtype": a.dtype.str, "shape": list(a.shape), "bytes": len(data)}
            )
        else:
            data = bytes(value)
            desc.append({"name": name, "dtype": "bytes", "shape": [len(data)], "bytes": len(data)})
        parts.append(data)
    head = json.dumps({**fields, "blobs": desc}, separators=(",", ":")).encode()
    return _LEN.pack(len(head)) + head + b"".join(parts)


def decode_message(data: bytes) -> tuple[dict[str, Any], dict[str, Any]]:
    """(fields, blobs) of one message; arrays as numpy arrays, ``bytes`` as bytes.
    ValueError when the message is malformed."""
    if len(data) < _LEN.size:
        raise ValueError("message shorter than its length field")
    (n,) = _LEN.unpack_from(data, 0)
    fields = json.loads(bytes(data[_LEN.size : _LEN.size + n]))
    if not isinstance(fields, dict) or not isinstance(fields.get("blobs", []), list):
        raise ValueError("message fields are not a JSON object with a blobs list")
    off = _LEN.size + n
    blobs: dict[str, Any] = {}
    for b in fields.pop("blobs", []):
        size = int(b["bytes"])
        raw = bytes(data[off : off + size])
        if len(raw) != size:
            raise ValueError(f"blob {b.get('name')!r} is cut short")
        off += size
        if b["dtype"] == "bytes":
            blobs[b["name"]] = raw
        else:
            blobs[b["name"]] = np.frombuffer(raw, np.dtype(b["dtype"])).reshape(b["shape"])
    if off != len(data):
        raise ValueError(f"{len(data) - off} bytes after the last blob")
    return fields, blobs


class DeviceRecordingWriter:
    """Writes a device recording; thread-safe (one lock around the MCAP writer).
    ``write(topic, t, fields, blobs)``; ``flush()`` closes the chunk in progress (call it
    every second or so: a killed recorder keeps what was flushed); ``close()`` writes the
    summary and footer. Counts messages per topic in ``counts``."""

    def __init__(
        self, path: str | Path, info: dict[str, str] | None = None, chunk_size: int = 4 << 20
    ) -> None:
        self.path = Path(path)
        self._stream: IO[bytes] = open(self.path, "xb")  # noqa: SIM115 - closed in close()
        self._lock = threading.Lock()
        self._writer = Writer(self._stream, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library="humantele devices record")
        meta = {
            "version": FORMAT_VERSION,
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            **(info or {}),
        }
        self._writer.add_metadata(METADATA_NAME, meta)
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        self.closed = False

    def _channel(self, topic: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            name, schema = TOPICS[topic]
            sid = self._writer.register_schema(name, SCHEMA_ENCODING, json.dumps(schema).encode())
            cid = self._writer.register_channel(topic, MESSAGE_ENCODING, sid)
            self._channels[topic] = cid
        return cid

    def write(
        self, topic: str, t: float, fields: dict[str, Any], blobs: dict[str, bytes | np.ndarray]
    ) -> None:
        """One sample of ``topic`` received at ``t`` (s, ``time.monotonic``)."""
        data = encode_message(fields, blobs)
        ns = max(0, int(t * 1e9))
        with self._lock:
            if self.closed:
                return
            seq = self._seq.get(topic, 0)
            self._seq[topic] = seq + 1
            self._writer.add_message(self._channel(topic), ns, data, ns, seq)
            self.counts[topic] = self.counts.get(topic, 0) + 1

    def flush(self) -> None:
        with self._lock:
            if not self.closed:
                self._writer.flush()

    def bytes_written(self) -> int:
        """Bytes in the file so far (flushed chunks)."""
        try:
            return self.path.stat().st_size
        except OSError:
            return 0

    def close(self) -> None:
        with self._lock:
            if self.closed:
                return
            self.closed = True
            try:
                self._writer.finish()
                self._stream.flush()
            finally:
                self._stream.close()


@dataclass
class Sample:
    """One recorded message: its topic, log time (s), fields and blobs."""

    topic: str
    t: float
    fields: dict[str, Any]
    blobs: dict[str, Any]


class DeviceRecording:
    """A device recording to read. Construction checks it is one (one-line
    :class:`DeviceRecordingError` otherwise) and whether it is complete (a footer's magic at
    its end); :meth:`samples` reads it lazily, once per call, from the start."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.problem: str | None = None
        self.bad_messages = 0  # malformed messages skipped
        self._warned = False
        try:
            size = self.path.stat().st_size
            with open(self.path, "rb") as f:
                head = f.read(len(MAGIC))
                f.seek(max(0, size - len(MAGIC)))
                tail = f.read(len(MAGIC))
        except OSError as exc:
            raise DeviceRecordingError(
                f"{self.path}: cannot read it ({exc.strerror or exc})"
            ) from None
        if head != MAGIC:
            raise DeviceRecordingError(
                f"{self.path} is not an MCAP file, so not a device "
                "recording (`humantele devices record` writes one)"
            )
        self.complete = size >= 2 * len(MAGIC) and tail == MAGIC
        self.info = self._check_header()
        if not self.complete:
            self.problem = (
                f"{self.path.name} is truncated (no MCAP footer: the recording was "
                "cut short); replaying what is intact"
            )

    def _check_header(self) -> dict[str, str]:
        """The recording's metadata; DeviceRecordingError unless the header's profile and
        the first metadata say it is a device recording."""
        with open(self.path, "rb") as f:
            records = StreamReader(f, validate_crcs=True).records
            try:
                header = next(records)
                meta = next(records)
            except Exception as exc:  # noqa: BLE001 - any failure: not one of ours
                raise DeviceRecordingError(
                    f"{self.path}: not a readable MCAP file ({exc or type(exc).__name__})"
                ) from None
        profile = getattr(header, "profile", None) if isinstance(header, Header) else None
        if profile != PROFILE or not (isinstance(meta, Metadata) and meta.name == METADATA_NAME):
            what = f"profile {profile!r}" if profile else "no profile"
            raise DeviceRecordingError(
                f"{self.path} is an MCAP file but not a device recording ({what}; a session "
                "recording is not one): record one with `humantele devices record`"
            )
        info = dict(meta.metadata)
        if info.get("version") != FORMAT_VERSION:
            raise DeviceRecordingError(
                f"{self.path}: device recording format version "
                f"{info.get('version')!r}, this reads {FORMAT_VERSION}"
            )
        return info

    def span(self) -> tuple[float, float] | None:
        """The first and last message's times (s, the recorder's ``time.monotonic``), from the
        file's summary; None for a file without one (cut short) or with no message."""
        if not self.complete:
            return None
        try:
            with open(self.path, "rb") as f:
                summary = make_reader(f).get_summary()
        except Exception:  # noqa: BLE001 - a summary we cannot read: no span
            return None
        stats = None if summary is None else summary.statistics
        if stats is None or stats.message_count == 0:
            return None
        return stats.message_start_time * 1e-9, stats.message_end_time * 1e-9

    def warn_once(self, what: str = "") -> None:
        """Log :attr:`problem` once per recording (the replays call it at open and at the
        torn tail)."""
        if self.problem and not self._warned:
            self._warned = True
            log.warning("%s%s", self.problem, f" ({what})" if what else "")

    def samples(self, topics: set[str]) -> Iterator[Sample]:
        """The messages of ``topics`` in file order; stops at a torn tail (then
        :attr:`problem` says where). A malformed message is skipped and counted in
        ``bad_messages``."""
        channels: dict[int, str | None] = {}
        read = 0
        with open(self.path, "rb") as f:
            records = StreamReader(f, validate_crcs=True).records
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    return
                except Exception as exc:  # noqa: BLE001 - a torn tail: keep what came before
                    detail = str(exc) or type(exc).__name__
                    self.problem = (
                        f"{self.path.name} is truncated or damaged after "
                        f"{read} messages ({detail}); replayed what is intact"
                    )
                    self._warned = False
                    self.warn_once()
                    return
                if isinstance(record, Channel):
                    channels[record.id] = record.topic if record.topic in topics else None
                elif isinstance(record, Message):
                    read += 1
                    topic = channels.get(record.channel_id)
                    if topic is None:
                        continue
                    try:
                        fields, blobs = decode_message(record.data)
                    except (ValueError, KeyError, TypeError):
                        self.bad_messages += 1
                        continue
                    yield Sample(topic, record.log_time * 1e-9, fields, blobs)
                elif isinstance(record, Footer):
                    return


def open_recording(path: str | Path) -> DeviceRecording:
    """:class:`DeviceRecording` (the backends' one way in), logging a truncated file once."""
    rec = DeviceRecording(path)
    rec.warn_once("at open")
    return rec

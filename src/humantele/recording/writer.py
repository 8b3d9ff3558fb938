"""Writing recordings: :class:`McapLog` (synchronous MCAP file) and :class:`Recorder` (the
non-blocking front end the daemons call from their loops).

Crash safety: the recorder's writer thread closes the MCAP chunk in progress, flushes and
``fsync``s at least every ``flush_interval_s`` (0.2 s), so after a SIGKILL the file holds every
sample written up to about 0.25 s before the kill; :func:`humantele.recording.reader.read_recording`
reads a file that lacks its footer. A failure while recording (disk full, I/O error) is logged
and counted in :attr:`Recorder.stats`; it never raises into the caller.
"""

from __future__ import annotations

import collections
import datetime
import json
import logging
import os
import shutil
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Literal

from mcap.writer import CompressionType, Writer
from pydantic import Field

from humantele.config import ConfigModel
from humantele.recording.schemas import (
    CHANNELS,
    MESSAGE_ENCODING,
    SCHEMA_ENCODING,
    SESSION_METADATA,
    check_participant_id,
    make_sample,
    schema_bytes,
)

log = logging.getLogger("humantele.recording")
ATTACHMENT = "@attachment"  # the queue's marker for a file to attach (Recorder.attach)

try:
    import zstandard  # noqa: F401

    _HAVE_ZSTD = True
except ImportError:  # pragma: no cover - zstandard ships with the test environment
    _HAVE_ZSTD = False

_dumps = json.JSONEncoder(allow_nan=False, separators=(",", ":")).encode


class RecordingError(OSError):
    """A recording that cannot start (unwritable path, existing file, disk full)."""


class RecorderConfig(ConfigModel):
    """How a daemon records (``[recording]`` in its configuration)."""

    flush_interval_s: float = Field(0.2, gt=0.0, le=0.4, description="chunk close + fsync period")
    poll_interval_s: float = Field(0.05, gt=0.0, le=0.1, description="writer thread wake-up")
    batch_max_samples: int = Field(100, ge=1, le=10_000, description="samples per packed message")
    queue_size: int = Field(200_000, ge=100, description="samples waiting; beyond: dropped")
    queue_mb: float = Field(
        64.0,
        gt=0.0,
        description="bytes payloads (video frames, files) waiting, MB; beyond: dropped",
    )
    min_free_mb: float = Field(50.0, ge=0.0, description="free disk space needed to start, MB")
    compression: Literal["zstd", "none"] = "zstd"
    fsync: bool = True


class McapLog:
    """A recording file: validates samples, packs high-rate ones, writes MCAP chunks.

    Not thread-safe; :class:`Recorder` drives it from one writer thread. ``append`` raises
    ValueError on a bad sample (nothing is written) and OSError on an I/O failure.
    """

    def __init__(
        self,
        output: str | Path | IO[bytes],
        metadata: dict[str, str],
        *,
        compression: str = "zstd",
        batch_max_samples: int = 100,
        fsync: bool = True,
    ) -> None:
        if isinstance(output, str | Path):
            self._stream: IO[bytes] = open(output, "xb")  # noqa: SIM115 - closed in close()
            self._owns = True
        else:
            self._stream = output
            self._owns = False
        self._fsync = fsync
        self._batch_max = batch_max_samples
        comp = (
            CompressionType.ZSTD if compression == "zstd" and _HAVE_ZSTD else CompressionType.NONE
        )
        # Chunks are closed by flush(); the size limit only bounds a chunk between flushes.
        self._writer = Writer(self._stream, chunk_size=1 << 20, compression=comp)
        self._writer.start(profile="", library="humantele")
        self._writer.add_metadata(SESSION_METADATA, dict(metadata))
        self._channel_ids: dict[str, int] = {}
        self._sequence: dict[str, int] = collections.defaultdict(int)
        self._pending: dict[str, tuple[int, dict[str, list[Any]]]] = {}  # columnar batches
        self.messages = 0
        self.samples = 0  # accepted by append
        self.samples_flushed = 0  # on disk (as far as fsync says)
        self.closed = False
        self.flush()

    def _channel(self, topic: str) -> int:
        cid = self._channel_ids.get(topic)
        if cid is None:
            spec = CHANNELS[topic]
            sid = self._writer.register_schema(
                spec.schema_name, SCHEMA_ENCODING, schema_bytes(spec)
            )
            cid = self._writer.register_channel(topic, MESSAGE_ENCODING, sid)
            self._channel_ids[topic] = cid
        return cid

    def _emit(self, topic: str, log_time_ns: int, message: dict[str, Any]) -> None:
        seq = self._sequence[topic]
        self._sequence[topic] = seq + 1
        self._writer.add_message(
            self._channel(topic), log_time_ns, _dumps(message).encode(), log_time_ns, seq
        )
        self.messages += 1

    def append(self, topic: str, t: float, payload: dict[str, Any], log_time_ns: int) -> None:
        """Add one sample of ``topic`` (see :mod:`humantele.recording.schemas`)."""
        spec = CHANNELS.get(topic)
        if spec is None:
            raise ValueError(f"unknown topic {topic!r}")
        sample = make_sample(spec, t, payload)
        self.samples += 1
        if not spec.batch:
            self._emit(topic, log_time_ns, sample)
            return
        pending = self._pending.get(topic)
        if pending is not None and pending[1].keys() != sample.keys():
            self._emit(topic, *self._pending.pop(topic))  # another set of fields: new batch
            pending = None
        if pending is None:
            self._pending[topic] = (log_time_ns, {k: [v] for k, v in sample.items()})
            return
        columns = pending[1]
        for k, v in sample.items():
            columns[k].append(v)
        if len(columns["t"]) >= self._batch_max:
            self._emit(topic, *self._pending.pop(topic))

    def attach(self, name: str, media_type: str, data: bytes, log_time_ns: int) -> None:
        """Add a file (an MCAP attachment, e.g. a captured image); OSError on I/O failure."""
        if not isinstance(data, bytes | bytearray) or not name or len(name) > 200:
            raise ValueError(f"attachment {name!r}: bytes and a name of 1-200 characters")
        self._writer.add_attachment(log_time_ns, log_time_ns, name, media_type, bytes(data))
        self.samples += 1

    def flush(self) -> None:
        """Write the packed samples, close the chunk, flush and fsync: all so far is on disk."""
        for topic, (log_time_ns, columns) in list(self._pending.items()):
            self._emit(topic, log_time_ns, columns)
        self._pending.clear()
        self._writer.flush()
        pending = self.samples
        if self._fsync:
            try:
                os.fsync(self._stream.fileno())
            except (AttributeError, OSError, ValueError) as exc:
                if isinstance(exc, OSError) and exc.errno not in (None, 22):  # EINVAL: a pipe
                    raise
        self.samples_flushed = pending

    def close(self) -> None:
        """Flush and write the MCAP summary and footer."""
        if self.closed:
            return
        self.closed = True
        try:
            self.flush()
            self._writer.finish()
            self._stream.flush()
            if self._fsync and self._owns:
                os.fsync(self._stream.fileno())
        finally:
            if self._owns:
                self._stream.close()


def role_path(path: str | Path, role: str) -> Path:
    """The file a daemon of ``role`` records to when a session is recorded as ``path`` by
    several processes: ``runs/demo.mcap`` -> ``runs/demo.expert.mcap``. ``humantele analyze``
    joins the files again by their session id."""
    path = Path(path)
    stem = path.name[: -len(".mcap")] if path.name.endswith(".mcap") else path.name
    return path.with_name(f"{stem}.{role}.mcap")


@dataclass
class RecorderStats:
    """Counters of a :class:`Recorder` (read any time, from any thread)."""

    queued: int = 0
    written: int = 0  # flushed to the file
    dropped_overflow: int = 0
    dropped_invalid: int = 0
    dropped_failed: int = 0
    flushes: int = 0
    writer_cpu_s: float = 0.0
    error: str | None = None
    last_invalid: str | None = None


def _session_metadata(
    role: str, session_id: str | None, follower_id: str | None, sonographer_id: str | None
) -> dict[str, str]:
    from humantele import __version__ as version  # noqa: PLC0415

    md = {
        "role": role,
        "session_id": session_id or uuid.uuid4().hex[:12],
        "created_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "software": f"humantele {version}",
        "time": "t fields: seconds on the recording daemon's clock (CLOCK_MONOTONIC); "
        "t + clock_unix_offset_s is Unix time; see */clock_sync for the other daemon's",
        # the wall clock at the start (a tool's time axis: Foxglove's), not for the analysis
        "clock_unix_offset_s": f"{time.time() - time.monotonic():.6f}",
    }
    if follower_id is not None:
        md["follower_id"] = check_participant_id(follower_id, "follower_id")
    if sonographer_id is not None:
        md["sonographer_id"] = check_participant_id(sonographer_id, "sonographer_id")
    if not md["session_id"].replace("-", "").replace("_", "").isalnum():
        raise ValueError(f"session_id {session_id!r}: use letters, digits, '-' and '_' only")
    return md


class Recorder:
    """Records one daemon's streams into an MCAP file without ever blocking the caller.

    ``write(topic, t, payload)`` costs the caller a deque append; a writer thread validates,
    packs, writes and fsyncs. When the queue is full the sample is dropped and counted; an I/O
    failure during the session is logged once, kept in ``stats.error`` and counted, never raised.
    A path that cannot be recorded to raises :class:`RecordingError` here, at start.

    ``role`` is 'expert', 'follower' or 'demo' (both daemons in one process, one file).
    ``follower_id``/``sonographer_id`` are pseudonyms ('F03', 'S1'): ValueError otherwise.
    Payloads are serialised later in the writer thread: do not mutate them after ``write``.
    """

    def __init__(
        self,
        path: str | Path | IO[bytes],
        role: str,
        *,
        session_id: str | None = None,
        follower_id: str | None = None,
        sonographer_id: str | None = None,
        config: RecorderConfig | None = None,
    ) -> None:
        if role not in ("expert", "follower", "demo"):
            raise ValueError(f"role must be 'expert', 'follower' or 'demo', got {role!r}")
        self.config = config or RecorderConfig()
        self.role = role
        self.follower_id = follower_id
        self.sonographer_id = sonographer_id
        self.metadata = _session_metadata(role, session_id, follower_id, sonographer_id)
        self.path = Path(path) if isinstance(path, str | Path) else None
        if self.path is not None:
            self._check_path(self.path)
        try:
            self._log = McapLog(
                path,
                self.metadata,
                compression=self.config.compression,
                batch_max_samples=self.config.batch_max_samples,
                fsync=self.config.fsync,
            )
        except OSError as exc:
            where = self.path or "stream"
            raise RecordingError(f"cannot record to {where}: {exc.strerror or exc}") from exc
        self.stats = RecorderStats()
        self._queue: collections.deque[tuple[str, float, Any, int]] = collections.deque()
        self._maxlen = self.config.queue_size
        self._max_bytes = int(self.config.queue_mb * 1e6)
        self._bytes_in = 0  # bytes payloads queued (caller side only)
        self._bytes_out = 0  # of those, taken by the writer thread (writer side only)
        self._closing = False
        self._failed = False
        self._wake = threading.Event()
        self._warned_topics: set[str] = set()
        self._thread = threading.Thread(target=self._run, name="humantele-recorder", daemon=True)
        self._thread.start()

    def _check_path(self, path: Path) -> None:
        if path.exists():
            raise RecordingError(f"cannot record to {path}: the file exists (never overwritten)")
        parent = path.parent if str(path.parent) else Path(".")
        if not parent.is_dir():
            raise RecordingError(f"cannot record to {path}: no directory {parent}")
        if not os.access(parent, os.W_OK):
            raise RecordingError(f"cannot record to {path}: directory {parent} is not writable")
        free_mb = shutil.disk_usage(parent).free / 1e6
        if free_mb < self.config.min_free_mb:
            raise RecordingError(
                f"cannot record to {path}: only {free_mb:.0f} MB free "
                f"(recording.min_free_mb = {self.config.min_free_mb:g})"
            )

    # ---- caller side (any thread) -------------------------------------------------------
    def write(self, topic: str, t: float, payload: dict[str, Any]) -> bool:
        """Queue one sample of ``topic`` at time ``t`` (s, this daemon's clock); never blocks.
        Returns False if it was dropped (queue full, recorder failed or closed)."""
        if self._failed or self._closing:
            self.stats.dropped_failed += 1
            return False
        if len(self._queue) >= self._maxlen:
            self.stats.dropped_overflow += 1
            return False
        data = payload.get("data") if isinstance(payload, dict) else None
        if isinstance(data, bytes | bytearray):  # a video frame or a file: bound the memory
            if self._bytes_in + len(data) - self._bytes_out > self._max_bytes:
                self.stats.dropped_overflow += 1
                return False
            self._bytes_in += len(data)
        self._queue.append((topic, t, payload, time.time_ns()))
        self.stats.queued += 1
        return True

    def attach(self, name: str, media_type: str, data: bytes, t: float) -> bool:
        """Queue a file (``data``, e.g. a captured JPEG) to be attached to the recording at
        time ``t`` (s, this daemon's clock); never blocks. False if it was dropped."""
        return self.write(ATTACHMENT, t, {"name": name, "media_type": media_type, "data": data})

    def scan_start(
        self,
        t: float,
        scan: int,
        follower_id: str | None = None,
        sonographer_id: str | None = None,
    ) -> bool:
        """Record the start of scan number ``scan`` (expert clock); ids default to the
        recorder's. ValueError if an id is not a pseudonym."""
        payload: dict[str, Any] = {"event": "start", "scan": int(scan)}
        fid = follower_id or self.follower_id
        sid = sonographer_id or self.sonographer_id
        if fid is not None:
            payload["follower_id"] = check_participant_id(fid, "follower_id")
        if sid is not None:
            payload["sonographer_id"] = check_participant_id(sid, "sonographer_id")
        return self.write("/expert/scan", t, payload)

    def scan_stop(self, t: float, scan: int) -> bool:
        """Record the end of scan ``scan`` (expert clock)."""
        return self.write("/expert/scan", t, {"event": "stop", "scan": int(scan)})

    @property
    def failed(self) -> bool:
        return self._failed

    def close(self, timeout: float = 10.0) -> RecorderStats:
        """Write what is queued, finish the file (footer) and stop the thread."""
        self._closing = True
        self._wake.set()
        self._thread.join(timeout)
        return self.stats

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- writer thread ------------------------------------------------------------------
    def _fail(self, exc: BaseException) -> None:
        self._failed = True
        self.stats.error = f"{type(exc).__name__}: {exc}"
        self.stats.written = self._log.samples_flushed
        self.stats.dropped_failed += (
            len(self._queue) + self._log.samples - self._log.samples_flushed
        )
        self._queue.clear()
        log.error("recording to %s failed, recording stopped: %s", self.path, self.stats.error)

    def _drain(self) -> None:
        q, logfile, stats = self._queue, self._log, self.stats
        while q:
            topic, t, payload, log_time_ns = q.popleft()
            data = payload.get("data") if isinstance(payload, dict) else None
            if isinstance(data, bytes | bytearray):
                self._bytes_out += len(data)
            try:
                if topic == ATTACHMENT:
                    logfile.attach(
                        payload["name"], payload["media_type"], payload["data"], log_time_ns
                    )
                    continue
                logfile.append(topic, t, payload, log_time_ns)
            except (ValueError, TypeError, AttributeError) as exc:
                stats.dropped_invalid += 1
                stats.last_invalid = str(exc)
                if topic not in self._warned_topics:
                    self._warned_topics.add(topic)
                    log.warning("recording: dropped a bad sample (%s); counting the rest", exc)

    def _run(self) -> None:
        cfg = self.config
        last_flush = time.monotonic()
        try:
            while not self._closing:
                self._wake.wait(cfg.poll_interval_s)
                self._drain()
                now = time.monotonic()
                if now - last_flush >= cfg.flush_interval_s:
                    last_flush = now
                    self._log.flush()
                    self.stats.flushes += 1
                    self.stats.written = self._log.samples_flushed
                self.stats.writer_cpu_s = time.thread_time()
            self._drain()
            self._log.close()
            self.stats.written = self._log.samples_flushed
        except Exception as exc:  # noqa: BLE001 - a recording failure must not stop the session
            self._fail(exc)
            try:
                self._log._stream.close() if self._log._owns else None
            except OSError:
                pass
        self.stats.writer_cpu_s = time.thread_time()

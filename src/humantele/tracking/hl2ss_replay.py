"""A replay server speaking the hl2ss AHAT protocol, strict as the hl2ss app is.

It reads each client's configuration as the app does (:func:`read_configuration`) and closes
the socket where the app would (divisor 0, bitrate 0 even for RAW, unknown profiles, mode 3);
it also closes on depth ZDEPTH (no Zdepth encoder here), recording why in ``refusals``. AB
RAW frames are sent as they are, AB H.264/H.265 encoded per connection with libx264/libx265
through PyAV (:class:`~humantele.tracking.hl2ss_codec.AhatEncoder`), as the app encodes. Mode 2
sends the calibration (closes when it has none). Modes 0/1 send the packets of the next
"turn" in hl2ss's own layout (:func:`encode_ahat_packet`): every ``divisor``-th record, with
the rig pose in mode 1 (zeros for a record without one, as the app sends when the headset is
not located).

A turn is a list of items (or any iterable, iterated again for each client: :class:`McapTurn`
reads a device recording lazily): an :class:`AhatRecord` (encoded for the client's mode and
profile), an :class:`EncodedFrame` (encoded ahead, sent at its own capture time), ``bytes``
(sent as they are: corrupt packets for tests) or None (the server drops the connection there).
Refused and calibration connections do not use up a turn; after the last turn, new clients
are closed at once (``repeat=True``: every client gets the first turn again). ``rate_hz``
paces the records as the headset would (None: as fast as the client reads);
``recorded_times=True`` paces them at their own timestamps instead (100 ns ticks, from the
first record sent; a recording's real timing, gaps and jitter included). ``live=True``
stamps each frame with its capture time on this machine's ``time.monotonic`` (100 ns ticks),
as the headset stamps its own clock, so a client on the same machine knows each frame's age.
``spells``: (start, end) s from the connection's start where the headset's hand tracker
sees no hand and the AHAT camera runs at 5 Hz (:func:`sensor_frames`).

``epoch`` (a ``time.monotonic`` value, which every process of a machine shares; with
``rate_hz`` and a turn given as a list of records): the headset's world runs on from it whether
or not a client reads it, as a real one's does, and as another replay of the same clinic (the
force board's, started from the same epoch) does: record ``n`` (looped) is captured at ``epoch
+ n / rate_hz``, a client that connects (or reconnects after a stall) gets the frame of now,
and a frame whose time passed by more than a period before it could be sent (a server starved
on a loaded machine, a client that reads late) is dropped, as the headset's sensor drops what
its sender could not take (counted in ``dropped_late``); looped, the timestamps run on (each
round's are its records' plus the rounds before it, at the recording's own spacing), as a
headset's clock never goes back. Without it, each connection starts the
turn from its first record and sends every frame, however late: a replay that falls behind
the force board's for good, and starts again from the start at each reconnection.
``start_file``: the epoch is the first connection's time, shared through that file with the
other replays of the clinic (:func:`~humantele.runtime.shared_start.shared_start`): the
recorded devices run together from the follower's first read of any of them.

In its own process, serving records saved with :func:`save_records` (``.npz``) or a device
recording made by ``humantele devices record`` (``.mcap``: the frames and rig poses exactly as
the headset sent them, and its calibration; a truncated one is served up to its torn tail,
said on stderr; a file that is not one is refused in one line)::

    python -m humantele.tracking.hl2ss_replay FILE.npz|REC.mcap [--host H] [--port P] [--rate R]

(``--rate``: frames per second, 0 unpaced; default 45 for ``.npz``, the recorded times for
``.mcap``.)

prints ``hl2ss replay listening on H:P`` once it listens and serves until stopped.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import signal
import socket
import sys
import threading
import time
import zipfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from humantele.geometry import Pose
from humantele.runtime.shared_start import BadStartFile, shared_start
from humantele.tracking.hl2ss_calibration import Hl2ssAhatCalibration
from humantele.tracking.hl2ss_codec import AhatEncoder
from humantele.tracking.hl2ss_protocol import (
    DEPTH_PROFILE_SAME,
    HEADER,
    MODE_CALIBRATION,
    MODE_FRAMES_POSE,
    VIDEO_PROFILE_RAW,
    AhatConfiguration,
    ConfigurationRefused,
    encode_ahat_packet,
    hl2ss_matrix_from_pose,
    pose_from_hl2ss,
    read_configuration,
)


@dataclass
class AhatRecord:
    """One AHAT frame to replay: device timestamp (100 ns ticks), depth (mm) and AB images,
    sensor ticks, and the rig's pose in the app's world (None: not located); ``pose_hl2ss``:
    the pose matrix exactly as a headset sent it (recorded; sent as it is when given)."""

    timestamp: int
    depth_mm: NDArray[np.uint16]
    ab: NDArray[np.uint16]
    sensor_ticks: int = 0
    T_world_rig: Pose | None = None
    pose_hl2ss: NDArray[np.float32] | None = None

    def hl2ss_pose(self) -> NDArray[np.float32]:
        """The rig pose as hl2ss sends it (zeros: not located)."""
        if self.pose_hl2ss is not None:
            return self.pose_hl2ss
        return (np.zeros((4, 4), np.float32) if self.T_world_rig is None
                else hl2ss_matrix_from_pose(self.T_world_rig))  # fmt: skip

    def packet(self, mode: int) -> bytes:
        """The RAW packet of this record for a client in ``mode``."""
        pose = self.hl2ss_pose() if mode == MODE_FRAMES_POSE else None
        return encode_ahat_packet(self.timestamp, self.depth_mm, self.ab, self.sensor_ticks, pose)


def round_ticks(records: list[TurnItem]) -> int:
    """One round of a looped turn in timestamp ticks (100 ns): its records' first to last
    timestamp and one mean spacing more; 0 with fewer than two records."""
    stamps = [r.timestamp for r in records if isinstance(r, AhatRecord)]
    if len(stamps) < 2:
        return 0
    return round((stamps[-1] - stamps[0]) * len(stamps) / (len(stamps) - 1))


@dataclass
class EncodedFrame:
    """A frame encoded ahead (:meth:`AhatEncoder.payload`): its payload, its capture time (s
    from the connection's start), the AB profile it was encoded with and the rig pose as
    hl2ss sends it (None: zeros, not located)."""

    t_s: float
    payload: bytes
    profile_ab: int
    pose_hl2ss: NDArray[np.float32] | None = None


SPELL_RATE_HZ = 5.0  # the AHAT rate while the hand tracker sees no hand (hl2ss issue 162)


def sensor_frames(seconds: float, spells: list[tuple[float, float]] = (),
                  rate_hz: float = 45.0) -> list[tuple[int, float]]:  # fmt: skip
    """(frame index at ``rate_hz``, capture time s) of the frames the headset captures in
    ``seconds``: all of them, but only one in ``rate_hz / 5`` inside a spell (the hand
    tracker's 5 Hz)."""
    out = []
    step = max(1, round(rate_hz / SPELL_RATE_HZ))
    for k in range(int(seconds * rate_hz)):
        t = k / rate_hz
        if any(a <= t < b for a, b in spells) and k % step:
            continue
        out.append((k, t))
    return out


TurnItem = AhatRecord | EncodedFrame | bytes | None


_AGAIN = object()  # between two rounds of a looped turn


class Hl2ssReplayServer:
    """Serves ``turns`` (one per accepted stream connection) on ``host``:``port`` (0: any free
    port, see ``port``) from a background thread; ``close()`` stops it."""

    def __init__(
        self,
        turns: list[Iterable[TurnItem]],
        calibration: Hl2ssAhatCalibration | None = None,
        host: str = "127.0.0.1",
        port: int = 0,
        repeat: bool = False,
        loop: bool = False,
        rate_hz: float | None = None,
        recorded_times: bool = False,
        live: bool = False,
        spells: list[tuple[float, float]] = (),
        epoch: float | None = None,
        start_file: str | Path | None = None,
    ):
        self.turns = list(turns)
        self.repeat = repeat
        self.loop = loop  # within a connection: the turn again at its end, as a live headset
        self.rate_hz = rate_hz
        self.recorded_times = recorded_times
        self.live = live
        self.spells = list(spells)
        self.epoch = epoch
        self.start_file = start_file  # the epoch, claimed at the first connection or read there
        self.dropped_late = 0  # frames past their time by over a period (with an epoch)
        self.sent = 0  # frames sent, all connections
        self.calibration = calibration
        self._calibration_bytes = None if calibration is None else calibration.to_bytes()
        self.configs: list[AhatConfiguration] = []  # accepted stream configurations
        self.refusals: list[str] = []
        self.calibration_sent = 0
        self._stop = threading.Event()
        self.sock = socket.create_server((host, port))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.thread = threading.Thread(target=self._run, name="hl2ss-replay", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn:
                conn.settimeout(5.0)
                with contextlib.suppress(OSError):
                    self._serve(conn)

    def _recv_exactly(self, conn: socket.socket, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = conn.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("client left during the configuration")
            buf += chunk
        return buf

    def _serve(self, conn: socket.socket) -> None:
        try:
            cfg = read_configuration(lambda n: self._recv_exactly(conn, n))
        except ConfigurationRefused as exc:
            self.refusals.append(str(exc))
            return  # the app returns from Run(): the socket is closed
        if cfg.mode == MODE_CALIBRATION:
            if self._calibration_bytes is None:
                self.refusals.append("no calibration to replay")
                return
            conn.sendall(self._calibration_bytes)
            self.calibration_sent += 1
            return
        if cfg.profile_z != DEPTH_PROFILE_SAME:
            self.refusals.append(f"no Zdepth encoder here (asked depth {cfg.profile_z})")
            return
        if not self.turns:
            self.refusals.append("no turn left")
            return
        self.configs.append(cfg)
        items = self.turns[0] if self.repeat else self.turns.pop(0)
        if self.epoch is None and self.start_file is not None:
            try:
                self.epoch = shared_start(self.start_file)
            except BadStartFile as exc:
                self.refusals.append(str(exc))
                return
        if self.epoch is not None and self.rate_hz and isinstance(items, list) and items:
            self._serve_from_epoch(conn, cfg, items)
            return
        encoder: AhatEncoder | None = None
        k = 0
        step = max(1, round((self.rate_hz or 45.0) / SPELL_RATE_HZ))
        t0 = time.monotonic()
        ts0: int | None = None
        for item in self._items(items):
            if item is None:
                return  # drop the connection here
            if item is _AGAIN:  # looping: recorded times start again (a rate keeps counting)
                if self.recorded_times:
                    t0, ts0 = time.monotonic() + 1.0 / 45.0, None
                continue
            if isinstance(item, EncodedFrame):
                if item.profile_ab != cfg.profile_ab:
                    self.refusals.append(f"frames encoded as AB {item.profile_ab}, asked "
                                         f"{cfg.profile_ab}")  # fmt: skip
                    return
                due = t0 + item.t_s
                delay = due - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
                data = self._packet(due, item.payload, item.pose_hl2ss, cfg.mode)
            elif isinstance(item, AhatRecord):
                send = k % cfg.divisor == 0
                k += 1
                if not send:
                    continue
                due = None
                if self.rate_hz and self.spells:
                    tk = (k - 1) / self.rate_hz
                    if any(a <= tk < b for a, b in self.spells) and (k - 1) % step:
                        continue  # the hand tracker's 5 Hz: not captured
                if self.recorded_times:
                    ts0 = item.timestamp if ts0 is None else ts0
                    due = t0 + (item.timestamp - ts0) / 1e7
                elif self.rate_hz:
                    due = t0 + (k - 1) / self.rate_hz
                if due is not None:
                    delay = due - time.monotonic()
                    if delay > 0 and self._stop.wait(delay):
                        return
                data, encoder = self._record_packet(item, cfg, encoder, due)
            else:
                data = item
            try:
                conn.sendall(data)
            except OSError:  # the client left before the last packet
                return
            self.sent += 1
        conn.settimeout(0.1)
        while not self._stop.is_set():  # keep it open until the client leaves
            try:
                if not conn.recv(1):
                    return
            except TimeoutError:
                continue

    def _serve_from_epoch(
        self, conn: socket.socket, cfg: AhatConfiguration, records: list[TurnItem]
    ) -> None:
        """The headset's world from ``epoch`` (class docstring): the frame of now, then each at
        its time; one past its time by more than a period is dropped."""
        assert self.epoch is not None and self.rate_hz
        period = 1.0 / self.rate_hz
        encoder: AhatEncoder | None = None
        lap = round_ticks(records)
        n = max(0, math.ceil((time.monotonic() - self.epoch) / period))
        while self.loop or n < len(records):
            due = self.epoch + n * period
            delay = due - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                return
            if delay < -period:  # past its time: not captured, as the headset's sensor drops
                now_n = math.ceil((time.monotonic() - self.epoch) / period)
                self.dropped_late += max(1, now_n - n)
                n = max(n + 1, now_n)
                continue
            item = records[n % len(records)]
            n += 1
            if (n - 1) % cfg.divisor:
                continue
            if item is None:
                return
            if isinstance(item, AhatRecord):
                rounds = (n - 1) // len(records)
                if rounds and lap:  # the clock runs on: never back at the loop's start
                    item = replace(item, timestamp=item.timestamp + rounds * lap)
                data, encoder = self._record_packet(item, cfg, encoder, due)
            elif isinstance(item, bytes):
                data = item
            else:
                self.refusals.append("an epoch replays records, not encoded frames")
                return
            try:
                conn.sendall(data)
            except OSError:  # the client left
                return
            self.sent += 1

    def _record_packet(
        self,
        item: AhatRecord,
        cfg: AhatConfiguration,
        encoder: AhatEncoder | None,
        due: float | None,
    ) -> tuple[bytes, AhatEncoder | None]:
        """``item``'s packet for this connection (RAW as recorded, unless stamped live; else
        through ``encoder``, made on the first frame that needs it), and the encoder."""
        if cfg.profile_ab == VIDEO_PROFILE_RAW and not self.live:
            return item.packet(cfg.mode), encoder
        encoder = encoder or AhatEncoder(cfg)
        payload = encoder.payload(item.depth_mm, item.ab, item.sensor_ticks)
        return self._packet(due if self.live else None, payload, item.hl2ss_pose(), cfg.mode,
                            item.timestamp), encoder  # fmt: skip

    def _packet(self, due: float | None, payload: bytes, pose: NDArray[np.float32] | None,
                mode: int, timestamp: int = 0) -> bytes:  # fmt: skip
        """A packet around ``payload``: stamped ``due`` (monotonic s) when live, else
        ``timestamp``; the pose (zeros: not located) in mode 1."""
        if self.live and due is not None:
            timestamp = int(due * 1e7)
        tail = b""
        if mode == MODE_FRAMES_POSE:
            tail = (np.zeros((4, 4), "<f4") if pose is None else np.asarray(pose, "<f4")).tobytes()
        return HEADER.pack(timestamp, len(payload)) + payload + tail

    def _items(self, items: Iterable[TurnItem]) -> Iterator[TurnItem | object]:
        """The turn's items; with ``loop``, again and again (``_AGAIN`` between rounds)."""
        while True:
            yield from items
            if not self.loop:
                return
            yield _AGAIN

    def close(self) -> None:
        self._stop.set()
        self.sock.close()
        self.thread.join(timeout=5.0)

    def __enter__(self) -> Hl2ssReplayServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --- recorded records in a file ---------------------------------------------------------------


def save_records(
    path: str | Path,
    records: list[AhatRecord],
    calibration: Hl2ssAhatCalibration | None = None,
    compress: bool = True,
) -> None:
    """Write records (and the calibration) to an ``.npz``; poses as hl2ss sends them (zeros:
    not located). Deflate at level 1: AHAT frames are mostly sensor noise, which the default
    level (6) squeezes hardly more at five times the time (np.load reads either). ``compress``
    False stores them as they are: 1 MB a frame, 1.7 times the file, but written 6 times and
    read 4 times faster (a file made to be served once)."""
    poses = [np.zeros((4, 4), np.float32) if r.T_world_rig is None
             else hl2ss_matrix_from_pose(r.T_world_rig) for r in records]  # fmt: skip
    arrays = {
        "timestamp": np.array([r.timestamp for r in records], np.uint64),
        "sensor_ticks": np.array([r.sensor_ticks for r in records], np.uint64),
        "depth_mm": np.stack([np.asarray(r.depth_mm, np.uint16) for r in records]),
        "ab": np.stack([np.asarray(r.ab, np.uint16) for r in records]),
        "pose_hl2ss": np.stack(poses),
    }
    if calibration is not None:
        arrays["calibration"] = np.frombuffer(calibration.to_bytes(), np.uint8)
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(path, "w", method, compresslevel=1 if compress else None) as z:
        for name, array in arrays.items():
            with z.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, array, allow_pickle=False)


class McapTurn:
    """The AHAT frames of a device recording (``humantele devices record``) as a turn read
    lazily from the file, again for every client (a long recording is not held in memory).
    Construction checks the file (ValueError, one line: not a device recording, or no AHAT
    frame) and takes its calibration; ``problem`` says what cut it short (None: complete),
    once the reading reached the torn tail (and at once for a file without footer);
    ``on_problem(message)`` is called when a reading stops at it."""

    def __init__(self, path: str | Path, on_problem: Callable[[str], None] | None = None):
        from humantele.recording.device_file import (
            AHAT_CALIBRATION,
            AHAT_FRAME,
            DeviceRecording,
            DeviceRecordingError,
        )

        self.path, self.on_problem = Path(path), on_problem
        self._topics = {AHAT_CALIBRATION, AHAT_FRAME}
        try:
            self._rec = DeviceRecording(path)
        except DeviceRecordingError as exc:
            raise ValueError(f"hl2ss replay: {exc}") from None
        self.calibration: Hl2ssAhatCalibration | None = None
        frames = iter(self)
        first = next(frames, None)
        frames.close()
        if first is None:
            raise ValueError(f"hl2ss replay: {path} holds no AHAT frame"
                             + ("" if self.problem is None else f" ({self.problem})"))  # fmt: skip

    @property
    def problem(self) -> str | None:
        return self._rec.problem

    def __iter__(self) -> Iterator[AhatRecord]:
        from humantele.recording.device_file import AHAT_CALIBRATION

        n = 0
        for s in self._rec.samples(self._topics):
            if s.topic == AHAT_CALIBRATION:
                if self.calibration is None:
                    self.calibration = Hl2ssAhatCalibration.from_bytes(
                        bytes(s.blobs["calibration"]))  # fmt: skip
                continue
            m = s.blobs.get("pose")
            m = None if m is None else np.asarray(m, np.float32).reshape(4, 4)
            n += 1
            yield AhatRecord(int(s.fields["timestamp"]), s.blobs["depth"], s.blobs["ab"],
                             int(s.fields.get("sensor_ticks", 0)),
                             None if m is None else pose_from_hl2ss(m)[0], m)  # fmt: skip
        if self._rec.problem and self.on_problem is not None:
            self.on_problem(f"{self._rec.problem}: served its first {n} frames")


def load_mcap_records(
    path: str | Path,
) -> tuple[list[AhatRecord], Hl2ssAhatCalibration | None, str | None]:
    """All AHAT frames of a device recording in memory (short recordings, tests), its
    calibration and what cut it short (None: complete); ValueError as :class:`McapTurn`."""
    turn = McapTurn(path)
    records = list(turn)
    return records, turn.calibration, turn.problem


def load_records(path: str | Path) -> tuple[list[AhatRecord], Hl2ssAhatCalibration | None]:
    """The records and calibration :func:`save_records` wrote; ValueError naming the file."""
    try:
        with np.load(path) as z:
            poses = [pose_from_hl2ss(m)[0] for m in z["pose_hl2ss"]]
            cols = zip(
                z["timestamp"], z["depth_mm"], z["ab"], z["sensor_ticks"], poses, strict=True
            )
            records = [AhatRecord(int(ts), d, a, int(st), p) for ts, d, a, st, p in cols]
            cal = (Hl2ssAhatCalibration.from_bytes(z["calibration"].tobytes())
                   if "calibration" in z.files else None)  # fmt: skip
    except (OSError, KeyError, ValueError) as exc:
        raise ValueError(f"hl2ss replay file {path}: {exc}") from exc
    return records, cal


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="serve recorded AHAT frames as the hl2ss app does")
    ap.add_argument("file", help=".npz written by save_records, or a device recording (.mcap)")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=0, help="0: any free port (printed)")
    ap.add_argument("--loop", action="store_true", help="start again at the end (per client)")
    ap.add_argument("--epoch", type=float, default=None,
                    help="a time.monotonic() value: the headset's world runs from it (.npz "
                    "at a rate; see Hl2ssReplayServer)")  # fmt: skip
    ap.add_argument("--start-file", default=None,
                    help="the epoch shared with another replay of the same clinic: claimed "
                    "in this file at the first connection, or read from it if the other "
                    "replay was read first (humantele.runtime.shared_start)")  # fmt: skip
    ap.add_argument("--rate", type=float, default=None,
                    help="frames per second (0: unpaced; default: 45 for .npz, the recorded "
                    "times for .mcap)")  # fmt: skip
    args = ap.parse_args(argv)
    mcap = Path(args.file).suffix != ".npz"

    def say(message: str) -> None:
        print(f"hl2ss replay: {message}", file=sys.stderr, flush=True)

    records: Iterable[TurnItem]
    try:
        if not mcap:
            records, cal = load_records(args.file)
        else:
            records = turn = McapTurn(args.file, say)
            cal = turn.calibration
            if turn.problem:
                say(turn.problem)
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 1
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with Hl2ssReplayServer([records], cal, args.host, args.port, repeat=True, loop=args.loop,
                           rate_hz=(45.0 if args.rate is None and not mcap else args.rate) or None,
                           recorded_times=mcap and args.rate is None,
                           epoch=args.epoch, start_file=args.start_file) as srv:  # fmt: skip
        print(f"hl2ss replay listening on {args.host}:{srv.port}", flush=True)
        stop.wait()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

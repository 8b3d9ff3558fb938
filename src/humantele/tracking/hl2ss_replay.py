"""A replay server speaking the hl2ss AHAT protocol, strict as the hl2ss app is.

It reads each client's configuration as the app does (:func:`read_configuration`) and closes
the socket where the app would (divisor 0, bitrate 0 even for RAW, unknown profiles, mode 3);
it also closes on requests it cannot replay (a depth profile other than SAME or an AB profile
other than RAW: the app would send encoded frames), recording why in ``refusals``. Mode 2
sends the calibration (closes when it has none). Modes 0/1 send the packets of the next
"turn" in hl2ss's own layout (:func:`encode_ahat_packet`): every ``divisor``-th record, with
the rig pose in mode 1 (zeros for a record without one, as the app sends when the headset is
not located).

A turn is a list of items: an :class:`AhatRecord` (encoded for the client's mode), ``bytes``
(sent as they are: corrupt packets for tests) or None (the server drops the connection there).
Refused and calibration connections do not use up a turn; after the last turn, new clients
are closed at once (``repeat=True``: every client gets the first turn again). ``rate_hz``
paces the records as the headset would (None: as fast as the client reads).

In its own process, serving records saved with :func:`save_records`::

    python -m humantele.tracking.hl2ss_replay FILE.npz [--host H] [--port P] [--rate 45]

prints ``hl2ss replay listening on H:P`` once it listens and serves until stopped.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from humantele.geometry import Pose
from humantele.tracking.hl2ss_calibration import Hl2ssAhatCalibration
from humantele.tracking.hl2ss_protocol import (
    DEPTH_PROFILE_SAME,
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
    sensor ticks, and the rig's pose in the app's world (None: not located)."""

    timestamp: int
    depth_mm: NDArray[np.uint16]
    ab: NDArray[np.uint16]
    sensor_ticks: int = 0
    T_world_rig: Pose | None = None

    def packet(self, mode: int) -> bytes:
        pose = None
        if mode == MODE_FRAMES_POSE:
            pose = (np.zeros((4, 4), np.float32) if self.T_world_rig is None
                    else hl2ss_matrix_from_pose(self.T_world_rig))  # fmt: skip
        return encode_ahat_packet(self.timestamp, self.depth_mm, self.ab, self.sensor_ticks, pose)


TurnItem = AhatRecord | bytes | None


class Hl2ssReplayServer:
    """Serves ``turns`` (one per accepted stream connection) on ``host``:``port`` (0: any free
    port, see ``port``) from a background thread; ``close()`` stops it."""

    def __init__(
        self,
        turns: list[list[TurnItem]],
        calibration: Hl2ssAhatCalibration | None = None,
        host: str = "127.0.0.1",
        port: int = 0,
        repeat: bool = False,
        rate_hz: float | None = None,
    ):
        self.turns = list(turns)
        self.repeat = repeat
        self.rate_hz = rate_hz
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
        if cfg.profile_z != DEPTH_PROFILE_SAME or cfg.profile_ab != VIDEO_PROFILE_RAW:
            self.refusals.append(f"replay has RAW frames only (asked depth {cfg.profile_z}, "
                                 f"AB {cfg.profile_ab})")  # fmt: skip
            return
        if not self.turns:
            self.refusals.append("no turn left")
            return
        self.configs.append(cfg)
        items = self.turns[0] if self.repeat else self.turns.pop(0)
        k = 0
        t0 = time.monotonic()
        for item in items:
            if item is None:
                return  # drop the connection here
            if isinstance(item, AhatRecord):
                send = k % cfg.divisor == 0
                k += 1
                if not send:
                    continue
                if self.rate_hz:
                    delay = t0 + (k - 1) / self.rate_hz - time.monotonic()
                    if delay > 0 and self._stop.wait(delay):
                        return
                data = item.packet(cfg.mode)
            else:
                data = item
            try:
                conn.sendall(data)
            except OSError:  # the client left before the last packet
                return
        conn.settimeout(0.1)
        while not self._stop.is_set():  # keep it open until the client leaves
            try:
                if not conn.recv(1):
                    return
            except TimeoutError:
                continue

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
    path: str | Path, records: list[AhatRecord], calibration: Hl2ssAhatCalibration | None = None
) -> None:
    """Write records (and the calibration) to a compressed ``.npz``; poses as hl2ss sends them
    (zeros: not located)."""
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
    np.savez_compressed(path, **arrays)


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
    ap.add_argument("file", help=".npz written by save_records")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=0, help="0: any free port (printed)")
    ap.add_argument("--rate", type=float, default=45.0, help="frames per second (0: unpaced)")
    args = ap.parse_args(argv)
    try:
        records, cal = load_records(args.file)
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 1
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with Hl2ssReplayServer([records], cal, args.host, args.port, repeat=True,
                           rate_hz=args.rate or None) as srv:  # fmt: skip
        print(f"hl2ss replay listening on {args.host}:{srv.port}", flush=True)
        stop.wait()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

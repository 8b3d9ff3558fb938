"""The daemon's handle on the 1 kHz servo process (:mod:`humantele.haptics.servo_child`).

The servo runs in its own process (``multiprocessing`` spawn) so the daemon's Python threads
never hold its GIL. The daemon talks to it through three seqlocked shared-memory blocks
(:mod:`humantele.haptics.shm`, layout in :mod:`humantele.haptics.servo_layout`): commands
(model, registration, stop) in, the latest sample and the statistics out. Frames and safety:
:mod:`humantele.haptics.renderer`.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing as mp
import os
import threading
from typing import Any

import numpy as np

from humantele.geometry import Pose
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.haptics.servo_child import servo_main
from humantele.haptics.servo_config import ServoConfig
from humantele.haptics.servo_layout import (
    C_MODEL,
    C_MODEL_GEN,
    C_MODEL_ON,
    C_REG_GEN,
    C_REG_ON,
    C_REG_P,
    C_REG_Q,
    C_REG_S,
    C_STOP,
    CMD_LEN,
    S_BUTTONS,
    S_DEPTH,
    S_F,
    S_FAULT,
    S_FD,
    S_P,
    S_PD,
    S_Q,
    S_QD,
    S_RAMP,
    S_T,
    S_TICK,
    S_V,
    SAMPLE_LEN,
    STAT_FIELDS,
    STATS_LEN,
    ServoError,
    ServoSample,
    ServoStats,
)
from humantele.haptics.shm import SeqlockArray
from humantele.runtime.child import spawn, stop_process


class ServoProcess:
    """The servo loop in its own process; the daemon's handle on it.

    ``start()`` returns once the device is open and the loop runs (ServoError otherwise; a
    child that exits is seen at once, one that is alive but slow is waited for ``timeout_s``,
    120 s: its imports alone passed 30 s at load 20);
    ``set_model``/``set_registration`` take effect atomically at the next tick (with a force
    crossfade); ``latest()``/``stats()`` never block on the loop. Use as a context manager.
    """

    def __init__(self, config: ServoConfig | None = None, model: Ellipsoid | None = None) -> None:
        self.config = config or ServoConfig()
        self._cmd_values = np.zeros(CMD_LEN)
        self._last_sample: ServoSample | None = None
        self._last_stats: ServoStats | None = None
        self._lock = threading.Lock()
        self._proc: mp.process.BaseProcess | None = None
        self._blocks: list[SeqlockArray] = []
        self.realtime = False
        self.exitcode: int | None = None  # of the last process, once stopped
        self.set_model(model)

    # -- lifecycle --------------------------------------------------------------------------
    def start(self, timeout_s: float = 120.0) -> None:
        if self._proc is not None:
            raise ServoError("servo process already started")
        self._cmd = SeqlockArray(CMD_LEN)
        self._out = SeqlockArray(SAMPLE_LEN)
        self._st = SeqlockArray(STATS_LEN)
        self._blocks = [self._cmd, self._out, self._st]
        with self._lock:
            self._cmd.write(self._cmd_values)
        parent_conn, child_conn = mp.get_context("spawn").Pipe(duplex=False)
        names = (self._cmd.name, self._out.name, self._st.name)
        try:  # the servo checks its parent in its loop (runtime.child: watch=False)
            args = (self.config.model_dump_json(), names, os.getpid(), child_conn)
            self._proc = spawn(servo_main, args, name="humantele-servo", watch=False)
        except BaseException as exc:
            self._proc = None
            parent_conn.close()
            self.stop()  # frees the shared memory
            if isinstance(exc, Exception):
                raise ServoError(f"servo did not start: {type(exc).__name__}: {exc}") from exc
            raise
        child_conn.close()
        msg = None
        if parent_conn.poll(timeout_s):
            try:
                msg = parent_conn.recv()
            except EOFError:
                msg = None
        parent_conn.close()
        if msg is None or msg[0] != "ready":
            reason = msg[1] if msg else "the servo process exited or did not answer in time"
            self.stop()
            raise ServoError(f"servo did not start: {reason}")
        self.realtime = bool(msg[1]["realtime"])

    def stop(self, timeout_s: float = 3.0) -> None:
        """Stop the loop (force zeroed by the servo process) and free the shared memory."""
        proc = self._proc
        try:
            if proc is not None:
                with self._lock:
                    self._cmd_values[C_STOP] = 1.0
                    self._cmd.write(self._cmd_values)
                # SIGTERM next: the servo zeroes the force and exits
                self.exitcode = stop_process(proc, timeout_s=timeout_s)
                self._proc = None
                with contextlib.suppress(ServoError):
                    self._final_stats = self._read_stats()
        finally:  # the shared memory is freed whatever happened above
            blocks, self._blocks = self._blocks, []  # readers on other threads see none now
            for b in blocks:
                with contextlib.suppress(OSError):
                    b.close()
                with contextlib.suppress(OSError):
                    b.unlink()
            self._cmd_values[C_STOP] = 0.0

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    @property
    def returncode(self) -> int | None:
        """The servo process's exit code once it ended (None while it runs or before start)."""
        return self._proc.exitcode if self._proc is not None else self.exitcode

    def __enter__(self) -> ServoProcess:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- commands --------------------------------------------------------------------------
    def set_model(self, model: Ellipsoid | None) -> None:
        """Swap the patient model (None = free space) atomically, with a force crossfade."""
        arr = None if model is None else np.asarray(model.as_array(), dtype=float)
        if arr is not None and (arr.shape != (7,) or not np.all(np.isfinite(arr))):
            raise ValueError("model.as_array() must be 7 finite floats")
        with self._lock:
            v = self._cmd_values
            v[C_MODEL_GEN] += 1.0
            v[C_MODEL_ON] = 0.0 if arr is None else 1.0
            v[C_MODEL : C_MODEL + 7] = 0.0 if arr is None else arr
            self._push()

    def set_registration(self, T_patient_device: Pose | None, scale: float | None = None) -> None:
        """Set ``T_patient_device`` (None: automatic, above the model) and motion scaling."""
        s = self.config.motion_scale if scale is None else float(scale)
        if not (math.isfinite(s) and 0.0 < s <= 10.0):
            raise ValueError(f"motion scale must be in (0, 10], got {scale!r}")
        with self._lock:
            v = self._cmd_values
            v[C_REG_GEN] += 1.0
            v[C_REG_ON] = 0.0 if T_patient_device is None else 1.0
            if T_patient_device is not None:
                v[C_REG_P : C_REG_P + 3] = T_patient_device.position
                v[C_REG_Q : C_REG_Q + 4] = T_patient_device.quaternion
            v[C_REG_S] = s
            self._push()

    def _push(self) -> None:
        if self._blocks:
            self._cmd.write(self._cmd_values)

    # -- state -----------------------------------------------------------------------------
    def latest(self) -> ServoSample | None:
        """The latest tick's sample, or None before the first tick. If the servo died half-way
        through a write, the last sample read (its ``t`` shows its age)."""
        if not self._blocks:
            return None
        try:
            a = self._out.read()
        except TimeoutError:
            return self._last_sample
        if a[S_TICK] == 0:
            return None
        self._last_sample = ServoSample(
            t=float(a[S_T]),
            T_device_stylus=Pose(a[S_PD : S_PD + 3], a[S_QD : S_QD + 4]),
            T_patient_stylus=Pose(a[S_P : S_P + 3], a[S_Q : S_Q + 4]),
            velocity=tuple(float(x) for x in a[S_V : S_V + 3]),  # type: ignore[arg-type]
            force=tuple(float(x) for x in a[S_F : S_F + 3]),  # type: ignore[arg-type]
            force_device=tuple(float(x) for x in a[S_FD : S_FD + 3]),  # type: ignore[arg-type]
            depth=float(a[S_DEPTH]),
            buttons=int(a[S_BUTTONS]),
            fault_flags=int(a[S_FAULT]),
            tick=int(a[S_TICK]),
            ramp=float(a[S_RAMP]),
        )
        return self._last_sample

    def _read_stats(self) -> ServoStats:
        try:
            a = self._st.read()
        except TimeoutError:  # the servo died half-way through a write: the last we read
            if self._last_stats is None:
                raise ServoError("servo statistics unreadable") from None
            return self._last_stats
        vals: dict[str, Any] = {}
        for k, x in zip(STAT_FIELDS, a, strict=True):
            ftype = ServoStats.__dataclass_fields__[k].type
            vals[k] = bool(x) if ftype == "bool" else int(x) if ftype == "int" else float(x)
        self._last_stats = ServoStats(**vals)
        return self._last_stats

    def stats(self) -> ServoStats:
        """Loop statistics (updated 4 times a second, and at stop)."""
        if not self._blocks:
            final = getattr(self, "_final_stats", None)
            if final is None:
                raise ServoError("servo process not started")
            return final
        return self._read_stats()

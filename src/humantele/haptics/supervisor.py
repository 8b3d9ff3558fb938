"""The supervised servo: the expert's 1 kHz servo process kept running.

:class:`SupervisedServo` holds the current :class:`~humantele.haptics.servo.ServoProcess` and
what it should render (the model, the registration): a servo process that dies is noticed on
the daemon's tick and replaced after a back-off (``first_s``, doubled up to ``MAX_BACKOFF_S``;
:class:`~humantele.runtime.child.Restarter`), started off the event loop (spawning it and
opening the device take 0.5-2 s, up to the 30 s start timeout, while the link's heartbeats,
the console and the follower's state go on), and given the model and registration of the
moment it is swapped in. While it is down, :attr:`down` says why: the state shows it as a
fault, never as a silent zero force. :meth:`stop` (the daemon's end) lets a restart in flight
finish and stops what it started.
"""

from __future__ import annotations

import asyncio
import logging

from humantele.geometry import Pose
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.haptics.servo import ServoProcess
from humantele.haptics.servo_config import ServoConfig
from humantele.haptics.servo_layout import ServoError, ServoSample, ServoStats
from humantele.runtime.child import Restarter
from humantele.runtime.stats import process_cpu_percent

log = logging.getLogger(__name__)

MAX_BACKOFF_S = 30.0  # s, the longest wait between two restarts of a servo that keeps dying


class SupervisedServo:
    """The servo process the expert renders with, restarted when it dies (module docstring).

    The handle's reads (:meth:`latest`, :meth:`stats`, :attr:`alive`, :attr:`pid`) are those
    of the current process; :meth:`set_model` and :meth:`set_registration` are kept and given
    to each new process."""

    def __init__(self, config: ServoConfig, first_s: float = 2.0) -> None:
        self.config = config
        self.process = ServoProcess(config)
        self._model: Ellipsoid | None = None
        self._registration: tuple[Pose | None, float | None] | None = None
        self.stopped = False  # stopped by the daemon (its end)
        self._cpu_last: float | None = None
        self.restarter = Restarter(
            "servo", self._replace, first_s=first_s, max_s=max(first_s, MAX_BACKOFF_S)
        )

    # --- the current process ------------------------------------------------------------------

    def start(self) -> None:
        """Start the first process (blocks; ServoError with the reason)."""
        self.process.start()

    @property
    def alive(self) -> bool:
        return self.process.alive

    @property
    def pid(self) -> int | None:
        return self.process.pid

    @property
    def returncode(self) -> int | None:
        return self.process.returncode

    def latest(self) -> ServoSample | None:
        return self.process.latest()

    def stats(self) -> ServoStats:
        return self.process.stats()

    def set_model(self, model: Ellipsoid | None) -> None:
        """Render ``model`` (None: free space), now and in every restarted process."""
        self._model = model
        self.process.set_model(model)

    def set_registration(self, T_patient_device: Pose | None, scale: float | None = None) -> None:
        self._registration = (T_patient_device, scale)
        self.process.set_registration(T_patient_device, scale)

    # --- supervision --------------------------------------------------------------------------

    @property
    def down(self) -> str:
        """Why the servo is not running ("" while it runs)."""
        return self.restarter.down

    @down.setter
    def down(self, reason: str) -> None:
        self.restarter.down = reason

    @property
    def cannot_run(self) -> str:
        """Why the servo cannot run (its last start failed: a driver, a device), or "" (it
        runs, or died and its restart is pending or under way)."""
        r = self.restarter
        return r.down if r.failed_start or r.gave_up else ""

    @property
    def restarts(self) -> int:
        return self.restarter.restarts

    @property
    def restarting(self) -> bool:
        return self.restarter.restarting

    def check(self, t: float) -> None:
        """On each tick (``t``: the daemon's clock, s): a dead process is restarted when due."""
        if not self.stopped:
            self.restarter.check(t, self.process.alive, self.process.returncode)

    async def _replace(self) -> None:
        """The Restarter's start: the dead process stopped (its shared memory freed) and a new
        one started, off the loop; it gets the model and registration of now."""
        loop = asyncio.get_running_loop()
        new = ServoProcess(self.config, self._model)
        await loop.run_in_executor(None, self.process.stop)
        await loop.run_in_executor(None, new.start)  # ServoError: the Restarter keeps why
        if self.stopped:  # the daemon ended while this one started
            await loop.run_in_executor(None, new.stop)
            return
        self.process = new
        new.set_model(self._model)  # it may have changed meanwhile
        if self._registration is not None:
            new.set_registration(*self._registration)

    def state(self, latest: ServoSample | None) -> str:
        """``running``, ``fault: <names>`` (force zeroed by the loop; with "device lost,
        re-initialising" while the device is lost and being initialised again with back-off,
        see :meth:`humantele.haptics.devices.touchx.TouchX._recover`), ``down: <reason>``,
        ``starting``, or ``stopped`` (by the daemon, at its end)."""
        if self.stopped and not self.down:
            return "stopped"
        if self.down or not self.process.alive:
            return f"down: {self.down or 'servo process not running'}"
        if latest is not None and latest.fault:
            try:
                lost = self.process.stats().device_lost
            except ServoError:
                lost = 0
            return f"fault: {latest.fault}" + ("; device lost, re-initialising" if lost else "")
        return "running" if latest is not None else "starting"

    def cpu_percent(self) -> float | None:
        """CPU use (% of one core) of the current servo process since it started."""
        cpu = process_cpu_percent(self.process.pid)
        if cpu is not None:
            self._cpu_last = cpu
        return self._cpu_last

    async def stop(self) -> None:
        """The daemon's end: no more restarts, one in flight finished, the process stopped."""
        self.cpu_percent()
        self.stopped = True
        await self.restarter.close()
        self.process.stop()

    def stop_now(self) -> None:
        """Stop the current process (blocking; no restarter involved: tests, errors)."""
        self.stopped = True
        self.restarter.closed = True
        self.process.stop()

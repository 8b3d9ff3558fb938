"""What the servo process and the daemon share: the tick's sample, the loop statistics, and
the layout of the three shared-memory blocks (commands in; sample and statistics out)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from humantele.geometry import Pose
from humantele.haptics.renderer import FAULT_NAMES


@dataclass(frozen=True)
class ServoSample:
    """The latest tick. ``t`` monotonic s; ``T_device_stylus``: the stylus as the device read
    it (m); ``T_patient_stylus``: the same stylus in the patient frame the force law used
    (registration and motion scale applied); ``velocity`` m/s and ``force`` N in the patient
    frame (``force_device``: what went to the device, device frame); ``depth`` m
    (> 0 in contact); ``fault`` names of the active faults, '' when none."""

    t: float
    T_device_stylus: Pose
    T_patient_stylus: Pose
    velocity: tuple[float, float, float]
    force: tuple[float, float, float]
    force_device: tuple[float, float, float]
    depth: float
    buttons: int
    fault_flags: int
    tick: int
    ramp: float

    @property
    def fault(self) -> str:
        return ",".join(name for bit, name in FAULT_NAMES.items() if self.fault_flags & bit)


@dataclass(frozen=True)
class ServoStats:
    """Loop statistics since start. Periods are between tick starts (us); ``overruns``: periods
    over 1.5 T (a tick slipped); ``periods_over_2ms``: periods over 2 T (2 ms at
    the 1 kHz the figure is named for);
    ``late_ticks``: later than late_after_s (fault)."""

    ticks: int
    elapsed_s: float
    rate_hz: float
    period_p50_us: float
    period_p99_us: float
    period_max_us: float
    overruns: int
    periods_over_2ms: int
    late_ticks: int
    stale_ticks: int
    device_errors: int
    bad_data: int
    fault_episodes: int
    nonfinite_forces: int
    clamped_forces: int
    realtime: bool
    models_refused: int = 0  # models/registrations refused on arrival (the last good kept)
    tick_errors: int = 0  # ticks that raised (force zeroed, the model dropped)
    # the SCHED_FIFO priority of the device's own servo thread (the Touch X's HD scheduler
    # thread; 0: normal priority; -1: the device has no thread of its own)
    device_thread_fifo: int = -1
    # the device lost (a scheduler error: unplugged, its servo loop stalled) and being
    # re-initialised with back-off (1), or not (0); the re-initialisations so far
    device_lost: int = 0
    device_reinits: int = 0
    # why the overruns ran long (haptics.loop_counts.LongPeriods): the tick before worked over
    # T/2, the sleep woke over T/2 late, or neither; the longest tick's work (us); the spin
    # before each deadline now (us); the loop thread's page faults and involuntary context
    # switches and the process's garbage collections while the loop ran
    overruns_work: int = 0
    overruns_wake: int = 0
    overruns_other: int = 0
    work_max_us: float = 0.0
    spin_us: float = 0.0
    minor_faults: int = 0
    major_faults: int = 0
    involuntary_switches: int = 0
    gc_collections: int = 0

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


# ------------------------------------------------------------------------------- shared layout
# Commands (daemon -> servo).
C_MODEL_GEN, C_MODEL_ON, C_MODEL = 0, 1, 2  # model: 7 floats (Ellipsoid.as_array)
C_REG_GEN, C_REG_ON, C_REG_P, C_REG_Q, C_REG_S = 9, 10, 11, 14, 18
C_STOP = 19
CMD_LEN = 20
# Sample (servo -> daemon), written every tick. S_P, S_Q: patient frame; S_PD, S_QD: device.
S_T, S_P, S_Q, S_V, S_F, S_FD, S_DEPTH, S_BUTTONS, S_FAULT, S_TICK, S_RAMP, S_PD, S_QD = (
    0, 1, 4, 8, 11, 14, 17, 18, 19, 20, 21, 22, 25)  # fmt: skip
SAMPLE_LEN = 29
STAT_FIELDS = [f for f in ServoStats.__dataclass_fields__]
STATS_LEN = len(STAT_FIELDS)


class ServoError(RuntimeError):
    """The servo process could not start (the message carries the child's reason)."""

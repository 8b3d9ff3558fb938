"""The servo process: the 1 kHz loop on the device, fed and read through shared memory.

It asks for SCHED_FIFO and a CPU before it opens the device (falls back, logged once, when
refused), so a thread the device starts can inherit them; the Touch X's HD servo thread also
sets its own policy from inside (``TouchX.thread_priority``). A device with its own
servo clock (``wait_tick``: the Touch X, whose OpenHaptics scheduler calls a Python callback at
1 kHz) drives the loop: it blocks in ``wait_tick`` (the GIL free, so the device's callback,
which needs the GIL, never waits on this thread) and renders right after each device tick; the
switch interval is cut to ``GIL_SWITCH_S`` so any other Python thread hands the GIL over
quickly. Otherwise it sleeps to a deadline and spins the last stretch: as long as the sleep's
recent overshoot needs (:class:`SpinBudget`, at most ``spin_s``). Each tick is a
:class:`~humantele.haptics.renderer.ForceRenderer` tick. It reads commands (model,
registration, stop) and writes the latest sample and the statistics
(:mod:`humantele.haptics.servo_layout`); it never waits on the daemon. SIGTERM, the stop
command or the parent's death end the loop with the force zeroed; SIGINT is ignored (a
terminal's Ctrl-C reaches the whole process group and the daemon stops the servo itself, which
would otherwise see it die and restart it). A model, registration or tick that fails is refused
and counted (:func:`apply_commands`, ``ForceRenderer.safe_tick``): the loop goes on.
"""

from __future__ import annotations

import gc
import logging
import math
import os
import signal
import sys
import time

import numpy as np

from humantele.geometry import Pose
from humantele.haptics.devices import DeviceError, make_device
from humantele.haptics.ellipsoid import Ellipsoid
from humantele.haptics.loop_counts import LongPeriods, ThreadCounts
from humantele.haptics.renderer import (
    FAULT_DEVICE,
    FAULT_LATE,
    MAX_REGISTRATION_M,
    ForceRenderer,
)
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
)
from humantele.haptics.shm import SeqlockArray
from humantele.runtime.child import Priority, set_priority
from humantele.runtime.cpu_latency import hold_cpu_latency

log = logging.getLogger(__name__)

GIL_SWITCH_S = 0.0002  # s, the servo process's GIL switch interval with a device-driven loop


class SpinBudget:
    """How long to spin before a deadline (s): the sleep's recent overshoot, its ``q`` quantile
    (p99.5), plus ``margin_s``, within [``min_s``, ``max_s``].

    A sleep wakes late by the timer's slack and the scheduler's latency: ~30 us p99 at
    SCHED_FIFO here, more at normal priority or under load. Spinning ``max_s`` (``spin_s``,
    200 us) every tick costs a fifth of a core; spinning what the overshoot needs keeps as many
    ticks on time for less (``humantele bench loop``: the servo at 15 % of a core, not 23 %,
    the p99 period the same). The quantile is tracked with O(1) work a tick (a stochastic
    quantile: up ``q * step_s`` on an overshoot above it, down ``(1 - q) * step_s`` otherwise:
    it settles where a fraction ``1 - q`` of the overshoots is above it, and climbs 100 us in
    25 ms when the machine gets slower). It starts at ``max_s``: the loop starts as it did with
    a fixed spin.
    """

    def __init__(
        self,
        max_s: float,
        min_s: float = 20e-6,
        margin_s: float = 30e-6,
        step_s: float = 4e-6,
        q: float = 0.995,
    ) -> None:
        self.max_s, self.min_s, self.margin_s = max_s, min(min_s, max_s), margin_s
        self.up, self.down = q * step_s, (1.0 - q) * step_s
        self.quantile_s = max_s  # the overshoot's estimated q quantile (s)
        self.spin_s = max_s
        self.late_s = 0.0  # how late the last wait's sleep woke (s; 0: it did not sleep)

    def overshoot(self, late_s: float) -> None:
        """A sleep woke ``late_s`` after the time it was asked to: update the spin."""
        q = self.quantile_s
        self.quantile_s = max(0.0, q + (self.up if late_s > q else -self.down))
        self.spin_s = min(self.max_s, max(self.min_s, self.quantile_s + self.margin_s))

    def wait_until(self, deadline: float) -> None:
        """Sleep until ``spin_s`` before ``deadline`` (``time.monotonic()``, s), learn how late
        the sleep woke, then spin to the deadline."""
        clock = time.monotonic
        wake_t = deadline - self.spin_s
        delay = wake_t - clock()
        self.late_s = 0.0
        if delay > 0.0:
            time.sleep(delay)
            self.late_s = clock() - wake_t
            self.overshoot(self.late_s)
        while clock() < deadline:
            pass


class PeriodTiming:
    """Period statistics with O(1) work per tick: 1 us bins, and 100 us bins over them so that
    a percentile looks at 200 + 100 bins, not 20,000. (It summed all 20,000 bins, twice,
    allocating 160 kB each time: 0.7-4 ms and ~90 page faults in the tick that wrote the
    statistics, 4 times a second, each a long period of the servo's own; ``humantele bench
    loop`` counts them as 'work'.) The bins are touched once here, before the loop: no page
    fault on a bin's first use."""

    BINS = 20000
    COARSE = 100  # fine bins per coarse bin

    def __init__(self, period: float) -> None:
        self.period = period
        self.hist = np.zeros(self.BINS, dtype=np.int64)
        self.coarse = np.zeros(self.BINS // self.COARSE, dtype=np.int64)
        self.hist.fill(0)  # touch every page now (np.zeros maps them lazily)
        self.coarse.fill(0)
        self.n_periods = 0
        self.min_us = float("inf")
        self.max_us = 0.0
        self.max_at = 0
        self.ticks = 0
        self.overruns = 0
        self.t_first = None
        self.t_last = None

    def add(self, t: float) -> None:
        if self.t_last is not None:
            p_us = (t - self.t_last) * 1e6
            i = min(int(p_us), self.BINS - 1)
            self.hist[i] += 1
            self.coarse[i // self.COARSE] += 1
            self.n_periods += 1
            self.min_us = min(self.min_us, p_us)
            if p_us > self.max_us:
                self.max_us = p_us
                self.max_at = self.ticks
            if p_us > 1.5e6 * self.period:
                self.overruns += 1
        else:
            self.t_first = t
        self.t_last = t
        self.ticks += 1

    def count_over(self, seconds: float) -> int:
        """Periods longer than ``seconds`` (to the 1 us bin)."""
        i = min(int(seconds * 1e6), self.BINS)
        j = -(-i // self.COARSE)  # the first coarse bin wholly above i
        return int(self.hist[i : j * self.COARSE].sum() + self.coarse[j:].sum())

    def percentile(self, q: float) -> float:
        """The ``q`` quantile of the periods, us: a bin's middle, kept within [min, max]."""
        total = self.n_periods
        if total == 0:
            return 0.0
        want = q * total
        csum = np.cumsum(self.coarse)
        k = min(int(np.searchsorted(csum, want)), len(csum) - 1)
        before = int(csum[k - 1]) if k > 0 else 0
        fine = np.cumsum(self.hist[k * self.COARSE : (k + 1) * self.COARSE])
        idx = k * self.COARSE + min(int(np.searchsorted(fine, want - before)), self.COARSE - 1)
        return min(max(idx + 0.5, self.min_us), self.max_us)

    def rate(self) -> float:
        if self.ticks < 2:
            return 0.0
        return (self.ticks - 1) / (self.t_last - self.t_first)


def try_realtime(config: ServoConfig) -> bool:
    """SCHED_FIFO at ``realtime_priority`` (the first of :data:`humantele.runtime.child.
    PRIORITY`), the CPU affinity, 1 ns timer slack, the CPUs' wake-up latency request
    (``cpu_latency_us``, :mod:`humantele.runtime.cpu_latency`); True when the real-time policy
    was had."""
    ok = False
    if config.cpu_latency_us is not None:
        hold_cpu_latency(config.cpu_latency_us)
    if config.realtime_priority > 0:
        got = set_priority(Priority(fifo=config.realtime_priority))
        ok = "refused" not in got
        if not ok:
            log.warning("servo: SCHED_FIFO refused (%s); running with normal priority", got)
    if config.cpu_affinity:
        try:
            os.sched_setaffinity(0, config.cpu_affinity)
        except (OSError, ValueError) as exc:
            log.warning("servo: CPU affinity %s refused (%s)", config.cpu_affinity, exc)
    try:  # 1 ns timer slack: sleeps end on time (Linux prctl PR_SET_TIMERSLACK)
        import ctypes

        ctypes.CDLL(None).prctl(29, 1, 0, 0, 0)
    except (OSError, AttributeError):
        pass
    return ok


def servo_main(config_json: str, names: tuple[str, str, str], parent_pid: int, conn) -> None:
    """Entry point of the servo process."""
    stop = {"flag": False}

    def _on_signal(signum, frame):  # noqa: ARG001
        stop["flag"] = True

    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the daemon stops us
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    cmd = SeqlockArray(CMD_LEN, names[0])
    out = SeqlockArray(SAMPLE_LEN, names[1])
    st = SeqlockArray(STATS_LEN, names[2])
    device = None
    try:
        config = ServoConfig.model_validate_json(config_json)
        device = make_device(config.device)
        # Real-time before the device opens: a thread the device starts (the Touch X's HD
        # servo thread) inherits the policy and the CPUs where its library lets it; the Touch
        # X backend also sets its thread's policy from inside (TouchX.thread_priority), since
        # OpenHaptics' driver may not let it inherit.
        realtime = try_realtime(config)
        if hasattr(device, "thread_priority"):
            device.thread_priority = config.realtime_priority
        # Collect and freeze what the imports made before the device's own servo thread starts:
        # a full collection holds the GIL for tens of ms, during which a device callback that
        # needs it (the Touch X's) would miss its slot. _run's collection is then short.
        gc.collect()
        gc.freeze()
        device.open()
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises it
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        for b in (cmd, out, st):
            b.close()
        return
    conn.send(("ready", {"realtime": realtime, "pid": os.getpid()}))
    try:
        _run(config, device, cmd, out, st, stop, parent_pid, realtime)
    finally:
        try:
            device.command_force((0.0, 0.0, 0.0))
        except Exception:  # noqa: BLE001 - closing anyway
            pass
        device.close()
        last = out.read()  # the daemon sees the zeroed force of the stopped loop
        last[S_F : S_F + 3] = 0.0
        last[S_FD : S_FD + 3] = 0.0
        last[S_RAMP] = 0.0
        out.write(last)
        for b in (cmd, out, st):
            b.close()


def _run(config, device, cmd, out, st, stop, parent_pid, realtime) -> None:
    """The loop until ``stop["flag"]``, the stop command or the parent's death. With a device
    that has ``wait_tick`` the device's ticks pace it (see the module docstring); otherwise its
    own deadline clock does."""
    r = ForceRenderer(config)
    period = 1.0 / config.rate_hz
    timing = PeriodTiming(period)
    model_gen = reg_gen = -1.0
    spin = SpinBudget(config.spin_s)
    sample = np.zeros(SAMPLE_LEN)
    wait_tick = getattr(device, "wait_tick", None)
    seen = 0
    switch = sys.getswitchinterval()
    if wait_tick is not None:
        sys.setswitchinterval(min(switch, GIL_SWITCH_S))
    gc.collect()
    gc.disable()  # the loop makes no reference cycles; a GC pause would be a late tick
    causes = LongPeriods(period)
    counts = ThreadCounts()
    clock = time.monotonic
    next_t = clock() + period
    next_stats = next_t
    last_now = work_s = 0.0
    # Until the first consistent read: no stop, and generations equal to "nothing applied yet"
    # (the renderer starts with no model: zero force).
    c = np.zeros(CMD_LEN)
    c[C_MODEL_GEN] = c[C_REG_GEN] = -1.0
    try:
        while not stop["flag"]:
            if wait_tick is not None:
                # The device's clock: block (GIL free) until its next tick. No tick within
                # stale_after_s: go on with the old state, which the renderer finds stale.
                seen = wait_tick(seen, config.stale_after_s)
                now = clock()
                timing.add(now)
                late_s = 0.0
                flags = 0  # lateness against the device's tick is the renderer's stale check
            else:
                spin.wait_until(next_t)  # sleep, then spin the last stretch
                now = clock()
                timing.add(now)
                late_s = spin.late_s
                flags = FAULT_LATE if now - next_t > config.late_after_s else 0
            if last_now:
                causes.add(now - last_now, work_s, late_s)
            last_now = now
            if flags:
                r.fault(flags, now)
            # Commands from the daemon; mid-write (the daemon preempted): last tick's copy.
            c_new = cmd.try_read()
            if c_new is not None:
                c = c_new
            if c[C_STOP] != 0.0 or os.getppid() != parent_pid:
                break
            if c[C_MODEL_GEN] != model_gen or c[C_REG_GEN] != reg_gen:
                apply_commands(r, c, now)
                model_gen, reg_gen = c[C_MODEL_GEN], c[C_REG_GEN]
            # Device, force, device.
            try:
                state = device.read()
            except DeviceError:
                state = None
            f = r.safe_tick(state, now, flags)
            try:
                device.command_force(f)
            except DeviceError:
                r.fault(FAULT_DEVICE, now)
            pp, qp, vp, fp, fd, depth, buttons, fflags, ramp, p_dev, q_dev = r.sample
            sample[S_T] = now
            sample[S_P : S_P + 3] = pp
            sample[S_Q : S_Q + 4] = qp
            sample[S_V : S_V + 3] = vp
            sample[S_F : S_F + 3] = fp
            sample[S_FD : S_FD + 3] = fd
            sample[S_DEPTH] = depth
            sample[S_BUTTONS] = buttons
            sample[S_FAULT] = fflags
            sample[S_TICK] = timing.ticks
            sample[S_RAMP] = ramp
            sample[S_PD : S_PD + 3] = p_dev
            sample[S_QD : S_QD + 4] = q_dev
            out.write(sample)
            if now >= next_stats:
                st.write(_stats_row(timing, r, realtime, device, causes, counts, spin))
                next_stats = now + 0.25
            # Next deadline; after a long stall restart the schedule instead of bursting.
            next_t += period
            end = clock()
            work_s = end - now
            if end > next_t + period:
                next_t = end + period
    finally:
        st.write(_stats_row(timing, r, realtime, device, causes, counts, spin))
        if timing.overruns:  # why, in the daemon's log (humantele bench loop: against the bare)
            n = counts.counts()
            log.warning(
                "servo: %d periods over %.1f ms in %.0f s: the tick before worked over %.1f ms "
                "%d, the sleep woke over %.1f ms late %d, neither %d; %d page faults, %d "
                "involuntary switches, %d GC", timing.overruns, 1.5e3 * period,
                timing.t_last - timing.t_first if timing.ticks > 1 else 0.0, 0.5e3 * period,
                causes.work, 0.5e3 * period, causes.wake, causes.other,
                n["minor_faults"] + n["major_faults"], n["involuntary_switches"],
                n["gc_collections"],
            )  # fmt: skip
        counts.close()
        gc.enable()
        sys.setswitchinterval(switch)


def apply_commands(r: ForceRenderer, c: np.ndarray, now: float) -> None:
    """Give ``r`` the model and registration of the command block ``c``; never raises. A model
    that is not a body (``Ellipsoid.problem``), a registration that is not a rigid pose within
    reach, or a bad scale is refused (counted, logged) and the last good value kept."""
    model = None
    if c[C_MODEL_ON]:
        try:
            model = Ellipsoid.from_array(c[C_MODEL : C_MODEL + 7])
            why = model.problem()
        except Exception as exc:  # noqa: BLE001 - ValueError expected; anything is refused
            why = str(exc)
        if why is not None:
            r.refuse(f"model refused: {why}")
            model = r.model
    reg = None
    if c[C_REG_ON]:
        p, q = c[C_REG_P : C_REG_P + 3], c[C_REG_Q : C_REG_Q + 4]
        n = float(np.sqrt(np.sum(q * q))) if np.all(np.isfinite(q)) else 0.0
        if np.all(np.isfinite(p)) and np.all(np.abs(p) <= MAX_REGISTRATION_M) and 1e-6 < n < 1e6:
            reg = Pose(p, q / n)
        else:
            r.refuse(f"registration refused: position {p.tolist()} m, quaternion {q.tolist()}")
            reg = r.registration
    scale = float(c[C_REG_S]) or r.config.motion_scale
    if not (math.isfinite(scale) and 0.0 < scale <= 10.0):
        r.refuse(f"motion scale {scale!r} refused")
        scale = r.scale
    try:
        r.configure(model, reg, scale, now)
    except Exception as exc:  # noqa: BLE001 - keep what ran
        r.refuse(f"configuration refused: {type(exc).__name__}: {exc}")


def _stats_row(
    timing: PeriodTiming,
    r: ForceRenderer,
    realtime: bool,
    device: object = None,
    causes: LongPeriods | None = None,
    counts: ThreadCounts | None = None,
    spin: SpinBudget | None = None,
) -> list[float]:
    """The statistics block's values (:data:`STAT_FIELDS` order); ``counts`` is read here, so
    call it from the loop's thread."""
    c = r.counts
    causes = causes or LongPeriods(timing.period)
    n = counts.counts() if counts is not None else {}
    vals = {
        "ticks": timing.ticks,
        "elapsed_s": (timing.t_last - timing.t_first) if timing.ticks > 1 else 0.0,
        "rate_hz": timing.rate(),
        "period_p50_us": timing.percentile(0.5),
        "period_p99_us": timing.percentile(0.99),
        "period_max_us": timing.max_us,
        "overruns": timing.overruns,
        "periods_over_2ms": timing.count_over(2.0 * timing.period),
        "late_ticks": c["late"],
        "stale_ticks": c["stale"],
        "device_errors": c["device"],
        "bad_data": c["bad_data"],
        "fault_episodes": c["episodes"],
        "nonfinite_forces": c["nonfinite"],
        "clamped_forces": c["clamped"],
        "realtime": float(realtime),
        "models_refused": c["refused"],
        "tick_errors": c["tick_errors"],
        "device_thread_fifo": getattr(device, "thread_fifo", -1),
        "device_lost": int(getattr(device, "lost", None) is not None),
        "device_reinits": getattr(device, "reinits", 0),
        "overruns_work": causes.work,
        "overruns_wake": causes.wake,
        "overruns_other": causes.other,
        "work_max_us": causes.work_max_s * 1e6,
        "spin_us": spin.spin_s * 1e6 if spin is not None else 0.0,
        "minor_faults": n.get("minor_faults", 0),
        "major_faults": n.get("major_faults", 0),
        "involuntary_switches": n.get("involuntary_switches", 0),
        "gc_collections": n.get("gc_collections", 0),
    }
    return [float(vals[k]) for k in STAT_FIELDS]

"""``humantele bench haptics --callback``: the Touch X servo callback's own timing on the fake
OpenHaptics libHD (tests/devices/fake_libhd.c, compiled here with the system C compiler).

OpenHaptics runs the device callback in its own 1 kHz thread and every call into Python needs
the GIL. Each row runs the servo process's real loop (:func:`humantele.haptics.servo_child._run`,
a model in contact, no SCHED_FIFO) in a fresh process for ``seconds`` and reports the
callback's period (entry to entry, as Python runs it) and duration (``hdGetSchedulerTimeStamp``
at its end: from the scheduler tick's start, the wait for the GIL counted), the fake
scheduler's would-be watchdog trips (ticks whose callbacks ran over 1 ms: each an HD_TIMER_ERROR,
which now stops the callback and re-initialises the device, so the fake's watchdog is off and
the ticks are counted from its duration histogram, keeping every row measured for its whole
time) and the loop's rate.
Loops: ``device`` (the loop blocks in ``TouchX.wait_tick``, GIL free, switch interval 0.2 ms:
the project's) and ``sleep+spin`` (the loop on its own deadline clock, spinning the last
0.2 ms: what it did before). Loads: idle; one busy core (a separate ``python -c "while True:
pass"`` process); a CPU-bound Python thread inside the servo process.
"""

from __future__ import annotations

import ctypes
import gc
import multiprocessing as mp
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

FAKE_SOURCE = Path(__file__).resolve().parents[3] / "tests" / "devices" / "fake_libhd.c"
WATCHDOG_US = 1000
# (name, loop, load, switch interval for a device-driven loop or None for the project's)
ROWS: list[tuple[str, str, str, float | None]] = [
    ("device / idle", "device", "idle", None),
    ("device / one busy core", "device", "busy core", None),
    ("device / CPU-bound Python thread", "device", "python thread", None),
    ("device / Python thread, 5 ms switch", "device", "python thread", 0.005),
    ("sleep+spin / idle", "spin", "idle", None),
    ("sleep+spin / idle (run 2)", "spin", "idle", None),
    ("sleep+spin / idle (run 3)", "spin", "idle", None),
    ("sleep+spin / one busy core", "spin", "busy core", None),
    ("sleep+spin / CPU-bound Python thread", "spin", "python thread", None),
]


def build_fake_libhd(dest_dir: Path) -> Path:
    """Compile the fake libHD into ``dest_dir``; RuntimeError when there is no C compiler or
    no source (an installed package without the tests)."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None or not FAKE_SOURCE.exists():
        raise RuntimeError(f"needs a C compiler and {FAKE_SOURCE} (a source checkout)")
    out = dest_dir / "libHD.so"
    subprocess.run([cc, "-shared", "-fPIC", "-O1", "-o", str(out), str(FAKE_SOURCE),
                    "-lpthread", "-lm"], check=True)  # fmt: skip
    return out


class _OwnClock:
    """A device without ``wait_tick``: the servo loop then runs on its own sleep+spin clock."""

    def __init__(self, dev: Any) -> None:
        self._dev = dev

    def read(self):  # noqa: ANN201 - DeviceState
        return self._dev.read()

    def command_force(self, f) -> None:  # noqa: ANN001
        self._dev.command_force(f)


def _child(
    lib: str,
    loop: str,
    load: str,
    switch: float | None,
    seconds: float,
    rt: int,
    thread_rt: int,
    conn,
) -> None:
    """One row, in its own process: the servo loop on the fake device; sends the figures.
    ``rt`` > 0: the process at that SCHED_FIFO priority before the device opens, as
    :func:`~humantele.haptics.servo_child.servo_main` does (the fake's scheduler thread does
    not inherit it, see fake_libhd.c); ``thread_rt`` > 0: the backend's callback gives its own
    thread SCHED_FIFO ``thread_rt`` (``TouchX.thread_priority``, what the servo does now; 0:
    what it did before). The CPU-bound thread and the busy process stay at normal priority."""
    import numpy as np

    from humantele.haptics import servo_child
    from humantele.haptics.demo_patient import demo_model
    from humantele.haptics.devices import TouchX, TouchXConfig
    from humantele.haptics.servo_config import ServoConfig
    from humantele.haptics.servo_layout import (
        C_MODEL,
        C_MODEL_GEN,
        C_MODEL_ON,
        C_REG_GEN,
        CMD_LEN,
        SAMPLE_LEN,
        STAT_FIELDS,
        STATS_LEN,
    )  # fmt: skip
    from humantele.haptics.shm import SeqlockArray

    fake = ctypes.CDLL(lib)
    fake.fake_timing.restype = ctypes.c_double
    fake.fake_timing.argtypes = [ctypes.c_int, ctypes.c_double]
    fake.fake_counter.restype = ctypes.c_long
    fake.fake_reset(0)
    fake.fake_require_gtdd_home(0)
    fake.fake_set_watchdog_us(0)  # counted instead (fake_timing_over): see the docstring
    fake.fake_thread_policy.restype = ctypes.c_long
    fake.fake_timing_over.restype = ctypes.c_long
    fake.fake_timing_over.argtypes = [ctypes.c_int, ctypes.c_double]
    m = np.eye(4)
    m[1, 3] = -35.0  # mm: 5 mm into the demo patient under the automatic registration
    fake.fake_set_transform((ctypes.c_double * 16)(*m.T.reshape(-1)))
    cfg = ServoConfig(device=TouchXConfig(library=lib), realtime_priority=rt)
    dev = TouchX(cfg.device)
    dev.thread_priority = thread_rt
    realtime = servo_child.try_realtime(cfg) if rt > 0 else False  # as servo_main: before open
    gc.collect()  # as servo_main does before it opens the device
    gc.freeze()
    dev.open()
    device = dev if loop == "device" else _OwnClock(dev)
    if switch is not None:
        servo_child.GIL_SWITCH_S = switch
    blocks = [SeqlockArray(CMD_LEN), SeqlockArray(SAMPLE_LEN), SeqlockArray(STATS_LEN)]
    cmd, out, st = blocks
    c = np.zeros(CMD_LEN)
    c[C_MODEL_GEN], c[C_MODEL_ON], c[C_REG_GEN] = 0.0, 1.0, 0.0
    c[C_MODEL : C_MODEL + 7] = demo_model().as_array()
    cmd.write(c)
    stop = {"flag": False}
    timer = threading.Timer(seconds, lambda: stop.__setitem__("flag", True))
    timer.start()
    if load == "python thread":

        def burn() -> None:
            while not stop["flag"]:
                pass

        threading.Thread(target=burn, daemon=True).start()
    try:
        servo_child._run(cfg, device, cmd, out, st, stop, os.getppid(), realtime)
        thread_policy = int(fake.fake_thread_policy())  # read back from the kernel
    finally:
        dev.close()
    stats = dict(zip(STAT_FIELDS, st.read().tolist(), strict=True))
    for b in blocks:
        b.close()
        b.unlink()
    res = dev.timing.summary()
    res.update({
        "tick_period_p99_us": fake.fake_timing(0, 0.99),
        "tick_duration_p99_us": fake.fake_timing(1, 0.99),
        "watchdog_trips": float(fake.fake_timing_over(1, float(WATCHDOG_US))),
        "device_ticks": float(fake.fake_counter(0)),
        "loop_rate_hz": stats["rate_hz"],
        "loop_fault_episodes": stats["fault_episodes"],
        "realtime": bool(realtime),
        "thread_fifo": float(thread_policy - 1000 if thread_policy > 1000 else 0),
    })  # fmt: skip
    conn.send(res)


def run_row(
    lib: Path,
    loop: str,
    load: str,
    switch: float | None,
    seconds: float,
    rt: int = 0,
    thread_rt: int = 0,
) -> dict:
    """One row in a fresh spawned process (with a busy-core process beside it if asked)."""
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe(duplex=False)
    burner = None
    if load == "busy core":
        burner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        load_before = os.getloadavg()[0]
        p = ctx.Process(
            target=_child,
            args=(str(lib), loop, load, switch, seconds, rt, thread_rt, child),
        )
        p.start()
        child.close()
        res = parent.recv() if parent.poll(seconds + 60.0) else {}
        p.join(30.0)
        if p.is_alive():
            p.kill()
            p.join()
        res["load_1min"] = max(load_before, os.getloadavg()[0])
    finally:
        if burner is not None:
            burner.kill()
            burner.wait()
    return res


# The rows of the callback thread's priority (issue 30): the process at SCHED_FIFO, the
# callback's own thread at normal priority (before) and at SCHED_FIFO (now).
FIFO_ROWS = [r for r in ROWS if r[1] == "device" and r[2] in ("idle", "busy core")]


def measure(seconds: float, rt: int = 0, fifo_only: bool = False) -> list[dict]:
    """All rows at normal priority (unless ``fifo_only``), then (``rt`` > 0) the rows with the
    process at SCHED_FIFO ``rt``: :data:`FIFO_ROWS` with the callback thread left at normal
    priority ("before": the servo until issue 30) and every row with the callback thread at
    SCHED_FIFO ``rt`` (the servo now)."""
    plan: list[tuple[int, int, tuple[str, str, str, float | None]]] = []
    if not fifo_only:
        plan += [(0, 0, r) for r in ROWS]
    if rt > 0:
        plan += [(rt, 0, r) for r in FIFO_ROWS]
        plan += [(rt, rt, r) for r in (FIFO_ROWS if fifo_only else ROWS)]
    with tempfile.TemporaryDirectory() as d:
        lib = build_fake_libhd(Path(d))
        rows = []
        for prio, thread_prio, (name, loop, load, switch) in plan:
            res = run_row(lib, loop, load, switch, seconds, prio, thread_prio)
            if prio:
                name = f"{name}, SCHED_FIFO {prio}" + ("" if res.get("realtime") else " refused")
                name += (
                    f", callback thread SCHED_FIFO {res.get('thread_fifo', 0):.0f}"
                    if thread_prio
                    else ", callback thread normal (before)"
                )
            res.update({"row": name, "loop": loop, "load": load, "rt": prio,
                        "thread_rt": thread_prio})  # fmt: skip
            rows.append(res)
            print(f"  {name}: period p99 {res.get('period_p99_us', 0):.0f} us, duration p99 "
                  f"{res.get('duration_p99_us', 0):.0f} us, > 1 ms "
                  f"{res.get('durations_over_1ms', 0):.0f}, watchdog "
                  f"{res.get('watchdog_trips')}", flush=True)  # fmt: skip
        return rows


HEADER = [
    "loop / load", "period p50 / p99 / max us", "duration p50 / p99 / max us",
    "callbacks > 1 ms", "watchdog trips", "loop Hz", "load avg",
]  # fmt: skip


def table_rows(rows: list[dict]) -> list[list[object]]:
    out = []
    for r in rows:
        n = max(r.get("callbacks", 0.0), 1.0)
        out.append([
            r["row"],
            f"{r['period_p50_us']:.0f} / {r['period_p99_us']:.0f} / {r['period_max_us']:.0f}",
            f"{r['duration_p50_us']:.0f} / {r['duration_p99_us']:.0f} / "
            f"{r['duration_max_us']:.0f}",
            f"{r['durations_over_1ms']:.0f} ({100 * r['durations_over_1ms'] / n:.2f} %)",
            f"{r['watchdog_trips']:.0f}",
            f"{r['loop_rate_hz']:.0f}",
            f"{r['load_1min']:.2f}",
        ])  # fmt: skip
    return out


def section(
    rows: list[dict], seconds: float, table: str, machine: str, rt: int = 0, fifo_only: bool = False
) -> str:
    return "\n\n".join([
        "## Haptics: the Touch X servo callback (fake OpenHaptics libHD)",
        machine + " A shared machine (other work ran beside it): the load average (1 min, the "
        "larger of before and after the row) is given per row.",
        f"`humantele bench haptics --callback --callback-seconds {seconds:g}"
        + (f" --callback-realtime {rt}" if rt else "")
        + (" --callback-fifo-only" if fifo_only else "")
        + "`: each row runs the servo process's loop on the Touch X backend over the fake libHD "
        "(its own 1 kHz scheduler thread; its watchdog's trips counted, not acted on) with the "
        "demo patient in contact "
        f"for {seconds:g} s, at normal priority"
        + (f", then with the process at SCHED_FIFO {rt} before the device opens (as the "
           "servo runs where allowed; the load stays at normal priority): the fake's scheduler "
           "thread does not inherit it (as OpenHaptics' driver-made thread need not), so "
           "'callback thread normal (before)' is the servo until issue 30 and 'callback thread "
           f"SCHED_FIFO {rt}' the servo now (the backend's first callback sets its own "
           "thread's policy, read back from the kernel)" if rt else "")
        + ". Period: the callback's entry to entry, as its Python code runs; "
        "duration: `hdGetSchedulerTimeStamp()` at its end, i.e. from the scheduler tick's "
        "start, the wait for the GIL included. `device`: the loop blocks in "
        "`TouchX.wait_tick` (GIL free) and the servo process's switch interval is 0.2 ms (the "
        "project's); `sleep+spin`: the loop on its own deadline clock, spinning the last "
        "0.2 ms holding the GIL (the loop as before; the backend as now: its libHD calls keep "
        "the GIL, so a callback takes it once). One busy core: a separate `python -c \"while True: "
        "pass\"` process; Python thread: a CPU-bound thread inside the servo process.",
        table,
        "Watchdog trips: ticks whose callbacks ran over 1 ms, where the fake's watchdog would "
        "raise HD_TIMER_ERROR (OpenHaptics does not publish its own limit; its guide asks "
        "callbacks to take \"significantly less time\" than the 1 ms slice and the device's "
        "amplifiers cut out when the servo loop stalls); each would now stop the callback and "
        "re-initialise the device (docs/hardware.md), so here the watchdog only counts. "
        "A CPU-bound Python thread inside the servo process makes the callback wait for the GIL "
        "whatever the loop does: with SCHED_FIFO it is a priority inversion (the thread holding "
        "the GIL is preempted by normal-priority work and cannot hand it over). The servo "
        "process runs no other Python thread (the daemon's threads are in their own process); "
        "the 0.2 ms switch interval bounds the wait while the holder runs (compare the 5 ms "
        "row). The two 1 kHz clocks of a `sleep+spin` row (the device's scheduler and the loop's "
        "deadlines) keep the phase they start with for the whole run, so whether the device's "
        "callback falls into the loop's spin and render window, and waits for the GIL every "
        "tick, changes from run to run: hence three idle runs.",
    ])  # fmt: skip

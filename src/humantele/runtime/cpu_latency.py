"""Keep the CPUs' wake-up from idle short while the servo runs: a PM QoS request on Linux's
``/dev/cpu_dma_latency``, as cyclictest and real-time audio make.

A CPU with nothing to run between two ticks goes idle; in a virtual machine its idle state
("haltpoll idle") hands the virtual CPU back to the host, which must schedule it again for the
next tick. Measured here (issue 34, ``humantele bench loop --together --load``): with one core
busy the scheduler put the busy process beside the bare loop, whose CPU then never idled,
and the servo's CPU idled between ticks and woke late 386-700 times in 15 s against the bare
loop's 274-356. With a request of 0 us the idle loop polls instead of halting (cpuidle's
POLL state) and the servo's late wakes were 12-167, as the bare loop's. The request holds for
as long as the descriptor is open (the kernel drops it when the process ends); it costs an
idle CPU's spinning, on a haptic workstation only while the servo runs.
"""

from __future__ import annotations

import logging
import os
import struct
from pathlib import Path

log = logging.getLogger(__name__)

CPU_DMA_LATENCY = Path("/dev/cpu_dma_latency")
_held: list[int] = []  # descriptors kept open for the process's life


def hold_cpu_latency(max_us: int, path: Path = CPU_DMA_LATENCY) -> bool:
    """Ask that no CPU take over ``max_us`` (us) to wake from idle while this process lives;
    True when the kernel took the request. Refused (not root: a warning) or absent (no such
    device: info): False, with the reason logged."""
    try:
        fd = os.open(path, os.O_WRONLY)
    except OSError as exc:  # absent (a container, not Linux): said quietly; refused: a warning
        level = logging.INFO if isinstance(exc, FileNotFoundError) else logging.WARNING
        log.log(level, "CPU wake-up latency request refused (%s: %s)", path, exc.strerror)
        return False
    try:
        os.write(fd, struct.pack("i", int(max_us)))
    except OSError as exc:
        os.close(fd)
        log.warning("CPU wake-up latency request refused (%s: %s)", path, exc.strerror)
        return False
    _held.append(fd)
    return True


def release_cpu_latency() -> None:
    """Drop this process's requests (closing their descriptors)."""
    while _held:
        os.close(_held.pop())

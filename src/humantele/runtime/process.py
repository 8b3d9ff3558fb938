"""A daemon process's life: stop signals and the demo that started it."""

from __future__ import annotations

import os
import signal
from collections.abc import Callable
from typing import Any

PARENT_PID_ENV = "HUMANTELE_PARENT_PID"  # set by the demo for the daemons it starts


def on_stop_signals(loop: Any, callback: Callable[[], None]) -> None:
    """Call ``callback`` on SIGINT or SIGTERM (asyncio loop)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, callback)


def ignore_stop_signals() -> None:
    """After the asyncio loop closed (its handlers are gone): a late SIGINT/SIGTERM (a
    terminal's Ctrl-C reaching the process group, a supervisor's SIGTERM) must not turn a
    clean stop into a KeyboardInterrupt or a death by signal while the process exits."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)


def parent_gone() -> bool:
    """True when this process was started by a demo (``HUMANTELE_PARENT_PID``) that is gone."""
    want = os.environ.get(PARENT_PID_ENV)
    return bool(want) and str(os.getppid()) != want

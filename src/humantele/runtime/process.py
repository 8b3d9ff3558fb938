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


def parent_gone() -> bool:
    """True when this process was started by a demo (``HUMANTELE_PARENT_PID``) that is gone."""
    want = os.environ.get(PARENT_PID_ENV)
    return bool(want) and str(os.getppid()) != want

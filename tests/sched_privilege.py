"""Whether a process started from the tests may take SCHED_FIFO (root, or an rtprio limit)."""

import subprocess
import sys


def fifo_allowed() -> bool:
    """As a child would find it: a fresh interpreter asks for SCHED_FIFO 1."""
    code = "import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))"
    return subprocess.run([sys.executable, "-c", code], capture_output=True).returncode == 0

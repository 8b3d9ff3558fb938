"""Command-line pieces shared by the commands: argument types that refuse bad values with one
clear line (argparse prints it and exits 2), the exit codes, and the one-line text of a socket
that cannot be opened.

Exit codes: 0 done (also after Ctrl-C or SIGTERM), 1 failed at run time, 2 bad configuration or
arguments, 3 refused by the signaling server (wrong token, room full): retrying cannot help, so
a supervisor (the demo, systemd's ``RestartPreventExitStatus=2 3``) does not restart on 2 or 3.
"""

from __future__ import annotations

import argparse
import errno
import math
import socket

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_CONFIG = 2
EXIT_REFUSED = 3
FATAL_EXIT_CODES = (EXIT_CONFIG, EXIT_REFUSED)  # restarting does not help

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


def duration_s(text: str) -> float:
    """``--duration``: a finite number of seconds > 0."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not math.isfinite(v) or v <= 0.0:
        raise argparse.ArgumentTypeError(f"{text!r}: give a finite number of seconds above 0")
    return v


def log_level(text: str) -> str:
    """``--log-level``: one of the logging levels (any case); returned upper-case."""
    v = text.strip().upper()
    if v not in LOG_LEVELS:
        raise argparse.ArgumentTypeError(f"{text!r}: choose one of {', '.join(LOG_LEVELS)}")
    return v


def port(text: str) -> int:
    """A TCP port, 0-65535 (0: the system picks one)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"{v}: a port is 0-65535")
    return v


def socket_error(what: str, host: str, port_: int, exc: OSError) -> str:
    """One line for an address that cannot be listened on (in use, unknown host, ...)."""
    if isinstance(exc, socket.gaierror):
        reason = f"cannot resolve the host name ({exc.strerror or exc})"
    else:
        reasons = {
            errno.EADDRINUSE: "the port is in use (another server running?)",
            errno.EACCES: "permission denied (ports below 1024 need privileges)",
            errno.EADDRNOTAVAIL: "this machine has no such address",
        }
        reason = reasons.get(exc.errno or 0) or exc.strerror or str(exc)
    return f"{what}: cannot listen on {host}:{port_}: {reason}"

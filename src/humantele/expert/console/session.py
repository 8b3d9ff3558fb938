"""What the console needs of the session: a state snapshot, the probe pose at a time, and the
sonographer's commands. The expert daemon gives one (:mod:`humantele.expert.console.hook`);
tests give their own.

``snapshot()`` is a JSON-able dict, read about 20 times a second, all fields optional (None:
not known, shown as such)::

    t                 the expert's clock (s)
    link              {"state": "connected" | "connecting" | "disconnected",
                       "pose_age_ms": age of the follower's latest probe pose (ms)}
    calibration       {"state": "calibrated" | "calibrating" | "not calibrated",
                       "landmark": the landmark the follower is asked to press, or None,
                       "last": the last calibration event, as text}
    alignment         {"mm": tip distance, "deg": angle} between the virtual probe and the
                      follower's real one (None when either is unknown)
    servo             {"rate_hz", "fault" ("" when none), "alive"}
    recording         {"on": bool, "error": text or None, "written": samples}
    scan              the scan in progress (number) or None
    clutch            {"on": the console's clutch, "engaged": the mapping's clutch}
    force             the contact force along the beam (N, > 0 pressing into the patient):
                      {"measured_n": the follower's sensor, along its probe's beam,
                       "rendered_n": the servo's force on the sonographer's hand, along the
                       stylus's beam (the virtual probe's), "contact": bool}
"""

from __future__ import annotations

from typing import Any, Protocol

from humantele.recording import Recorder


class ConsoleSession(Protocol):
    """The session as the console sees it (all called on the daemon's event loop)."""

    @property
    def recorder(self) -> Recorder | None:
        """Where the console's events go when the session records (None: not recording)."""

    def snapshot(self) -> dict[str, Any]:
        """The session at a glance (see the module docstring)."""

    def pose_at(self, t: float) -> dict[str, Any] | None:
        """The follower's probe at expert time ``t`` (s): ``{"position", "quaternion"}``
        (``T_patient_probe``, m), with ``virtual_position``/``virtual_quaternion`` (the
        expert's virtual probe) when known; None when there is no pose near ``t``."""

    def start_scan(self) -> int:
        """Start a scan; its number."""

    def stop_scan(self) -> None: ...

    def set_clutch(self, on: bool) -> None:
        """Hold the clutch from the console (as the stylus button does) or release it."""

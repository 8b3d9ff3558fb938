"""What the follower records (``--record FILE`` or ``[follower.session] record``), as samples
(topic, payload); ``t`` is the daemon's monotonic clock (its ClockSync's), s.

- ``/follower/force``: every force reading (tip frame, N);
- ``/follower/probe_pose``: every tracker frame once calibrated (patient frame; ``tracked``
  false with a zero pose when the probe was not found);
- ``/follower/calibration``: reset, each landmark taken or refused, the fit;
- ``/follower/ellipsoid``: the fitted model (world frame), once per calibration;
- ``/follower/latency``: the pose stream's one-way latency (``pose_one_way``) and the time
  the virtual probe was stale since the last report (``pose_stale_s``, s) about once a
  second; the
  clock-sync estimate when it changes (``/follower/clock_sync``).

A path that cannot be recorded to stops the daemon at start (exit code 2); a failure during
the session is reported in the stats and never stops the session.
"""

from __future__ import annotations

from typing import Any

from humantele.follower.calibration import CalibrationEvent
from humantele.follower.sensing import Measurement
from humantele.tracking.status import TrackingStatus

ZERO_POSE = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))  # recorded when the probe is not tracked


def measurement_samples(m: Measurement, calibration: Any) -> list[tuple[str, dict]]:
    """The force (tip frame) and, once calibrated, the probe pose (patient frame)."""
    out: list[tuple[str, dict]] = []
    if m.force_tip is not None:
        out.append(("/follower/force", {"force": m.force_tip}))
    if calibration is None:
        return out
    if m.status == TrackingStatus.TRACKED and m.T_world_tip is not None:
        T = calibration.T_world_patient.inverse() @ m.T_world_tip
        pose = {"position": T.position, "quaternion": T.quaternion, "tracked": True}
    else:
        pose = {"position": ZERO_POSE[0], "quaternion": ZERO_POSE[1], "tracked": False}
    if m.device_time_s is not None:
        pose["device_time_s"] = m.device_time_s
    out.append(("/follower/probe_pose", pose))
    return out


def calibration_event_samples(ev: CalibrationEvent) -> list[dict]:
    """``/follower/calibration`` payloads of one calibration event."""
    point = {"landmark": ev.landmark, "position": [float(v) for v in ev.point]}
    if ev.kind == "refused":
        return [{"event": "error", **point, "message": ev.message[:200]}]
    return [{"event": "point", **point}] + ([{"event": "fit"}] if ev.kind == "done" else [])

"""Alignment error between the virtual probe and the real (tracked) probe, as in the paper.

Method (documented in docs/analysis.md):

1. Follower timestamps are converted into the expert's clock with :class:`ClockMap`, fitted to
   the recorded clock-sync estimates (the half of them with the shortest round trip, as NTP
   does; a straight line when they span >= 30 s, so clock drift is removed, else their median).
2. Only frames with ``tracked`` true are used. At each one the virtual pose is interpolated
   between the two expert samples around it: position linearly, orientation by slerp. Frames
   outside the expert's samples, or in a gap longer than ``max_gap_s``, are skipped.
3. Position error ``e = p_real - p_virtual`` (patient frame); orientation error
   ``R_err = R_virtual^-1 R_real`` (probe frame) and its angle, the geodesic distance on SO(3),
   not a difference of Euler angles.
4. RMSE = sqrt(mean |e|^2) and sqrt(mean angle(R_err)^2). Centered: the mean error removed,
   ``e - mean(e)`` for position, ``mean(R_err)^-1 R_err`` for orientation, where the mean
   rotation is the chordal L2 mean on SO(3) (scipy ``Rotation.mean``: the rotation closest to
   the arithmetic mean of the rotation matrices).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

MIN_DRIFT_SPAN_S = 30.0


@dataclass(frozen=True)
class PoseTrack:
    """Poses over time: ``t`` (N,) s increasing, ``position`` (N, 3) m, ``quaternion`` (N, 4)
    (x, y, z, w), all ``T_patient_probe``."""

    t: NDArray[np.float64]
    position: NDArray[np.float64]
    quaternion: NDArray[np.float64]

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=float).reshape(-1)
        p = np.asarray(self.position, dtype=float).reshape(-1, 3)
        q = np.asarray(self.quaternion, dtype=float).reshape(-1, 4)
        if not len(t) == len(p) == len(q):
            raise ValueError(f"pose track lengths differ: t {len(t)}, p {len(p)}, q {len(q)}")
        order = np.argsort(t, kind="stable")
        if np.any(np.diff(t) < 0):
            t, p, q = t[order], p[order], q[order]
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "quaternion", q)

    def __len__(self) -> int:
        return len(self.t)

    def select(self, mask: ArrayLike) -> PoseTrack:
        mask = np.asarray(mask)
        return PoseTrack(self.t[mask], self.position[mask], self.quaternion[mask])

    def interpolate(
        self, t_query: ArrayLike, max_gap_s: float = 0.05
    ) -> tuple[NDArray[np.float64], Rotation, NDArray[np.bool_]]:
        """Pose at ``t_query``: (positions (M, 3), rotations (M), valid (M,)). Linear in
        position, slerp in orientation; invalid (and left at the nearest sample) outside the
        track or where the two samples around ``t`` are more than ``max_gap_s`` apart."""
        tq = np.asarray(t_query, dtype=float).reshape(-1)
        if len(self.t) < 2:
            return np.zeros((len(tq), 3)), Rotation.identity(len(tq)), np.zeros(len(tq), bool)
        i = np.clip(np.searchsorted(self.t, tq, side="right") - 1, 0, len(self.t) - 2)
        t0, t1 = self.t[i], self.t[i + 1]
        dt = t1 - t0
        valid = (tq >= self.t[0]) & (tq <= self.t[-1]) & (dt <= max_gap_s) & (dt > 0)
        a = np.clip((tq - t0) / np.where(dt > 0, dt, 1.0), 0.0, 1.0)
        pos = self.position[i] + a[:, None] * (self.position[i + 1] - self.position[i])
        r0 = Rotation.from_quat(self.quaternion[i])
        step = (r0.inv() * Rotation.from_quat(self.quaternion[i + 1])).as_rotvec()
        rot = r0 * Rotation.from_rotvec(a[:, None] * step)
        return pos, rot, valid


@dataclass(frozen=True)
class ClockMap:
    """Follower clock to expert clock: ``t_e = t_f + offset_s + drift * (t_f - t_ref)``."""

    offset_s: float = 0.0
    drift: float = 0.0
    t_ref: float = 0.0
    source: str = "none recorded: same clock assumed"
    n_estimates: int = 0

    def to_expert(self, t_follower: ArrayLike) -> NDArray[np.float64]:
        t = np.asarray(t_follower, dtype=float)
        return t + self.offset_s + self.drift * (t - self.t_ref)


def fit_clock_map(
    t_follower: ArrayLike, offset_s: ArrayLike, rtt_s: ArrayLike | None = None
) -> ClockMap:
    """Fit :class:`ClockMap` to estimates ``offset_s = t_expert - t_follower`` taken at
    follower times ``t_follower``; keeps the half with the shortest round trip."""
    t = np.asarray(t_follower, dtype=float).reshape(-1)
    off = np.asarray(offset_s, dtype=float).reshape(-1)
    ok = np.isfinite(t) & np.isfinite(off)
    if rtt_s is not None:
        rtt = np.asarray(rtt_s, dtype=float).reshape(-1)
        known = np.isfinite(rtt) & ok
        if known.sum() >= 4:
            ok &= known & (rtt <= np.median(rtt[known]))
    t, off = t[ok], off[ok]
    if len(t) == 0:
        return ClockMap()
    t_ref = float(t[0])
    if len(t) >= 4 and t[-1] - t[0] >= MIN_DRIFT_SPAN_S:
        drift, offset = np.polyfit(t - t_ref, off, 1)
        return ClockMap(float(offset), float(drift), t_ref, "clock sync, linear fit", len(t))
    return ClockMap(float(np.median(off)), 0.0, t_ref, "clock sync, median", len(t))


@dataclass(frozen=True)
class AlignmentErrors:
    """Per-frame errors at expert times ``t``: ``position`` (N, 3) m = real - virtual in the
    patient frame, ``rotation`` R_virtual^-1 R_real (probe frame)."""

    t: NDArray[np.float64]
    position: NDArray[np.float64]
    rotation: Rotation


def alignment_errors(
    virtual: PoseTrack, real: PoseTrack, max_gap_s: float = 0.05
) -> AlignmentErrors:
    """Errors of ``real`` (tracked frames only, times already on the expert clock) against
    ``virtual`` interpolated at those times; frames without a virtual pose are skipped."""
    pos_v, rot_v, valid = virtual.interpolate(real.t, max_gap_s)
    rot_err = (
        rot_v[valid].inv() * Rotation.from_quat(real.quaternion[valid]) if valid.any() else None
    )
    return AlignmentErrors(
        real.t[valid],
        real.position[valid] - pos_v[valid],
        rot_err if rot_err is not None else Rotation.identity(0),
    )


@dataclass(frozen=True)
class AlignmentRmse:
    """The paper's four figures for one scan (SI units), the sample count and the mean error."""

    n: int
    position_rmse_m: float
    centered_position_rmse_m: float
    orientation_rmse_rad: float
    centered_orientation_rmse_rad: float
    mean_position_error_m: tuple[float, float, float]
    mean_rotation_error_rad: float


def alignment_rmse(errors: AlignmentErrors) -> AlignmentRmse:
    """RMSE and centered RMSE of position and orientation (see the module docstring)."""
    n = len(errors.t)
    if n == 0:
        nan = float("nan")
        return AlignmentRmse(0, nan, nan, nan, nan, (nan, nan, nan), nan)
    e = errors.position
    mean_e = e.mean(axis=0)
    ang = errors.rotation.magnitude()
    mean_r = errors.rotation.mean()
    centered_ang = (mean_r.inv() * errors.rotation).magnitude()
    return AlignmentRmse(
        n=n,
        position_rmse_m=float(np.sqrt(np.mean(np.sum(e * e, axis=1)))),
        centered_position_rmse_m=float(np.sqrt(np.mean(np.sum((e - mean_e) ** 2, axis=1)))),
        orientation_rmse_rad=float(np.sqrt(np.mean(ang * ang))),
        centered_orientation_rmse_rad=float(np.sqrt(np.mean(centered_ang**2))),
        mean_position_error_m=(float(mean_e[0]), float(mean_e[1]), float(mean_e[2])),
        mean_rotation_error_rad=float(mean_r.magnitude()),
    )

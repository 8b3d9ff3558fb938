"""The simulated follower: a patient to press on and a human hand that tracks the virtual probe.

Used by the follower daemon when no person is there (demo, tests, benchmarks). It models what
the anchors measured of novices and no more:

- lag: the hand reacts after ``reaction_delay_s`` and closes the gap with a first-order
  response of time constant ``tracking_time_constant_s`` (together ~0.35 s: Black et al., C&G 2024,
  Table 3; docs/references.md);
- a constant offset (how this person holds the probe), position in world (m) and rotation;
- hand tremor: a 8-12 Hz band-limited random motion (physiological tremor) of given RMS.

Poses here are of the transducer's **tip frame** in the world frame (headset, y up): origin at
the centre of the transducer face, +z along the beam (out of the face, into the patient).

The simulated patient is an ellipsoidal abdomen lying on a bed: soft tissue of stiffness
``tissue_stiffness_n_per_m`` and a stiff bed. Its four true landmarks drive the scripted
calibration presses (:class:`CalibrationScript`).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import ArrayLike, NDArray

from humantele.follower.clinic import SimHeadConfig, SimHumanConfig, SimPatientConfig
from humantele.geometry import (
    Pose,
    matrix_to_quat,
    quat_conjugate,
    quat_from_axis_angle,
    quat_multiply,
    quat_normalize,
)

UP = np.array([0.0, 1.0, 0.0])


class SimPatient:
    """An ellipsoidal abdomen on a bed; forces on the probe tip (world frame, N)."""

    def __init__(self, config: SimPatientConfig | None = None) -> None:
        self.config = c = config or SimPatientConfig()
        self.semi_axes = np.array([c.half_length_m, c.half_height_m, c.half_width_m])
        yaw = math.radians(c.yaw_deg)
        center = np.array([c.center_xz_m[0], c.bed_height_m + c.half_height_m, c.center_xz_m[1]])
        # Ellipsoid frame: x head to feet, y up, z to the patient's right (the paper's axes).
        self.T_world_body = Pose(center, quat_from_axis_angle(UP, yaw))
        self.T_body_world = self.T_world_body.inverse()

    def ellipsoid(self):  # -> humantele.haptics.ellipsoid.Ellipsoid
        """The true abdomen as an Ellipsoid (world frame, m), e.g. for the sim ultrasound."""
        from humantele.haptics.ellipsoid import Ellipsoid

        c = self.config
        return Ellipsoid(tuple(self.T_world_body.position), tuple(self.semi_axes),
                         math.radians(c.yaw_deg))  # fmt: skip

    def landmarks(self) -> dict[str, NDArray[np.float64]]:
        """The true xiphoid, extreme left, extreme right and a bed point (world, m)."""
        a, b = self.config.half_width_m, self.config.half_height_m
        pts = {
            "xiphoid": [0.0, b, 0.0],
            "left": [0.0, 0.0, -a],
            "right": [0.0, 0.0, a],
            "bed": [0.0, -b, a + 0.12],
        }
        return {k: self.T_world_body.apply(np.array(v, dtype=float)) for k, v in pts.items()}

    def outward_normal(self, point_world: ArrayLike) -> NDArray[np.float64]:
        """Unit outward normal of the abdomen (or the bed, for the bed landmark) near a point."""
        p = np.asarray(point_world, dtype=float)
        if p[1] <= self.config.bed_height_m + 1e-3:
            return UP.copy()
        q = self.T_body_world.apply(p)
        n = q / self.semi_axes**2
        norm = float(np.linalg.norm(n))
        return UP.copy() if norm < 1e-9 else self.T_world_body.rotate(n / norm)

    def force(self, tip_world: ArrayLike) -> NDArray[np.float64]:
        """Force (world, N) the patient and bed put on a probe tip at ``tip_world`` (m)."""
        c = self.config
        p = np.asarray(tip_world, dtype=float)
        f = np.zeros(3)
        q = self.T_body_world.apply(p)
        r = float(np.sqrt(np.sum((q / self.semi_axes) ** 2)))
        if 1e-9 < r < 1.0:
            depth = float(np.linalg.norm(q)) * (1.0 / r - 1.0)  # along the ray from the centre
            n = q / self.semi_axes**2
            f += (
                c.tissue_stiffness_n_per_m * depth * self.T_world_body.rotate(n / np.linalg.norm(n))
            )
        if p[1] < c.bed_height_m:
            f += c.bed_stiffness_n_per_m * (c.bed_height_m - p[1]) * UP
        return f


def quat_slerp(q0: ArrayLike, q1: ArrayLike, s: float) -> NDArray[np.float64]:
    """Spherical interpolation from q0 (s=0) to q1 (s=1), shortest way; (x, y, z, w)."""
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    rel = quat_multiply(quat_conjugate(q0), q1)
    if rel[3] < 0:
        rel = -rel
    angle = 2.0 * math.atan2(float(np.linalg.norm(rel[:3])), float(rel[3]))
    if angle < 1e-9:
        return quat_normalize(q1)
    return quat_normalize(quat_multiply(q0, quat_from_axis_angle(rel[:3], angle * s)))


def probe_down_quat(normal_world: ArrayLike) -> NDArray[np.float64]:
    """Tip frame orientation with +z (the beam) along ``-normal``: pressing into the surface."""
    z = -np.asarray(normal_world, dtype=float)
    z = z / np.linalg.norm(z)
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(ref, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return matrix_to_quat(np.column_stack([x, y, z]))


class _Tremor:
    """Band-limited noise around ``hz``: an AR(2) resonator with a stationary RMS of ``rms``."""

    def __init__(self, rms: float, hz: float, rate_hz: float, rng: np.random.Generator) -> None:
        self.rng = rng
        r = 0.97
        theta = 2.0 * math.pi * hz / rate_hz
        self.phi1, self.phi2 = 2.0 * r * math.cos(theta), -r * r
        # Stationary variance of an AR(2) process per unit innovation variance.
        g0 = (1 - self.phi2) / ((1 + self.phi2) * ((1 - self.phi2) ** 2 - self.phi1**2))
        self.sigma = rms / math.sqrt(g0)
        self.x1 = np.zeros(3)
        self.x2 = np.zeros(3)

    def step(self) -> NDArray[np.float64]:
        x = self.phi1 * self.x1 + self.phi2 * self.x2 + self.rng.normal(0.0, self.sigma, 3)
        self.x2, self.x1 = self.x1, x
        return x


class SimHuman:
    """A person holding the real probe on the virtual one; ``step`` returns the true tip pose."""

    def __init__(
        self, config: SimHumanConfig | None = None, patient: SimPatient | None = None
    ) -> None:
        self.config = c = config or SimHumanConfig()
        self.patient = patient
        rng = np.random.default_rng(c.seed)
        self._pos_tremor = _Tremor(c.tremor_mm_rms / 1000.0, c.tremor_hz, c.rate_hz, rng)
        self._rot_tremor = _Tremor(math.radians(c.tremor_deg_rms), c.tremor_hz, c.rate_hz, rng)
        self.offset = np.asarray(c.offset_mm, dtype=float) / 1000.0
        rv = np.radians(np.asarray(c.offset_rotation_deg, dtype=float))
        angle = float(np.linalg.norm(rv))
        self.offset_q = quat_from_axis_angle(rv, angle) if angle > 0 else np.array([0, 0, 0, 1.0])
        self._targets: deque[tuple[float, Pose]] = deque()
        self.hand: Pose | None = None  # the smoothed hand pose, before offset and tremor
        self._t: float | None = None

    def step(self, t: float, target: Pose | None) -> Pose | None:
        """Advance to time ``t`` (s) with the latest target tip pose (world) or None if none;
        returns the true tip pose (world), or None before the first target."""
        c = self.config
        if target is not None:
            self._targets.append((t, target))
        # The target the person is reacting to now: the newest one older than the delay.
        cut = t - c.reaction_delay_s
        while len(self._targets) > 1 and self._targets[1][0] <= cut:
            self._targets.popleft()
        delayed = self._targets[0][1] if self._targets and self._targets[0][0] <= cut else None
        if self.hand is None:
            if delayed is None:
                return None
            self.hand = delayed
        elif delayed is not None:
            dt = 0.0 if self._t is None else max(0.0, t - self._t)
            alpha = 1.0 - math.exp(-dt / c.tracking_time_constant_s)
            pos = self.hand.position + alpha * (delayed.position - self.hand.position)
            self.hand = Pose(pos, quat_slerp(self.hand.quaternion, delayed.quaternion, alpha))
        self._t = t
        pos = self.hand.position + self.offset + self._pos_tremor.step()
        rv = self._rot_tremor.step()
        ang = float(np.linalg.norm(rv))
        q = quat_multiply(self.hand.quaternion, self.offset_q)
        if ang > 1e-12:
            q = quat_multiply(q, quat_from_axis_angle(rv, ang))
        if self.patient is not None:
            pos = self._limit_push(pos)
        return Pose(pos, q)

    def _limit_push(self, tip: NDArray[np.float64]) -> NDArray[np.float64]:
        """A person stops pushing at ``max_push_n``: back off along the force until below it."""
        f = self.patient.force(tip)
        fn = float(np.linalg.norm(f))
        for _ in range(20):
            if fn <= self.config.max_push_n:
                break
            tip = tip + f / fn * 0.002
            f = self.patient.force(tip)
            fn = float(np.linalg.norm(f))
        return tip


class CalibrationScript:
    """The scripted technician: for the landmark asked, go over it, press, hold, lift.

    ``target(name, t)`` gives the tip pose the person aims at ``t`` seconds into the press of
    landmark ``name``, or None once that press is over (the daemon then asks for the next
    landmark, or the same one again if it was refused or missed). The press depth is chosen to
    reach ``press_force_n``. Travel happens ``lift_m`` above the landmarks, clear of the body.
    """

    LANDMARK_ORDER = ("xiphoid", "left", "right", "bed")

    def __init__(
        self,
        patient: SimPatient,
        press_force_n: float = 12.0,
        hover_m: float = 0.04,
        move_s: float = 0.35,
        press_s: float = 0.25,
        hold_s: float = 0.45,
        lift_s: float = 0.2,
        lift_m: float = 0.12,
    ) -> None:
        self.patient = patient
        lm = patient.landmarks()
        self.segments: dict[str, list[tuple[float, Pose]]] = {}
        for name in self.LANDMARK_ORDER:
            p = lm[name]
            n = patient.outward_normal(p)
            stiff = (
                patient.config.bed_stiffness_n_per_m
                if name == "bed"
                else patient.config.tissue_stiffness_n_per_m
            )
            q = probe_down_quat(n)
            above = Pose(p + hover_m * n, q)
            pressed = Pose(p - press_force_n / stiff * n, q)
            high = Pose(above.position + lift_m * UP, q)
            steps = [(0.0, high), (move_s, high), (move_s, above), (press_s, pressed),
                     (hold_s, pressed), (lift_s, above), (lift_s, high)]  # fmt: skip
            t, seg = 0.0, []
            for dt, pose in steps:
                t += dt
                seg.append((t, pose))
            self.segments[name] = seg
        self.segment_s = self.segments["xiphoid"][-1][0]
        self.duration_s = self.segment_s * len(self.LANDMARK_ORDER)
        self.hold_end_s = 2 * move_s + press_s + hold_s  # pressed until here, then lifted

    def target(self, name: str, t: float) -> Pose | None:
        wp = self.segments[name]
        if t < 0 or t > wp[-1][0]:
            return None
        for (t0, p0), (t1, p1) in zip(wp, wp[1:], strict=False):
            if t <= t1:
                s = 0.0 if t1 <= t0 else (t - t0) / (t1 - t0)
                return Pose(
                    p0.position + s * (p1.position - p0.position),
                    quat_slerp(p0.quaternion, p1.quaternion, s),
                )
        return wp[-1][1]


# Camera looking straight down: camera x = world x, camera y (image down) = world z,
# camera z (forward) = world -y (OpenCV camera axes).
_Q_WORLD_CAMERA_DOWN = matrix_to_quat(np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]))


class SimHead:
    """``T_world_camera`` of the headset: ``height_m`` above a lagged copy of the probe tip."""

    def __init__(self, config: SimHeadConfig | None = None) -> None:
        self.config = config or SimHeadConfig()
        self.focus: NDArray[np.float64] | None = None
        self._t: float | None = None

    def step(self, t: float, tip_world: ArrayLike | None) -> Pose | None:
        if tip_world is not None:
            tip = np.asarray(tip_world, dtype=float)
            if self.focus is None:
                self.focus = tip.copy()
            else:
                dt = 0.0 if self._t is None else max(0.0, t - self._t)
                alpha = 1.0 - math.exp(-dt / self.config.follow_time_constant_s)
                self.focus = self.focus + alpha * (tip - self.focus)
            self._t = t
        if self.focus is None:
            return None
        return Pose(self.focus + self.config.height_m * UP, _Q_WORLD_CAMERA_DOWN)

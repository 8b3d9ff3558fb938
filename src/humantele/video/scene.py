"""The seam between a simulated world and the sim video sources: one snapshot of the scene.

A sim source is given ``scene: Callable[[], SceneSnapshot]`` and calls it once per frame (in
its reader thread: the callable must be thread-safe and quick, e.g. return the latest snapshot
the world published). Frames: world = the headset's world frame, y up, metres; poses are
:class:`humantele.geometry.Pose` ``T_world_x``.

- ``patient``: the patient ellipsoid (:class:`humantele.haptics.ellipsoid.Ellipsoid`, which
  holds ``T_world_patient``; patient frame x head to feet, y up, z from the patient's left to
  right). For the sim this is the *true* patient the probe presses on, not the fitted model.
- ``T_world_tip``: the real probe's tip frame (origin at the centre of the transducer face, +z
  along the beam into the patient, +x along the array); for the sim the true pose, what the
  transducer physically images.
- ``force_n``: the contact force along the beam (N, >= 0 when pressing).
- ``T_world_head``: the headset's POV camera (OpenCV axes: x right, y down, z forward), as the
  follower's ``SimHead`` gives it.
- ``T_world_virtual_tip``: the virtual probe's tip frame, or None when there is none.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from humantele.geometry import Pose, matrix_to_quat, quat_from_axis_angle, quat_multiply
from humantele.haptics.ellipsoid import Ellipsoid


@dataclass(frozen=True)
class SceneSnapshot:
    """What the sim sources need of the world at time ``t`` (s, the world's clock)."""

    t: float
    patient: Ellipsoid | None
    T_world_tip: Pose | None
    force_n: float
    T_world_head: Pose | None
    T_world_virtual_tip: Pose | None = None

    @property
    def T_world_patient(self) -> Pose | None:  # noqa: N802 (frame names keep their case)
        return None if self.patient is None else self.patient.T_world_patient


Scene = Callable[[], SceneSnapshot]


def pose_is_finite(pose: object) -> bool:
    """True when ``pose`` is a Pose with a finite unit quaternion and a finite position within
    1000 km (beyond, the sources' float32 arithmetic would overflow).

    Pose validates itself when made, but a snapshot can come from anywhere (another thread, a
    deserialiser that bypassed the check): the sources check again and count what fails.
    """
    if not isinstance(pose, Pose):
        return False
    p = np.asarray(pose.position, dtype=float)
    q = np.asarray(pose.quaternion, dtype=float)
    if p.shape != (3,) or q.shape != (4,):
        return False
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        return False
    if float(np.max(np.abs(p))) >= 1e6 or float(np.max(np.abs(q))) > 2.0:
        return False  # checked before the norm, which would overflow for huge components
    return abs(float(q @ q) - 1.0) < 1e-6


# ---------------------------------------------------------------------------- a default scene
# The follower's default simulated patient (humantele.follower.sim_human.SimPatientConfig):
# bed at 0.80 m, abdomen centre (0.35, -0.15) in world x z, yaw 20 deg, semi-axes 0.35 (along
# the body), 0.11 (up), 0.16 (lateral). Repeated here so the video package needs no follower.
DEFAULT_PATIENT = Ellipsoid((0.35, 0.91, -0.15), (0.35, 0.11, 0.16), math.radians(20.0))


def look_at(eye: np.ndarray, target: np.ndarray, up: tuple = (0.0, 1.0, 0.0)) -> Pose:
    """``T_world_camera`` (OpenCV axes: x right, y down, z forward) of a camera at ``eye``
    looking at ``target`` (world, m) with world ``up`` toward the image top."""
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=float))
    if np.linalg.norm(x) < 1e-9:  # looking straight along up: any x
        x = np.cross(z, (0.0, 0.0, 1.0))
    x /= np.linalg.norm(x)
    return Pose(eye, matrix_to_quat(np.column_stack([x, np.cross(z, x), z])))


def probe_on_skin(
    patient: Ellipsoid,
    point_patient: tuple[float, float, float],
    press_m: float = 0.008,
    rotate_rad: float = 0.0,
    tilt_rad: float = 0.0,
    rock_rad: float = 0.0,
) -> Pose:
    """``T_world_tip`` of a probe on the skin above ``point_patient`` (patient frame, m).

    The face centre sits where the vertical line (patient y) through the point leaves the top
    of the body, pressed ``press_m`` in along the beam, which points down (patient -y). The
    array (tip +x, the image's right) points to the patient's left (a transverse view shown the
    sonographers' way, the patient's right on the image left), turned by ``rotate_rad`` about
    the beam (pi/2: +x toward the feet, a sagittal view with the head on the image left);
    then ``tilt_rad`` fans the image plane (about tip x) and ``rock_rad`` rocks the probe in
    the image plane (about tip y), both about the face centre.
    """
    x, _, z = (float(v) for v in point_patient)
    c_long, b, a = (float(v) for v in patient.semi_axes)
    r2 = (x / c_long) ** 2 + (z / a) ** 2
    y_skin = b * math.sqrt(max(0.0, 1.0 - r2))
    # Columns: tip x = patient -z, tip y = patient +x, tip z (beam) = patient -y.
    q = matrix_to_quat(np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]]))
    for axis, angle in (
        ((0, 0, 1.0), rotate_rad),
        ((1.0, 0, 0), tilt_rad),
        ((0, 1.0, 0), rock_rad),
    ):
        if angle:
            q = quat_multiply(q, quat_from_axis_angle(axis, angle))
    face = np.array([x, y_skin, z])
    T_patient_tip = Pose(face, q)
    T_patient_tip = Pose(face + T_patient_tip.rotate((0.0, 0.0, press_m)), q)
    return patient.T_world_patient @ T_patient_tip


class DemoScene:
    """A scene without a follower, for the benchmark and a standalone source: the default
    patient; the probe on the right kidney in a sagittal view, sweeping +-3 cm across the body
    every ``period_s`` and pressing 8 mm (5 N); the virtual probe a little off it; the head
    0.5 m from the probe, above and beside the patient, looking at it. ``clock`` gives the time
    (s, default ``time.monotonic``); call the scene for a snapshot."""

    def __init__(self, clock: Callable[[], float] | None = None, period_s: float = 8.0) -> None:
        import time

        self.clock = clock or time.monotonic
        self.period_s = period_s
        self.patient = DEFAULT_PATIENT

    def __call__(self) -> SceneSnapshot:
        t = float(self.clock())
        s = math.sin(2.0 * math.pi * t / self.period_s)
        z = 0.45 * 0.16 + 0.03 * s
        tip = probe_on_skin(self.patient, (0.12, 0.0, z), rotate_rad=math.pi / 2)
        virtual = probe_on_skin(
            self.patient, (0.13, 0.0, z + 0.012), rotate_rad=math.pi / 2 + 0.15, tilt_rad=0.1
        )
        eye = self.patient.T_world_patient.apply((0.02, 0.45, 0.42))
        head = look_at(eye, tip.position)
        return SceneSnapshot(t, self.patient, tip, 5.0, head, virtual)

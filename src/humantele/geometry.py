"""Poses, rotations and transforms: the one geometry module of humantele.

Conventions (used everywhere in the package):

- SI units: metres, radians, seconds. Millimetres and degrees only at the edges.
- Quaternions are unit quaternions in **scalar-last order (x, y, z, w)**, the order of
  ``scipy.spatial.transform.Rotation.as_quat()`` and of three.js ``Quaternion``. ``q`` and
  ``-q`` are the same rotation; functions here return ``w >= 0``.
- A transform is named by its frames: ``T_a_b`` maps coordinates expressed in frame ``b`` into
  frame ``a`` (``p_a = T_a_b.apply(p_b)``), so ``T_a_c = T_a_b @ T_b_c``.
- Patient frame of the paper: x along the body (head to feet), y up from the bed, z lateral.
- World frame of the headset: y up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

IDENTITY_QUAT = np.array([0.0, 0.0, 0.0, 1.0])


def _components(a: ArrayLike, n: int) -> list[float] | None:
    """The ``n`` floats of a single vector ``a`` (shape ``(n,)``), or None for anything else.

    The scalar fast paths below use them: on one 3-vector or quaternion a numpy call costs
    about a microsecond, more than the arithmetic, and the daemons' loops do hundreds a tick.
    """
    if isinstance(a, np.ndarray):
        return a.tolist() if a.shape == (n,) and a.dtype == np.float64 else None
    if isinstance(a, tuple | list) and len(a) == n and all(isinstance(c, int | float) for c in a):
        return [float(c) for c in a]
    return None


def quat_normalize(q: ArrayLike) -> NDArray[np.float64]:
    """Unit quaternion (x, y, z, w) with w >= 0; raises ValueError on zero or non-finite input."""
    c = _components(q, 4)
    if c is not None:
        x, y, z, w = c
        n = math.hypot(x, y, z, w)  # no overflow for large finite components
        if not math.isfinite(n) or n < 1e-12:
            raise ValueError("quaternion must be finite and non-zero")
        s = -1.0 / n if w < 0.0 else 1.0 / n
        return np.array((x * s, y * s, z * s, w * s))
    q = np.asarray(q, dtype=float)
    if q.shape[-1] != 4:
        raise ValueError(f"quaternion needs 4 components (x, y, z, w), got shape {q.shape}")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(q)) or np.any(n < 1e-12):
        raise ValueError("quaternion must be finite and non-zero")
    q = q / n
    return np.where(q[..., 3:4] < 0.0, -q, q)


def quat_multiply(q1: ArrayLike, q2: ArrayLike) -> NDArray[np.float64]:
    """Hamilton product q1 * q2 (apply q2 first, then q1); (x, y, z, w), broadcasts."""
    a, b = _components(q1, 4), _components(q2, 4)
    if a is not None and b is not None:
        return np.array(quat_multiply_tuple(a, b))
    q1 = np.asarray(q1, dtype=float)
    q2 = np.asarray(q2, dtype=float)
    x1, y1, z1, w1 = np.moveaxis(q1, -1, 0)
    x2, y2, z2, w2 = np.moveaxis(q2, -1, 0)
    return np.stack(
        [
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        ],
        axis=-1,
    )


def quat_multiply_tuple(
    a: tuple[float, float, float, float], b: tuple[float, float, float, float]
) -> tuple[float, float, float, float]:
    """Hamilton product a * b of plain float tuples (x, y, z, w): the fast path for 1 kHz code,
    where a numpy call (~1 us each) would cost more than the arithmetic."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def quat_conjugate(q: ArrayLike) -> NDArray[np.float64]:
    """Inverse of a unit quaternion (x, y, z, w)."""
    q = np.array(q, dtype=float)
    q[..., :3] *= -1.0
    return q


def quat_to_matrix(q: ArrayLike) -> NDArray[np.float64]:
    """3x3 rotation matrix (or (..., 3, 3)) of unit quaternion(s) (x, y, z, w)."""
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def matrix_to_quat(R: ArrayLike) -> NDArray[np.float64]:
    """Unit quaternion (x, y, z, w), w >= 0, of a 3x3 rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3):
        raise ValueError(f"rotation matrix must be 3x3, got {R.shape}")
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    return quat_normalize(q)


def quat_from_axis_angle(axis: ArrayLike, angle: float) -> NDArray[np.float64]:
    """Unit quaternion (x, y, z, w) rotating by ``angle`` rad about ``axis`` (any length > 0)."""
    axis = np.asarray(axis, dtype=float)
    n = np.linalg.norm(axis)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError("rotation axis must be finite and non-zero")
    s = math.sin(angle / 2.0)
    return quat_normalize([*(axis / n * s), math.cos(angle / 2.0)])


def quat_rotate(q: ArrayLike, v: ArrayLike) -> NDArray[np.float64]:
    """Rotate vector(s) v (..., 3) by unit quaternion q (x, y, z, w)."""
    qc, vc = _components(q, 4), _components(v, 3)
    if qc is not None and vc is not None:  # v + w t + u x t, t = 2 u x v
        ux, uy, uz, w = qc
        vx, vy, vz = vc
        tx, ty, tz = 2.0 * (uy * vz - uz * vy), 2.0 * (uz * vx - ux * vz), 2.0 * (ux * vy - uy * vx)
        return np.array(
            (
                vx + w * tx + (uy * tz - uz * ty),
                vy + w * ty + (uz * tx - ux * tz),
                vz + w * tz + (ux * ty - uy * tx),
            )
        )
    q = np.asarray(q, dtype=float)
    v = np.asarray(v, dtype=float)
    u = q[..., :3]
    w = q[..., 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def rotation_angle(q_a: ArrayLike, q_b: ArrayLike) -> NDArray[np.float64] | float:
    """Angle (rad, in [0, pi]) of the relative rotation between q_a and q_b, (x, y, z, w).

    This is the geodesic distance on SO(3): ``angle(q_a^-1 q_b)``; not a difference of Euler
    angles. Broadcasts over leading dimensions. Computed as ``2 atan2(|v|, |w|)`` of the
    relative quaternion, exact near 0 too (``arccos`` of the dot product loses half the digits
    there: 3e-8 rad for quaternions one rounding apart).
    """
    rel = quat_multiply(quat_conjugate(q_a), q_b)
    ang = 2.0 * np.arctan2(np.linalg.norm(rel[..., :3], axis=-1), np.abs(rel[..., 3]))
    return float(ang) if np.ndim(ang) == 0 else ang


@dataclass(frozen=True)
class Pose:
    """A rigid transform ``T_a_b``: position (m) of frame b's origin in frame a, and the unit
    quaternion (x, y, z, w) rotating b's axes into a's. ``T_a_b.apply(p_b) == p_a``.
    """

    position: NDArray[np.float64]
    quaternion: NDArray[np.float64]

    def __post_init__(self) -> None:
        c = _components(self.position, 3)
        if c is not None:
            if not (math.isfinite(c[0]) and math.isfinite(c[1]) and math.isfinite(c[2])):
                raise ValueError("pose position must be finite")
            p = np.array(c)
        else:
            p = np.array(self.position, dtype=float).reshape(3)  # a copy: a Pose never aliases
            if not np.all(np.isfinite(p)):
                raise ValueError("pose position must be finite")
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "quaternion", quat_normalize(np.asarray(self.quaternion)))

    @classmethod
    def identity(cls) -> Pose:
        return cls(np.zeros(3), IDENTITY_QUAT.copy())

    @classmethod
    def from_matrix(cls, T: ArrayLike) -> Pose:
        """From a 4x4 homogeneous transform."""
        T = np.asarray(T, dtype=float)
        if T.shape != (4, 4):
            raise ValueError(f"homogeneous transform must be 4x4, got {T.shape}")
        return cls(T[:3, 3], matrix_to_quat(T[:3, :3]))

    def as_matrix(self) -> NDArray[np.float64]:
        """4x4 homogeneous transform."""
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(self.quaternion)
        T[:3, 3] = self.position
        return T

    @property
    def rotation_matrix(self) -> NDArray[np.float64]:
        return quat_to_matrix(self.quaternion)

    def apply(self, points_b: ArrayLike) -> NDArray[np.float64]:
        """Map point(s) (..., 3) from frame b into frame a."""
        return quat_rotate(self.quaternion, points_b) + self.position

    def rotate(self, vectors_b: ArrayLike) -> NDArray[np.float64]:
        """Map direction vector(s) (..., 3) from frame b into frame a (no translation)."""
        return quat_rotate(self.quaternion, vectors_b)

    def inverse(self) -> Pose:
        """``T_b_a`` from ``T_a_b``."""
        q_inv = quat_conjugate(self.quaternion)
        return Pose(-quat_rotate(q_inv, self.position), q_inv)

    def __matmul__(self, other: Pose) -> Pose:
        """Composition: ``T_a_b @ T_b_c == T_a_c``."""
        return Pose(self.apply(other.position), quat_multiply(self.quaternion, other.quaternion))

    def distance_to(self, other: Pose) -> tuple[float, float]:
        """(position error in m, rotation error in rad) between two poses in the same frame."""
        return (
            float(np.linalg.norm(self.position - other.position)),
            float(rotation_angle(self.quaternion, other.quaternion)),
        )

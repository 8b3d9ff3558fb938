"""The ellipsoid patient model of the seed paper: fit from four landmarks, penetration, force.

Frames and units
    World: the headset's frame, y up, metres (the frame of the landmarks). Patient frame: origin
    at the ellipsoid centre, x along the body, y up (= world y), z lateral from the patient's
    left to right; ``T_world_patient`` is a rotation by ``heading`` (rad) about world +y plus
    the centre. Semi-axes ``(c, b, a)`` lie along patient ``(x, y, z)``; the model is
    axis-aligned in the patient frame and tangent to the bed (the paper's assumptions).
    ``penetration``/``force`` take world points (m) and velocities (m/s) and return world
    normals and forces (N).

Depth convention
    ``depth > 0`` inside the model: the distance to push the point out to the surface along the
    returned unit outward ``normal``. ``depth <= 0`` outside (no contact); outside its magnitude
    is a distance estimate only.

Methods (``method=``)
    ``"radial"``: the paper's. Scale the ellipsoid about its centre so that p lies on it, take
    the gradient normal n there, and solve ``|p + d n|_P = 1`` (a quadratic in d). Root
    choice: the paper says "the smaller of the two"; with an outward normal and p inside, the
    roots have opposite signs and the push-out one (near side along n) is the positive one, so
    we take ``d = (-beta + sqrt(beta^2 - alpha gamma)) / alpha`` (computed in the cancellation-
    free form ``-gamma / (beta + sqrt(...))``). Outside, both roots are negative and this is
    the one nearer zero (the near-side surface). When the normal line misses the model (far
    outside a flat one) the depth is minus the distance to the radially scaled surface point.
    See :mod:`humantele.haptics.penetration` for ``"exact"`` and ``"newton"`` and for where
    each method fails.

Longitudinal semi-axis
    The paper sets it "very large"; the default here is 10 m (``DEFAULT_LONGITUDINAL``), which
    makes the model a near-cylinder over a 0.5 m scanning region (surface within 13 mm of the
    cylinder at 0.5 m from the xiphoid) while keeping the quadratic well conditioned.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from humantele.geometry import Pose, quat_from_axis_angle
from humantele.haptics import penetration as _pen

DEFAULT_LONGITUDINAL = 10.0  # m, the paper's "very large" longitudinal semi-axis c
MIN_TORSO_SEMI_AXIS = 0.05  # m, plausibility bounds for the lateral and vertical semi-axes
MAX_TORSO_SEMI_AXIS = 1.0  # m
MIN_SEMI_AXIS = 1.0e-6  # m, bounds for any semi-axis of the geometric object
MAX_SEMI_AXIS = 1.0e6  # m
# A body the servo renders and the wire carries (see body_problem): vertical and lateral
# semi-axes 1 cm to 2 m, the longitudinal one 1 cm to 100 m (the paper's "very large"), the
# centre within 5 m of the patient-frame origin, a finite heading.
MIN_BODY_SEMI_AXIS = 0.01  # m
MAX_BODY_SEMI_AXIS = 2.0  # m, vertical and lateral
MAX_LONGITUDINAL = 100.0  # m
MAX_BODY_CENTER_M = 5.0  # m, each coordinate
DEFAULT_FORCE_LIMIT = 7.9  # N, Touch X peak force (CHAI3D device tables; docs/references.md)
METHODS = ("radial", "newton", "exact")
ARRAY_LENGTH = 7  # as_array(): centre (3), semi_axes (3), heading (1)

_ZERO = (0.0, 0.0, 0.0)


class LandmarkError(ValueError):
    """A calibration landmark that cannot give a plausible model; ``landmark`` names it."""

    def __init__(self, landmark: str, reason: str) -> None:
        super().__init__(f"landmark {landmark!r}: {reason}")
        self.landmark = landmark
        self.reason = reason


def _point(name: str, p: Any) -> NDArray[np.float64]:
    try:
        a = np.asarray(p, dtype=float)
    except (TypeError, ValueError) as exc:
        raise LandmarkError(name, f"must be 3 numbers (x, y, z) in metres, got {p!r}") from exc
    if a.shape != (3,):
        raise LandmarkError(name, f"must be 3 numbers (x, y, z) in metres, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise LandmarkError(name, f"must be finite, got {a.tolist()}")
    return a


def body_problem(center: ArrayLike, semi_axes: ArrayLike, heading: float) -> str | None:
    """Why this ellipsoid is not a patient body the servo can render (None if it is).

    Bounds: see ``MIN_BODY_SEMI_AXIS`` etc. A semi-axis of 1e-160 m (1/s^2 overflows) or a
    20 m high body (every pose out of range) is refused here, by the wire schema and the servo.
    """
    try:
        c = np.asarray(center, dtype=float).reshape(-1)
        s = np.asarray(semi_axes, dtype=float).reshape(-1)
        h = float(heading)
    except (TypeError, ValueError):
        return "centre, semi-axes and heading must be numbers"
    if c.shape != (3,) or s.shape != (3,):
        return "centre and semi-axes must be 3 numbers each"
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(s)) and math.isfinite(h)):
        return "centre, semi-axes and heading must be finite"
    if np.any(np.abs(c) > MAX_BODY_CENTER_M):
        return f"centre {c.tolist()} m is more than {MAX_BODY_CENTER_M:g} m from the origin"
    highs = (MAX_LONGITUDINAL, MAX_BODY_SEMI_AXIS, MAX_BODY_SEMI_AXIS)
    for axis, v, hi in zip(("longitudinal", "vertical", "lateral"), s, highs, strict=True):
        if not MIN_BODY_SEMI_AXIS <= v <= hi:
            return (
                f"{axis} semi-axis {v:.3g} m is not a body's ({MIN_BODY_SEMI_AXIS:g} to {hi:g} m)"
            )
    return None


class Ellipsoid:
    """Axis-aligned ellipsoid in the patient frame, placed in the world by centre and heading.

    ``center`` (3,) m in world; ``semi_axes`` (3,) m along patient (x, y, z); ``heading`` rad
    about world +y (patient z axis = world (sin h, 0, cos h)).
    """

    __slots__ = ("center", "semi_axes", "heading", "_k", "_cos", "_sin", "_c")

    def __init__(self, center: ArrayLike, semi_axes: ArrayLike, heading: float = 0.0) -> None:
        c = np.asarray(center, dtype=float)
        s = np.asarray(semi_axes, dtype=float)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ValueError(f"ellipsoid center must be 3 finite numbers (m), got {center!r}")
        if s.shape != (3,) or not np.all(np.isfinite(s)):
            raise ValueError(f"ellipsoid semi_axes must be 3 finite numbers (m), got {semi_axes!r}")
        if np.any(s < MIN_SEMI_AXIS) or np.any(s > MAX_SEMI_AXIS):  # 1/s^2 stays finite
            raise ValueError(
                f"ellipsoid semi_axes must be in [{MIN_SEMI_AXIS:g}, {MAX_SEMI_AXIS:g}] m, "
                f"got {s.tolist()}"
            )
        h = float(heading)
        if not math.isfinite(h):
            raise ValueError(f"ellipsoid heading must be finite (rad), got {heading!r}")
        h = math.remainder(h, 2.0 * math.pi)  # in [-pi, pi]
        c.flags.writeable = False
        s.flags.writeable = False
        self.center = c
        self.semi_axes = s
        self.heading = h
        self._cos = math.cos(h)
        self._sin = math.sin(h)
        self._c = (float(c[0]), float(c[1]), float(c[2]))
        self._k = _pen.constants(float(s[0]), float(s[1]), float(s[2]))

    # ----------------------------------------------------------------- construction
    @classmethod
    def from_landmarks(
        cls,
        xiphoid: ArrayLike,
        left: ArrayLike,
        right: ArrayLike,
        bed: ArrayLike,
        longitudinal_semi_axis: float = DEFAULT_LONGITUDINAL,
    ) -> Ellipsoid:
        """Fit the model to four world points (m, y up): eqs. 1-5 of the paper, plus heading.

        The heading is the direction of ``right - left`` in the horizontal plane (it becomes
        patient +z); the centre is midway between left and right laterally, midway between
        xiphoid and bed vertically, and at the xiphoid along the body. Only the bed's height is
        used. Raises :class:`LandmarkError` naming the landmark and the reason.
        """
        x1 = _point("xiphoid", xiphoid)
        p2 = _point("left", left)
        p3 = _point("right", right)
        p4 = _point("bed", bed)
        c_long = float(longitudinal_semi_axis)
        if not (MIN_TORSO_SEMI_AXIS <= c_long <= MAX_SEMI_AXIS):
            raise ValueError(
                f"longitudinal_semi_axis must be in [{MIN_TORSO_SEMI_AXIS}, {MAX_SEMI_AXIS:g}] m,"
                f" got {longitudinal_semi_axis!r}"
            )
        dx, dz = p3[0] - p2[0], p3[2] - p2[2]
        width = math.hypot(dx, dz)
        a = width / 2.0
        if a < MIN_TORSO_SEMI_AXIS:
            raise LandmarkError(
                "right",
                f"is {width * 1e3:.1f} mm from 'left' horizontally; it must be on the other side"
                f" of the patient (lateral semi-axis {a * 1e3:.1f} mm < "
                f"{MIN_TORSO_SEMI_AXIS * 1e3:.0f} mm)",
            )
        if a > MAX_TORSO_SEMI_AXIS:
            raise LandmarkError(
                "right",
                f"is {width:.2f} m from 'left' horizontally: lateral semi-axis {a:.2f} m is "
                f"implausible for a torso (> {MAX_TORSO_SEMI_AXIS:g} m)",
            )
        heading = math.atan2(dx, dz)
        ch, sh = math.cos(heading), math.sin(heading)

        def lateral(p: NDArray[np.float64]) -> float:  # patient z of a world point
            return sh * p[0] + ch * p[2]

        def along(p: NDArray[np.float64]) -> float:  # patient x of a world point
            return ch * p[0] - sh * p[2]

        if not (lateral(p2) < lateral(x1) < lateral(p3)):
            raise LandmarkError(
                "xiphoid",
                "is not between 'left' and 'right' across the body; left and right must be on"
                " opposite sides of the xiphoid",
            )
        y_bed = p4[1]
        if x1[1] <= y_bed:
            raise LandmarkError(
                "xiphoid",
                f"is not above the bed (xiphoid y = {x1[1]:.3f} m, bed y = {y_bed:.3f} m)",
            )
        b = (x1[1] - y_bed) / 2.0
        if not (MIN_TORSO_SEMI_AXIS <= b <= MAX_TORSO_SEMI_AXIS):
            raise LandmarkError(
                "xiphoid",
                f"is {2 * b * 1e3:.0f} mm above the bed: vertical semi-axis {b * 1e3:.0f} mm is "
                f"implausible for a torso (must be {MIN_TORSO_SEMI_AXIS * 1e3:.0f}-"
                f"{MAX_TORSO_SEMI_AXIS * 1e3:.0f} mm)",
            )
        for name, p in (("left", p2), ("right", p3)):
            if p[1] <= y_bed:
                raise LandmarkError(
                    name, f"is not above the bed (y = {p[1]:.3f} m, bed y = {y_bed:.3f} m)"
                )
        # Centre in patient-aligned coordinates (rotation about y only), then back to world.
        zc = (lateral(p2) + lateral(p3)) / 2.0
        xc = along(x1)
        yc = (x1[1] + y_bed) / 2.0
        center = (ch * xc + sh * zc, yc, -sh * xc + ch * zc)
        return cls(center, (c_long, b, a), heading)

    def problem(self) -> str | None:
        """:func:`body_problem` of this model (None: a body the servo can render)."""
        return body_problem(self.center, self.semi_axes, self.heading)

    # ----------------------------------------------------------------- frames
    @property
    def rotation(self) -> NDArray[np.float64]:
        """R_world_patient (3x3): rotation by ``heading`` about world +y."""
        c, s = self._cos, self._sin
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])

    @property
    def T_world_patient(self) -> Pose:  # noqa: N802 (frame names keep their case)
        """Pose of the patient frame (origin at the centre) in the world frame."""
        return Pose(self.center.copy(), quat_from_axis_angle((0.0, 1.0, 0.0), self.heading))

    def to_patient(self, points_world: ArrayLike) -> NDArray[np.float64]:
        """World points (..., 3) in the patient frame."""
        return (np.asarray(points_world, dtype=float) - self.center) @ self.rotation

    def to_world_vectors(self, vectors_patient: ArrayLike) -> NDArray[np.float64]:
        """Patient-frame directions (..., 3) in the world frame."""
        return np.asarray(vectors_patient, dtype=float) @ self.rotation.T

    # ----------------------------------------------------------------- scalar servo path
    def penetration(self, p: Sequence[float], method: str = "radial") -> tuple[float, tuple]:
        """(depth m, unit outward normal in world) of world point ``p``; depth > 0 inside.

        Pure-Python float math for the 1 kHz loop. Raises ValueError for a non-finite point or
        an unknown method.
        """
        px, py, pz = p
        dx = px - self._c[0]
        dy = py - self._c[1]
        dz = pz - self._c[2]
        ch = self._cos
        sh = self._sin
        x = ch * dx - sh * dz
        z = sh * dx + ch * dz
        if method == "radial":
            d, nx, ny, nz = _pen.radial(x, dy, z, self._k)
        elif method == "newton":
            d, nx, ny, nz = _pen.newton(x, dy, z, self._k)
        elif method == "exact":
            d, nx, ny, nz = _pen.exact(x, dy, z, self._k)
        else:
            raise ValueError(f"unknown penetration method {method!r}; use one of {METHODS}")
        return d, (ch * nx + sh * nz, ny, -sh * nx + ch * nz)

    def force(
        self,
        p: Sequence[float],
        v: Sequence[float],
        kp: float | Sequence[float],
        kd: float | Sequence[float],
        method: str = "radial",
        force_limit: float = DEFAULT_FORCE_LIMIT,
    ) -> tuple[float, float, float]:
        """World force (N) ``f = d Kp n - Kd v`` in contact (d > 0), zero out of contact.

        ``p`` world point (m), ``v`` world velocity (m/s); ``kp`` (N/m) and ``kd`` (N s/m)
        scalars or diagonals (3,) in the world frame, non-negative. The magnitude is clamped to
        ``force_limit`` (N) keeping the direction. A non-finite point, velocity or result gives
        zero force (never NaN or inf). Raises ValueError only for negative gains or a bad
        limit: those are configuration errors.
        """
        if isinstance(kp, int | float):
            kpx = kpy = kpz = kp
        else:
            kpx, kpy, kpz = kp
        if isinstance(kd, int | float):
            kdx = kdy = kdz = kd
        else:
            kdx, kdy, kdz = kd
        if not (kpx >= 0 and kpy >= 0 and kpz >= 0 and kdx >= 0 and kdy >= 0 and kdz >= 0):
            raise ValueError(f"force gains must be non-negative, got kp={kp!r} kd={kd!r}")
        if not 0.0 <= force_limit < math.inf:
            raise ValueError(f"force_limit must be finite and >= 0 N, got {force_limit!r}")
        try:
            d, (nx, ny, nz) = self.penetration(p, method)
        except ValueError:
            if method not in METHODS:
                raise
            return _ZERO  # non-finite point: no force
        if not d > 0.0:
            return _ZERO
        vx, vy, vz = v
        fx = d * kpx * nx - kdx * vx
        fy = d * kpy * ny - kdy * vy
        fz = d * kpz * nz - kdz * vz
        mag = math.sqrt(fx * fx + fy * fy + fz * fz)
        if mag <= force_limit:
            return (fx, fy, fz)
        if not mag < math.inf:  # NaN or inf velocity
            return _ZERO
        s = force_limit / mag
        return (fx * s, fy * s, fz * s)

    # ----------------------------------------------------------------- batch (numpy)
    def penetration_batch(
        self, points: ArrayLike, method: str = "radial"
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Vectorised :meth:`penetration` over world points (N, 3): depths (N,), normals (N, 3).

        Non-finite points give depth NaN and normal zero (the scalar path raises instead).
        """
        local = self.to_patient(np.asarray(points, dtype=float).reshape(-1, 3))
        fn = _pen.BATCH.get(method)
        if fn is None:
            raise ValueError(f"unknown penetration method {method!r}; use one of {METHODS}")
        depth, n = fn(local, self.semi_axes)
        return depth, self.to_world_vectors(n)

    def force_batch(
        self,
        points: ArrayLike,
        velocities: ArrayLike,
        kp: float | ArrayLike,
        kd: float | ArrayLike,
        method: str = "radial",
        force_limit: float = DEFAULT_FORCE_LIMIT,
    ) -> NDArray[np.float64]:
        """Vectorised :meth:`force`: world forces (N, 3) for world points and velocities (N, 3)."""
        kp = np.broadcast_to(np.asarray(kp, dtype=float), (3,))
        kd = np.broadcast_to(np.asarray(kd, dtype=float), (3,))
        if np.any(~(kp >= 0)) or np.any(~(kd >= 0)):
            raise ValueError(f"force gains must be non-negative, got kp={kp!r} kd={kd!r}")
        if not 0.0 <= force_limit < math.inf:
            raise ValueError(f"force_limit must be finite and >= 0 N, got {force_limit!r}")
        depth, n = self.penetration_batch(points, method)
        v = np.asarray(velocities, dtype=float).reshape(-1, 3)
        with np.errstate(invalid="ignore", over="ignore"):
            f = depth[:, None] * kp * n - kd * v
            mag = np.sqrt(np.sum(f * f, axis=1))
            scale = np.where(mag > force_limit, force_limit / np.where(mag > 0, mag, 1.0), 1.0)
            f = f * scale[:, None]
        bad = ~(depth > 0.0) | ~np.isfinite(mag) | ~np.all(np.isfinite(f), axis=1)
        f[bad] = 0.0
        return f

    # ----------------------------------------------------------------- serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-able SI description: centre (m, world), semi_axes (m, patient x y z), heading."""
        return {
            "center": [float(v) for v in self.center],
            "semi_axes": [float(v) for v in self.semi_axes],
            "heading": self.heading,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Ellipsoid:
        """Inverse of :meth:`to_dict`; ValueError naming the bad field."""
        if not isinstance(d, Mapping):
            raise ValueError(f"ellipsoid must be a mapping, got {type(d).__name__}")
        extra = set(d) - {"center", "semi_axes", "heading"}
        if extra:
            raise ValueError(f"ellipsoid: unknown field(s) {sorted(extra)}")
        for key in ("center", "semi_axes", "heading"):
            if key not in d:
                raise ValueError(f"ellipsoid: missing field {key!r}")
        for key in ("center", "semi_axes"):
            v = d[key]
            ok = isinstance(v, list | tuple) and len(v) == 3
            if not ok or not all(isinstance(e, int | float) and not isinstance(e, bool) for e in v):
                raise ValueError(f"ellipsoid: field {key!r} must be 3 numbers, got {v!r}")
        h = d["heading"]
        if not isinstance(h, int | float) or isinstance(h, bool):
            raise ValueError(f"ellipsoid: field 'heading' must be a number (rad), got {h!r}")
        return cls(d["center"], d["semi_axes"], h)

    def as_array(self) -> NDArray[np.float64]:
        """Fixed-length float64 array (7,): centre (3), semi_axes (3), heading (1)."""
        return np.concatenate([self.center, self.semi_axes, [self.heading]])

    @classmethod
    def from_array(cls, a: ArrayLike) -> Ellipsoid:
        """Inverse of :meth:`as_array`; ValueError on wrong length, non-finite or bad axes."""
        arr = np.asarray(a, dtype=float).reshape(-1)
        if arr.shape != (ARRAY_LENGTH,):
            raise ValueError(f"ellipsoid array must have {ARRAY_LENGTH} floats, got {arr.shape}")
        return cls(arr[0:3], arr[3:6], float(arr[6]))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Ellipsoid):
            return NotImplemented
        return bool(np.array_equal(self.as_array(), other.as_array()))

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        c = ", ".join(f"{v:.4f}" for v in self.center)
        s = ", ".join(f"{v:.4f}" for v in self.semi_axes)
        return f"Ellipsoid(center=({c}), semi_axes=({s}), heading={self.heading:.4f})"

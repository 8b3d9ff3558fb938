"""Penetration depth and outward normal of a point in an axis-aligned ellipsoid's own frame.

Coordinates here are patient-frame (origin at the centre, m); semi-axes ``(sx, sy, sz)`` m.
Scalar functions return ``(depth, nx, ny, nz)``: ``depth > 0`` inside (distance to push out
along the unit outward normal n), ``depth <= 0`` outside. They are pure-Python float math for
the 1 kHz servo loop; ``BATCH`` holds numpy versions over (N, 3) arrays.

Methods and where they fail
    ``radial`` (the paper): normal of the ellipsoid scaled through p, then the quadratic along
    it. Exact on spheres and on the axes; elsewhere the normal line misses the closest point,
    so the depth is too large and the normal tilts towards the long axis. The error grows with
    flattening and depth (several mm on a flattened torso 20 mm inside). At the centre the
    normal is undefined: we return the smallest semi-axis along its axis (also the exact
    answer). Far outside a flat model the normal line can miss the model (negative
    discriminant): depth is then minus the distance to the radially scaled surface point.
    ``exact``: the true closest surface point. Lagrange: x_i = s_i^2 p_i / (t + s_i^2) with t
    the root of F(t) = sum (s_i p_i / (t + s_i^2))^2 - 1, convex and decreasing on
    t > -min s_i^2 (Eberly, "Distance from a point to an ellipse, an ellipsoid, or a
    hyperellipsoid"). We work in the positive octant, in w = t + min s_i^2 (so roots near the
    pole keep their precision), start with one Newton step from t = 0, clamp it to a proven
    lower bound, then Newton from the left, which converges monotonically. When the point lies
    in the plane of the smallest axis and deep enough, the closest point leaves that plane
    (t = -min s_i^2, closed form). There the closest point jumps: points just either side of
    the plane get normals pointing opposite ways (the medial surface), so the exact force
    direction is discontinuous deep inside (the radial normal is continuous except at the
    centre).
    ``newton``: the radial estimate converted to t, then Newton steps on F (safeguarded by the
    same lower bound), at most ``NEWTON_STEPS``. Near the surface it is exact to far below a
    micrometre; deep inside flat models (near the medial surface) it inherits exact's
    jumps but stops early, so it may be off there.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Q_CENTRE = 1e-24  # q = sum (p_i / s_i)^2 at or below this: the centre (|p| < 1e-12 s)
Q_FAR = 1e24  # q at or above this: far away (|p| > 1e12 s): radial scaling, no iteration
FAR_DEPTH = -1e300  # most negative depth returned (points near the float range)
EXACT_MAX_ITER = 60
NEWTON_STEPS = 2


def constants(sx: float, sy: float, sz: float) -> tuple:
    """Per-ellipsoid constants used by the scalar functions (semi-axes in m, all > 0)."""
    sm = min(sx, sy, sz)
    if sm == sy:  # prefer "up" for the centre normal (the torso's usual smallest axis)
        cn = (0.0, 1.0, 0.0)
    elif sm == sz:
        cn = (0.0, 0.0, 1.0)
    else:
        cn = (1.0, 0.0, 0.0)
    sm2 = sm * sm
    ex, ey, ez = sx * sx - sm2, sy * sy - sm2, sz * sz - sm2
    return (
        1.0 / (sx * sx),
        1.0 / (sy * sy),
        1.0 / (sz * sz),
        sm,
        cn[0],
        cn[1],
        cn[2],
        sx,
        sy,
        sz,
        ex,
        ey,
        ez,
        sm2,
        max(ex, ey, ez),
    )


def _special(x: float, y: float, z: float, k: tuple, q: float) -> tuple[float, float, float, float]:
    """Centre, far-away and non-finite points (shared by every method)."""
    if q != q or (q == math.inf and not (math.isfinite(x + y + z))):
        raise ValueError(f"point must be finite, got ({x!r}, {y!r}, {z!r})")
    if q <= Q_CENTRE:
        return k[3], k[4], k[5], k[6]
    # Far away: the gradient direction is scale-invariant, so scale the point down first.
    m = max(abs(x), abs(y), abs(z))
    xs, ys, zs = x / m, y / m, z / m
    gx, gy, gz = xs * k[0], ys * k[1], zs * k[2]
    rg = math.sqrt(gx * gx + gy * gy + gz * gz)
    r = math.sqrt(xs * xs + ys * ys + zs * zs)
    depth = -(m * r) * (1.0 - 1.0 / math.sqrt(q))
    return max(depth, FAR_DEPTH), gx / rg, gy / rg, gz / rg


def radial(x: float, y: float, z: float, k: tuple) -> tuple[float, float, float, float]:
    """The paper's radial penetration (see module docstring for the root choice)."""
    ix2, iy2, iz2 = k[0], k[1], k[2]
    gx = x * ix2
    gy = y * iy2
    gz = z * iz2
    q = x * gx + y * gy + z * gz
    if not Q_CENTRE < q < Q_FAR:
        return _special(x, y, z, k, q)
    gg = gx * gx + gy * gy + gz * gz
    rg = math.sqrt(gg)
    h = gx * gx * ix2 + gy * gy * iy2 + gz * gz * iz2
    # alpha d^2 + 2 beta d + gamma = 0 along the unit normal: alpha = h/gg, beta = rg,
    # gamma = q - 1. Push-out root -gamma / (beta + sqrt(beta^2 - alpha gamma)).
    disc = gg - h * (q - 1.0) / gg
    if disc >= 0.0:
        d = (1.0 - q) / (rg + math.sqrt(disc))
    else:  # far outside a flat model: the normal line misses it
        d = -math.sqrt(x * x + y * y + z * z) * (1.0 - 1.0 / math.sqrt(q))
    return d, gx / rg, gy / rg, gz / rg


def _lower_bound(ux: float, uy: float, uz: float, kx: float, ky: float, kz: float, k: tuple):
    """A w = t + min s^2 with F(w) >= 0 (left of the root), or None in the degenerate case."""
    sx, sy, sz, ex, ey, ez = k[7], k[8], k[9], k[10], k[11], k[12]
    pole = (kx > 0.0 and ex == 0.0) or (ky > 0.0 and ey == 0.0) or (kz > 0.0 and ez == 0.0)
    if not pole:
        f0 = -1.0
        if ex > 0.0:
            f0 += kx / (ex * ex)
        if ey > 0.0:
            f0 += ky / (ey * ey)
        if ez > 0.0:
            f0 += kz / (ez * ez)
        if f0 <= 0.0:
            return None
    # Each term alone reaches 1 at w = s_i u_i - e_i; all together at sqrt(sum k) - max e.
    return max(0.0, sx * ux - ex, sy * uy - ey, sz * uz - ez, math.sqrt(kx + ky + kz) - k[14])


def _degenerate(x: float, y: float, z: float, k: tuple) -> tuple[float, float, float, float]:
    """Closest point off the smallest-axis plane (t = -min s^2); p has no smallest-axis part."""
    sx, sy, sz, ex, ey, ez = k[7], k[8], k[9], k[10], k[11], k[12]
    cnx, cny, cnz = k[4], k[5], k[6]
    gx = x / ex if ex > 0.0 else 0.0
    gy = y / ey if ey > 0.0 else 0.0
    gz = z / ez if ez > 0.0 else 0.0
    r = 1.0 - (sx * gx) ** 2 - (sy * gy) ** 2 - (sz * gz) ** 2
    gm = math.sqrt(max(r, 0.0)) / k[3]  # gradient component along the smallest axis
    gx += gm * cnx
    gy += gm * cny
    gz += gm * cnz
    # closest point c_i = s_i^2 g_i; depth = |p - c|
    dx, dy, dz = x - sx * sx * gx, y - sy * sy * gy, z - sz * sz * gz
    rg = math.sqrt(gx * gx + gy * gy + gz * gz)
    return math.sqrt(dx * dx + dy * dy + dz * dz), gx / rg, gy / rg, gz / rg


def _solve(
    x: float, y: float, z: float, k: tuple, q: float, w: float, max_iter: int
) -> tuple[float, float, float, float]:
    """Newton on F(w) from the start ``w`` (any), safeguarded; then depth and normal."""
    ux, uy, uz = abs(x), abs(y), abs(z)
    sx, sy, sz, ex, ey, ez = k[7], k[8], k[9], k[10], k[11], k[12]
    kx, ky, kz = (sx * ux) ** 2, (sy * uy) ** 2, (sz * uz) ** 2
    ax, ay, az = w + ex, w + ey, w + ez
    tx = kx / (ax * ax) if kx > 0.0 else 0.0
    ty = ky / (ay * ay) if ky > 0.0 else 0.0
    tz = kz / (az * az) if kz > 0.0 else 0.0
    f = tx + ty + tz - 1.0
    if f < 0.0:  # right of the root: one Newton step lands left of it (convexity), clamp
        lo = _lower_bound(ux, uy, uz, kx, ky, kz, k)
        if lo is None:
            return _degenerate(x, y, z, k)
        fp = (tx / ax if kx > 0.0 else 0.0) + (ty / ay if ky > 0.0 else 0.0)
        fp += tz / az if kz > 0.0 else 0.0
        w = max(w + f / (2.0 * fp), lo)
    for _ in range(max_iter):  # Newton from the left: monotone
        ax, ay, az = w + ex, w + ey, w + ez
        tx = kx / (ax * ax) if kx > 0.0 else 0.0
        ty = ky / (ay * ay) if ky > 0.0 else 0.0
        tz = kz / (az * az) if kz > 0.0 else 0.0
        f = tx + ty + tz - 1.0
        if f <= 0.0:
            break
        fp = (tx / ax if kx > 0.0 else 0.0) + (ty / ay if ky > 0.0 else 0.0)
        fp += tz / az if kz > 0.0 else 0.0
        dw = f / (2.0 * fp)
        w += dw
        if dw <= 1e-15 * w:
            break
    ax, ay, az = w + ex, w + ey, w + ez
    gx = ux / ax if kx > 0.0 else 0.0
    gy = uy / ay if ky > 0.0 else 0.0
    gz = uz / az if kz > 0.0 else 0.0
    rg = math.sqrt(gx * gx + gy * gy + gz * gz)
    depth = (k[13] - w) * rg  # -t |grad| at the closest point
    return (
        depth,
        math.copysign(gx / rg, x),
        math.copysign(gy / rg, y),
        math.copysign(gz / rg, z),
    )


def exact(x: float, y: float, z: float, k: tuple) -> tuple[float, float, float, float]:
    """True closest surface point: signed distance and the outward normal there."""
    q = x * x * k[0] + y * y * k[1] + z * z * k[2]
    if not Q_CENTRE < q < Q_FAR:
        return _special(x, y, z, k, q)
    return _solve(x, y, z, k, q, k[13], EXACT_MAX_ITER)


def newton(x: float, y: float, z: float, k: tuple) -> tuple[float, float, float, float]:
    """Radial estimate refined by at most NEWTON_STEPS safeguarded Newton steps on F."""
    d, nx, ny, nz = radial(x, y, z, k)
    q = x * x * k[0] + y * y * k[1] + z * z * k[2]
    if not Q_CENTRE < q < Q_FAR:
        return d, nx, ny, nz
    # Radial surface point c = p + d n; there p - c = t grad(c), so t = -d / |grad(c)|.
    cx, cy, cz = x + d * nx, y + d * ny, z + d * nz
    gx, gy, gz = cx * k[0], cy * k[1], cz * k[2]
    w = k[13] - d / math.sqrt(gx * gx + gy * gy + gz * gz)
    if not w > 0.0:  # outside the domain of F (cannot happen near the surface): start at t = 0
        w = k[13]
    return _solve(x, y, z, k, q, w, NEWTON_STEPS)


# ----------------------------------------------------------------------------- batch (numpy)
def radial_batch(p: NDArray[np.float64], s: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
    """Vectorised :func:`radial` over patient-frame points (N, 3); semi-axes s (3,).

    Returns depths (N,) and unit normals (N, 3); non-finite points give NaN depth, zero normal.
    """
    p = np.asarray(p, dtype=float)
    inv2 = 1.0 / (s * s)
    with np.errstate(all="ignore"):
        g = p * inv2
        q = np.einsum("ij,ij->i", p, g)
        gg = np.einsum("ij,ij->i", g, g)
        rg = np.sqrt(gg)
        h = np.einsum("ij,ij->i", g * g, np.broadcast_to(inv2, g.shape))
        disc = gg - h * (q - 1.0) / gg
        near = (1.0 - q) / (rg + np.sqrt(np.maximum(disc, 0.0)))
        miss = -np.sqrt(np.einsum("ij,ij->i", p, p)) * (1.0 - 1.0 / np.sqrt(q))
        depth = np.where(disc >= 0.0, near, miss)
        n = g / rg[:, None]
    _fix_special(p, s, q, depth, n)
    return depth, n


def _fix_special(p: NDArray, s: NDArray, q: NDArray, depth: NDArray, n: NDArray) -> None:
    """Centre, far and non-finite points in place, as the scalar :func:`_special` does."""
    special = ~((q > Q_CENTRE) & (q < Q_FAR))
    if not np.any(special):
        return
    k = constants(*(float(v) for v in s))
    for i in np.flatnonzero(special):
        try:
            depth[i], *n[i] = _special(*(float(v) for v in p[i]), k, float(q[i]))
        except ValueError:
            depth[i], n[i] = math.nan, 0.0


BATCH = {"radial": radial_batch}

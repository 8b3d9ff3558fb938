"""A small synthetic abdominal phantom inside the patient ellipsoid, for the sim ultrasound.

Placed in the patient frame of the paper (origin at the ellipsoid centre, at the xiphoid along
the body; x head to feet, y up, z from the patient's left to right) *relative to the
ellipsoid*: a position is (x in m along the body, y as a fraction of the vertical semi-axis b,
z as a fraction of the lateral semi-axis a), so the anatomy stays inside any fitted torso;
sizes are in metres. Model no more than the scene needs:

- layers under the skin by depth below it: skin, subcutaneous fat, abdominal wall muscle, then
  deep soft tissue (bowel and mesentery, as an average);
- organs as axis-aligned ellipsoids (liver, the right kidney with its bright central sinus);
- tubes: a vessel (the aorta, anechoic with bright walls), bone (a rib under the right costal
  margin and the spine): a bright surface and almost no transmission, so a shadow beneath.

Each region has a material: ``echo`` (mean backscatter amplitude relative to soft tissue, 1),
``boundary`` (amplitude of the specular echo where a beam enters or leaves it) and
``attenuation_db_cm_mhz`` (one way). Later shapes in the lists lie over earlier ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from humantele.haptics.ellipsoid import Ellipsoid
from humantele.video.sim_config import Material, Organ, PhantomConfig, Tube  # noqa: F401 (their home before)
from humantele.video.speckle import SpeckleField

Placement = tuple[float, float, float]


LAYERS = ("outside", "skin", "fat", "muscle", "tissue")


@dataclass(frozen=True)
class _Shape:
    label: int
    center: tuple[float, float, float]  # patient frame, m
    inv_axes: tuple[float, float, float] | None  # ellipsoid: 1 / semi-axes
    direction: tuple[float, float, float] | None  # tube: unit axis
    radius2: float
    half_length: float
    bound: float  # radius of a sphere about the centre that holds the shape


Points = tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]


class Phantom:
    """The phantom placed in one patient ellipsoid: region labels and material tables.

    Points are given as three float32 arrays (x, y, z) in the patient frame, m.
    ``labels(points)`` gives each point its region: 0 outside the body, 1 skin, 2 fat,
    3 muscle, 4 deep tissue, then organs and tubes in the config's order (``names[label]``).
    ``echo``, ``boundary``, ``attenuation`` are float32 tables by label.
    """

    def __init__(self, config: PhantomConfig, patient: Ellipsoid, seed: int = 0) -> None:
        self.config = c = config
        self.semi_axes = tuple(float(v) for v in patient.semi_axes)
        _, b, a = self.semi_axes
        scale = np.array([1.0, b, a])
        mats = [Material(echo=0.0, attenuation_db_cm_mhz=0.0), c.skin, c.fat, c.muscle, c.tissue]
        self.names = list(LAYERS)
        shapes: list[_Shape] = []
        for organ in c.organs:
            axes = np.asarray(organ.semi_axes_m, dtype=float)
            center = tuple(float(v) for v in np.asarray(organ.center) * scale)
            inv = tuple(float(v) for v in 1.0 / axes)
            shapes.append(_Shape(len(self.names), center, inv, None, 0.0, 0.0, float(axes.max())))
            self.names.append(organ.name)
            mats.append(organ)
        for tube in c.tubes:
            d = np.asarray(tube.direction, dtype=float)
            d = tuple(float(v) for v in d / np.linalg.norm(d))
            center = tuple(float(v) for v in np.asarray(tube.point) * scale)
            bound = float(np.hypot(tube.half_length_m, tube.radius_m))
            shapes.append(
                _Shape(
                    len(self.names), center, None, d, tube.radius_m**2, tube.half_length_m, bound
                )
            )
            self.names.append(tube.name)
            mats.append(tube)
        self._shapes = shapes
        assert len(self.names) <= 256, "PhantomConfig holds at most MAX_SHAPES shapes"
        ell = [sh for sh in shapes if sh.inv_axes is not None]
        tub = [sh for sh in shapes if sh.inv_axes is None]
        self._ell = (
            np.array([sh.label for sh in ell], dtype=int),
            np.array([sh.center for sh in ell], dtype=float).reshape(-1, 3),
            np.array([sh.inv_axes for sh in ell], dtype=float).reshape(-1, 3),
        )
        self._tub = (
            np.array([sh.label for sh in tub], dtype=int),
            np.array([sh.center for sh in tub], dtype=float).reshape(-1, 3),
            np.array([sh.direction for sh in tub], dtype=float).reshape(-1, 3),
            np.array([sh.radius2 for sh in tub], dtype=float),
            np.array([sh.half_length for sh in tub], dtype=float),
        )
        self.echo = np.array([m.echo for m in mats], dtype=np.float32)
        self.boundary = np.array([m.boundary for m in mats], dtype=np.float32)
        self.attenuation = np.array([m.attenuation_db_cm_mhz for m in mats], dtype=np.float32)
        self.texture = np.array([m.texture for m in mats], dtype=np.float32)
        self._blobs = SpeckleField(c.texture_m, 0.0, seed + 7) if self.texture.any() else None
        self._layer_depths = [float(v) for v in np.cumsum([c.skin_m, c.fat_m, c.muscle_m])]

    def blobs(self, points: Points) -> NDArray[np.float32] | None:
        """The smooth Gaussian field (std 1, grain ``texture_m``, fixed in the tissue) that
        modulates the echo of textured materials by ``exp(texture * field)``, at patient-frame
        points; None when no material is textured."""
        return None if self._blobs is None else self._blobs.gaussian(points)

    def organ(self, name: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(centre (3,) m, semi-axes (3,) m) of organ ``name`` in the patient frame."""
        i = self.names.index(name) if name in self.names else -1
        for s in self._shapes:
            if s.label == i and s.inv_axes is not None:
                return np.array(s.center), 1.0 / np.array(s.inv_axes)
        raise KeyError(f"{name!r} is not an organ (an ellipsoid) of the phantom")

    def depth_below_skin(self, points: Points) -> NDArray[np.float32]:
        """First-order distance (m) of patient-frame points below the ellipsoid's skin:
        ``(1 - r^2) / |grad r^2|``; > 0 inside, < 0 outside (exact on the surface)."""
        r2 = None
        g2 = None
        for p, s in zip(points, self.semi_axes, strict=True):
            u = p * np.float32(1.0 / s)
            u2 = u * u
            r2 = u2 if r2 is None else r2 + u2
            g2 = (
                u2 * np.float32(1.0 / (s * s))
                if g2 is None
                else g2 + u2 * np.float32(1.0 / (s * s))
            )
        grad = np.sqrt(g2)
        grad *= 2.0
        np.maximum(grad, 1e-6, out=grad)
        return (1.0 - r2) / grad

    def labels(
        self,
        points: Points,
        near: tuple[NDArray[np.float64], NDArray[np.float64], float] | None = None,
    ) -> NDArray[np.int16]:
        """Region label of each patient-frame point. ``near`` = (point, unit normal, reach):
        the points all lie in that plane within ``reach`` (m) of that point; shapes that
        cannot touch that disc are skipped (a speed-up only)."""
        depth = self.depth_below_skin(points)
        lab = np.full(depth.shape, 4, dtype=np.int16)
        d1, d2, d3 = self._layer_depths
        lab[depth < d3] = 3
        lab[depth < d2] = 2
        lab[depth < d1] = 1
        outside = depth < 0.0
        x, y, z = points
        for s in self._shapes:
            if near is not None:
                rel = np.asarray(s.center) - near[0]
                if (
                    abs(float(rel @ near[1])) > s.bound
                    or float(np.linalg.norm(rel)) > near[2] + s.bound
                ):
                    continue
            lab[self._hit(s, x, y, z)] = s.label
        lab[outside] = 0
        return lab

    @staticmethod
    def _hit(s: _Shape, x, y, z) -> NDArray[np.bool_]:
        cx, cy, cz = s.center
        dx, dy, dz = x - np.float32(cx), y - np.float32(cy), z - np.float32(cz)
        if s.inv_axes is not None:
            ia, ib, ic = (np.float32(v) for v in s.inv_axes)
            dx *= ia
            dy *= ib
            dz *= ic
            return dx * dx + dy * dy + dz * dz < 1.0
        ux, uy, uz = (np.float32(v) for v in s.direction)
        along = dx * ux + dy * uy + dz * uz
        r2 = dx * dx + dy * dy + dz * dz - along * along
        return (r2 < s.radius2) & (np.abs(along) < s.half_length)

    # ------------------------------------------------------------------ along rays
    def along_rays(
        self,
        starts: NDArray[np.float64],
        dirs: NDArray[np.float64],
        ranges: NDArray[np.float32],
        target: str | None = None,
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.bool_] | None]:
        """Region labels and :meth:`depth_below_skin` at the points ``starts[b] + ranges[j] *
        dirs[b]`` (patient frame, m; ``starts``, ``dirs`` (B, 3), ``dirs`` unit, ``ranges``
        (S,) increasing): ((B, S) uint8 labels as :meth:`labels` gives, (B, S) float32 m,
        and with ``target`` (an organ's name) :meth:`inside_along` of it, else None).

        The same answer as :meth:`labels` of those points (to float rounding on a surface), at
        a fraction of its cost: the skin's depth is a ratio of two quadratics in the range
        along each ray, and each organ or tube is the interval of ranges between the ray's
        entry and exit (two roots per ray), painted in its rows of the grid."""
        ranges = np.asarray(ranges, dtype=np.float32)
        inv = 1.0 / np.asarray(self.semi_axes)
        # r^2 = |p / s|^2 and |grad r^2|^2 / 4 = |p / s^2|^2, each a quadratic along the ray.
        fs, ds = starts * inv, dirs * inv
        r2 = _quadratic((ds * ds).sum(1), 2.0 * (fs * ds).sum(1), (fs * fs).sum(1), ranges)
        fs, ds = fs * inv, ds * inv
        grad = _quadratic((ds * ds).sum(1), 2.0 * (fs * ds).sum(1), (fs * fs).sum(1), ranges)
        np.sqrt(grad, out=grad)
        grad *= 2.0
        np.maximum(grad, 1e-6, out=grad)
        depth = np.subtract(1.0, r2, out=r2)
        depth /= grad
        d1, d2, d3 = (np.float32(v) for v in self._layer_depths)
        inside_body = depth >= 0.0
        lab = inside_body.view(np.uint8).copy()
        for d in (d1, d2, d3):
            lab += depth >= d
        t = None if target is None else self._organ_label(target)
        inside = None if t is None else np.zeros(lab.shape, dtype=np.uint8)
        shapes = self._intervals(starts, dirs)
        if shapes:
            # Each shape's first and last sample inside, per ray, all at once.
            j0 = np.searchsorted(ranges, np.stack([lo for _, lo, _ in shapes]), side="right")
            j1 = np.searchsorted(ranges, np.stack([hi for _, _, hi in shapes]), side="left")
            hits = (j1 > j0).any(axis=1)
            for k in np.flatnonzero(hits):
                label = shapes[k][0]
                self._paint_rows(lab, label, j0[k], j1[k])
                if inside is not None and label == t:
                    self._paint_rows(inside, 1, j0[k], j1[k])
            if hits.any():
                lab *= inside_body  # nothing outside the body, whatever a tube does there
        return lab, depth, None if inside is None else inside.view(np.bool_)

    def inside_along(
        self,
        name: str,
        starts: NDArray[np.float64],
        dirs: NDArray[np.float64],
        ranges: NDArray[np.float32],
    ) -> NDArray[np.bool_]:
        """:meth:`inside` at the points of :meth:`along_rays`: (B, S) bool."""
        i = self._organ_label(name)
        out = np.zeros((len(starts), len(ranges)), dtype=np.uint8)
        lo, hi = self._intervals(starts, dirs, only=i)[0][1:]
        self._paint(out, 1, lo, hi, np.asarray(ranges, dtype=np.float32), None)
        return out.view(np.bool_)

    def _organ_label(self, name: str) -> int:
        i = self.names.index(name) if name in self.names else -1
        if not any(s.label == i and s.inv_axes is not None for s in self._shapes):
            raise KeyError(f"{name!r} is not an organ (an ellipsoid) of the phantom")
        return i

    def _intervals(self, starts, dirs, only: int | None = None) -> list[tuple[int, Any, Any]]:
        """(label, lo, hi) of every organ then tube (or of label ``only``), in the order they
        are painted: lo, hi (B,) bound the open interval of ranges where each ray is inside
        the shape (empty: lo >= hi)."""
        out = []
        labels, centers, inv = self._ell
        if labels.size and (only is None or only in labels):
            w = (starts[None, :, :] - centers[:, None, :]) * inv[:, None, :]  # (E, B, 3)
            d = dirs[None, :, :] * inv[:, None, :]
            lo, hi = _roots((d * d).sum(2), 2.0 * (w * d).sum(2), (w * w).sum(2) - 1.0)
            out += list(zip(labels.tolist(), lo, hi, strict=True))
        labels, centers, axis, radius2, half = self._tub
        if labels.size and (only is None or only in labels):
            w = starts[None, :, :] - centers[:, None, :]  # (T, B, 3)
            a0 = (w * axis[:, None, :]).sum(2)  # along the axis: a0 + r a1
            a1 = dirs @ axis.T  # (B, T)
            a1 = a1.T
            a = 1.0 - a1 * a1  # |dirs| = 1
            b = 2.0 * ((w * dirs[None]).sum(2) - a0 * a1)
            c = (w * w).sum(2) - a0 * a0 - radius2[:, None]
            lo, hi = _roots(a, b, c)
            # |a0 + r a1| < half_length
            h = half[:, None]
            flat = np.abs(a1) < 1e-12
            with np.errstate(divide="ignore", invalid="ignore"):
                r1, r2 = (-h - a0) / a1, (h - a0) / a1
            inside = np.abs(a0) < h
            alo = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(r1, r2))
            ahi = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(r1, r2))
            lo, hi = np.maximum(lo, alo), np.minimum(hi, ahi)
            out += list(zip(labels.tolist(), lo, hi, strict=True))
        return out if only is None else [o for o in out if o[0] == only]

    @staticmethod
    def _paint(lab, label: int, lo, hi, ranges, inside_body) -> None:
        """Set ``lab[b, j] = label`` where lo[b] < ranges[j] < hi[b] (and inside the body)."""
        j0 = np.searchsorted(ranges, lo, side="right")
        j1 = np.searchsorted(ranges, hi, side="left")
        Phantom._paint_rows(lab, label, j0, j1, inside_body)

    @staticmethod
    def _paint_rows(lab, label: int, j0, j1, inside_body=None) -> None:
        """Set ``lab[b, j] = label`` for j0[b] <= j < j1[b] (and inside the body)."""
        rows = np.flatnonzero(j1 > j0)
        if rows.size == 0:
            return
        b0, b1 = int(rows[0]), int(rows[-1]) + 1
        c0, c1 = int(j0[b0:b1].min()), int(j1[b0:b1].max())
        j = np.arange(c0, c1)
        hit = (j >= j0[b0:b1, None]) & (j < j1[b0:b1, None])
        if inside_body is not None:
            hit &= inside_body[b0:b1, c0:c1]
        lab[b0:b1, c0:c1][hit] = label

    def inside(self, name: str, points: Points) -> NDArray[np.bool_]:
        """Which patient-frame points lie inside organ ``name`` (its whole ellipsoid, whatever
        lies over it)."""
        i = self.names.index(name) if name in self.names else -1
        for s in self._shapes:
            if s.label == i and s.inv_axes is not None:
                return self._hit(s, *points)
        raise KeyError(f"{name!r} is not an organ (an ellipsoid) of the phantom")


def _quadratic(a, b, c, r: NDArray[np.float32]) -> NDArray[np.float32]:
    """``a r^2 + b r + c`` on the (B, S) grid of per-ray coefficients (B,) and ranges (S,)."""
    a32, b32, c32 = (np.asarray(v, dtype=np.float32)[:, None] for v in (a, b, c))
    q = a32 * (r * r)[None, :]
    q += b32 * r[None, :]
    q += c32
    return q


def _roots(a, b, c) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Where ``a r^2 + b r + c < 0`` (a >= 0), per ray: (lo, hi), empty as (inf, -inf); a
    ray along a tube's axis (a = 0) is inside everywhere or nowhere."""
    disc = b * b - 4.0 * a * c
    ok = (disc > 0.0) & (a > 1e-12)
    root = np.sqrt(np.where(ok, disc, 0.0))
    den = np.where(ok, 2.0 * a, 1.0)
    lo = np.where(ok, (-b - root) / den, np.inf)
    hi = np.where(ok, (-b + root) / den, -np.inf)
    along = a <= 1e-12  # parallel to the axis: inside everywhere when c < 0
    lo = np.where(along & (c < 0.0), -np.inf, lo)
    hi = np.where(along & (c < 0.0), np.inf, hi)
    return lo, hi

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

    def inside(self, name: str, points: Points) -> NDArray[np.bool_]:
        """Which patient-frame points lie inside organ ``name`` (its whole ellipsoid, whatever
        lies over it)."""
        i = self.names.index(name) if name in self.names else -1
        for s in self._shapes:
            if s.label == i and s.inv_axes is not None:
                return self._hit(s, *points)
        raise KeyError(f"{name!r} is not an organ (an ellipsoid) of the phantom")

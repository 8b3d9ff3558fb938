"""Probe tool definitions: where the retro-reflective marker spheres sit on the probe.

A tool file (packaged: ``humantele/defaults/tools/*.toml``; or a file of yours) gives, in
millimetres (the edge of the system), the marker sphere centres in the **probe frame**, the
sphere radius, the tip (centre of the transducer face) and the axis the face points along.
Inside, :class:`ToolDefinition` exposes the same in metres. The probe frame of the default
tool: origin near the marker centroid, x along the transducer array, y across it
(elevation), z along the handle towards the cable; the face points along -z.

A layout that could be confused with itself (a rigid motion or a reflection that maps the
markers, or any ``min_visible`` of them, onto a different assignment of markers) is refused
when loaded, because tracking it could give a wrong pose without knowing.
"""

from __future__ import annotations

import itertools
from functools import cached_property
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, field_validator, model_validator

from humantele.config import ConfigError, ConfigModel, load_config, named_config_path

DEFAULT_TOOL = "probe_default"


def kabsch(
    src: NDArray[np.float64], dst: NDArray[np.float64], allow_reflection: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Best rigid fit ``dst ~ R @ src + t`` for batches (..., N, 3); returns (R, t, rms).

    ``R`` has det +1 unless ``allow_reflection`` (then det may be -1). Units of the input.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    cs = src.mean(axis=-2, keepdims=True)
    cd = dst.mean(axis=-2, keepdims=True)
    h = np.swapaxes(src - cs, -1, -2) @ (dst - cd)
    u, _s, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.swapaxes(vt, -1, -2) @ np.swapaxes(u, -1, -2)))
    if allow_reflection:
        d = np.ones_like(d)
    corr = np.broadcast_to(np.eye(3), h.shape).copy()
    corr[..., 2, 2] = np.where(d == 0, 1.0, d)
    r = np.swapaxes(vt, -1, -2) @ corr @ np.swapaxes(u, -1, -2)
    t = cd[..., 0, :] - np.einsum("...ij,...j->...i", r, cs[..., 0, :])
    fitted = np.einsum("...ij,...nj->...ni", r, src) + t[..., None, :]
    rms = np.sqrt(np.mean(np.sum((fitted - dst) ** 2, axis=-1), axis=-1))
    return r, t, rms


def self_match_residual(
    markers: NDArray[np.float64], k: int
) -> tuple[float, tuple[tuple[int, ...], tuple[int, ...], bool]]:
    """Smallest RMS (same units) of a non-identity assignment of ``k`` markers onto ``k``
    markers, by a rigid motion (and, for the whole set, also by a reflection).

    Returns (rms, (source indices, target indices, reflected)). A small value means some
    marker subset looks like another one: the layout is ambiguous.
    """
    m = len(markers)
    srcs, dsts = [], []
    for s in itertools.combinations(range(m), k):
        for t in itertools.combinations(range(m), k):
            for p in itertools.permutations(t):
                if s == p:
                    continue
                srcs.append(s)
                dsts.append(p)
    best = (np.inf, ((), (), False))
    if not srcs:
        return best
    src_i = np.array(srcs)
    dst_i = np.array(dsts)
    for reflected in (False, True) if k == m else (False,):
        _r, _t, rms = kabsch(markers[src_i], markers[dst_i], allow_reflection=reflected)
        j = int(np.argmin(rms))
        if rms[j] < best[0]:
            best = (float(rms[j]), (tuple(srcs[j]), tuple(dsts[j]), reflected))
    return best


class ToolDefinition(ConfigModel):
    """A marker tool (probe). Fields in mm (file format); properties in m (use inside)."""

    name: str = "default ultrasound probe marker tree"
    markers_mm: list[list[float]] = Field(
        default_factory=lambda: [
            [-26.0, 18.0, 2.0],
            [-23.0, -30.0, 3.0],
            [9.0, -31.0, -10.0],
            [41.0, 42.0, 3.0],
        ],
        description="marker sphere centres in the probe frame, mm; at least 4",
    )
    sphere_radius_mm: float = Field(5.5, gt=0.5, le=30.0)
    tip_mm: list[float] = Field(
        default_factory=lambda: [0.0, 0.0, -150.0],
        description="centre of the transducer face in the probe frame, mm",
    )
    face_axis: list[float] = Field(
        default_factory=lambda: [0.0, 0.0, -1.0],
        description="direction the transducer face points, probe frame (normalised on load)",
    )
    min_visible: int = Field(3, ge=3, description="fewest matched markers that give a pose")
    min_separation_mm: float = Field(
        20.0, gt=0, description="closest two sphere centres may be (else blobs merge)"
    )
    min_asymmetry_mm: float = Field(
        3.0,
        gt=0,
        description="smallest RMS misfit any non-identity marker assignment must have",
    )

    @field_validator("markers_mm")
    @classmethod
    def _markers_shape(cls, v: list[list[float]]) -> list[list[float]]:
        if len(v) < 4:
            raise ValueError(f"a tool needs at least 4 markers, got {len(v)}")
        if len(v) > 8:
            raise ValueError(f"at most 8 markers are supported, got {len(v)}")
        for i, p in enumerate(v):
            if len(p) != 3 or not all(np.isfinite(p)):
                raise ValueError(f"marker {i} must be 3 finite numbers (x, y, z mm), got {p}")
        return v

    @field_validator("tip_mm", "face_axis")
    @classmethod
    def _vec3(cls, v: list[float]) -> list[float]:
        if len(v) != 3 or not all(np.isfinite(v)):
            raise ValueError(f"must be 3 finite numbers, got {v}")
        return v

    @model_validator(mode="after")
    def _layout_is_usable(self) -> ToolDefinition:
        if np.linalg.norm(self.face_axis) < 1e-9:
            raise ValueError("face_axis must be non-zero")
        m = np.asarray(self.markers_mm, dtype=float)
        n = len(m)
        if self.min_visible > n:
            raise ValueError(f"min_visible={self.min_visible} exceeds the {n} markers")
        d = np.linalg.norm(m[:, None] - m[None], axis=-1)[np.triu_indices(n, 1)]
        if d.min() < self.min_separation_mm:
            raise ValueError(
                f"markers closer than min_separation_mm={self.min_separation_mm} "
                f"(closest pair {d.min():.1f} mm): their images would merge"
            )
        for k in range(self.min_visible, n + 1):
            rms, (src, dst, refl) = self_match_residual(m, k)
            if rms < self.min_asymmetry_mm:
                how = "a reflection" if refl else "a rigid motion"
                raise ValueError(
                    f"ambiguous marker layout: {how} maps markers {list(src)} onto {list(dst)} "
                    f"within {rms:.2f} mm RMS (needs >= min_asymmetry_mm="
                    f"{self.min_asymmetry_mm}); make the layout less symmetric"
                )
        return self

    @cached_property
    def markers(self) -> NDArray[np.float64]:
        """(M, 3) marker sphere centres in the probe frame, m."""
        return np.asarray(self.markers_mm, dtype=float) / 1000.0

    @property
    def sphere_radius(self) -> float:
        """Marker sphere radius, m."""
        return self.sphere_radius_mm / 1000.0

    @property
    def tip(self) -> NDArray[np.float64]:
        """Centre of the transducer face in the probe frame, m."""
        return np.asarray(self.tip_mm, dtype=float) / 1000.0

    @property
    def face_direction(self) -> NDArray[np.float64]:
        """Unit vector the face points along, probe frame."""
        a = np.asarray(self.face_axis, dtype=float)
        return a / np.linalg.norm(a)


def load_tool(name_or_path: str | Path = DEFAULT_TOOL) -> ToolDefinition:
    """A tool by name (packaged ``humantele/defaults/tools/NAME.toml``) or from a file path."""
    p = named_config_path("tools", name_or_path, "tool")
    if not p.exists():
        raise ConfigError(f"{p}: no such tool definition file")
    return load_config(ToolDefinition, p)

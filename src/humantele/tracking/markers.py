"""Marker correspondence and pose: candidate 3D points (camera frame) -> pose of the probe.

:func:`estimate_pose` is a pure function. It searches the assignments of candidate points to
the tool's markers whose pairwise distances agree with the tool geometry (so extra blobs and
up to ``M - min_visible`` missing markers are tolerated), fits each by SVD (Kabsch), and keeps
the one with the most markers and then the smallest residual. It refuses (returns None) when
the best fit's residual is too large, or when another assignment with as many markers gives a
different pose just as well (ambiguous): never a wrong pose given silently.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from humantele.geometry import Pose, matrix_to_quat
from humantele.tracking.tool import ToolDefinition, kabsch

Status = Literal["tracked", "lost", "ambiguous"]


@dataclass(frozen=True)
class MatchParams:
    """Tolerances of the correspondence search, m."""

    distance_tol: float = 0.004  # |measured - model| pairwise distance allowed, m
    max_rms: float = 0.0015  # largest accepted RMS residual of the fit, m
    max_marker_error: float = 0.003  # largest accepted single-marker residual, m
    distinct_pose: float = 0.003  # two fits differ if some marker moves more than this, m
    max_candidates: int = 24  # more candidate points than this: keep the first ones


@dataclass(frozen=True)
class PoseEstimate:
    """Pose of the probe in the camera frame from matched markers.

    ``matched[i]`` is the index in the input points of tool marker ``i``, or -1 if missing.
    ``residual_m`` is the RMS distance (m) between the fitted model and the matched points.
    """

    T_camera_probe: Pose
    residual_m: float
    matched: tuple[int, ...]

    @property
    def n_matched(self) -> int:
        return sum(1 for i in self.matched if i >= 0)


@dataclass(frozen=True)
class MatchResult:
    """Outcome of a match: status, the estimate when tracked, and the number of fits tried."""

    status: Status
    estimate: PoseEstimate | None
    n_hypotheses: int


def _assignments(
    d_meas: NDArray[np.float64], d_model: NDArray[np.float64], tol: float, min_visible: int
) -> list[tuple[int, ...]]:
    """All assignments (tuple per model marker: candidate index or -1) that keep every pair of
    assigned markers within ``tol`` of the model distance and match >= min_visible markers."""
    m = d_model.shape[0]
    n = d_meas.shape[0]
    ok = np.abs(d_meas[None, None, :, :] - d_model[:, :, None, None]) <= tol  # (m, m, n, n)
    max_missing = m - min_visible
    out: list[tuple[int, ...]] = []
    current: list[int] = []

    def rec(i: int, missing: int) -> None:
        if i == m:
            out.append(tuple(current))
            return
        for c in range(n):
            if c in current:
                continue
            if all(a < 0 or ok[j, i, a, c] for j, a in enumerate(current)):
                current.append(c)
                rec(i + 1, missing)
                current.pop()
        if missing < max_missing:
            current.append(-1)
            rec(i + 1, missing + 1)
            current.pop()

    rec(0, 0)
    return out


def match_markers(
    points: ArrayLike, tool: ToolDefinition, params: MatchParams | None = None
) -> MatchResult:
    """Match candidate marker centres (N, 3) in the camera frame (m) to ``tool``."""
    p = params or MatchParams()
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)][: p.max_candidates]
    model = tool.markers
    if len(pts) < tool.min_visible:
        return MatchResult("lost", None, 0)
    d_meas = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    d_model = np.linalg.norm(model[:, None] - model[None], axis=-1)
    hyps = _assignments(d_meas, d_model, p.distance_tol, tool.min_visible)
    if not hyps:
        return MatchResult("lost", None, 0)
    fits: list[tuple[int, float, tuple[int, ...], NDArray, NDArray]] = []
    by_count: dict[int, list[tuple[int, ...]]] = {}
    for h in hyps:
        by_count.setdefault(sum(1 for a in h if a >= 0), []).append(h)
    for k, group in by_count.items():
        idx = np.array(group)
        mask = idx >= 0
        src = np.stack([model[mask[g]] for g in range(len(group))])
        dst = np.stack([pts[idx[g][mask[g]]] for g in range(len(group))])
        r, t, rms = kabsch(src, dst)
        err = np.linalg.norm(np.einsum("gij,gnj->gni", r, src) + t[:, None] - dst, axis=-1)
        good = (rms <= p.max_rms) & (err.max(axis=1) <= p.max_marker_error)
        for g in np.flatnonzero(good):
            fits.append((k, float(rms[g]), group[g], r[g], t[g]))
    if not fits:
        return MatchResult("lost", None, len(hyps))
    fits.sort(key=lambda f: (-f[0], f[1]))
    k0, rms0, h0, r0, t0 = fits[0]
    model_0 = model @ r0.T + t0
    for k, _rms, _h, r, t in fits[1:]:
        if k < k0:
            break
        if np.max(np.linalg.norm(model @ r.T + t - model_0, axis=1)) > p.distinct_pose:
            return MatchResult("ambiguous", None, len(hyps))
    est = PoseEstimate(Pose(t0, matrix_to_quat(r0)), rms0, h0)
    return MatchResult("tracked", est, len(hyps))


def estimate_pose(
    points: ArrayLike, tool: ToolDefinition, params: MatchParams | None = None
) -> PoseEstimate | None:
    """Pose of the probe in the camera frame from candidate marker centres (N, 3), m.

    Points may be in any order, include outliers and miss up to ``M - tool.min_visible``
    markers. Returns None when no fit is trustworthy (too few markers, residual too large,
    or ambiguous).
    """
    return match_markers(points, tool, params).estimate


def refine_pose(
    T_camera_probe: Pose,
    model: ArrayLike,
    points: ArrayLike,
    sigma_lateral: ArrayLike,
    sigma_range: float,
    iterations: int = 3,
) -> Pose:
    """Maximum-likelihood refinement for a camera that measures bearing well and range poorly.

    ``model`` (K, 3) markers in the probe frame and ``points`` (K, 3) their measured centres in
    the camera frame (m), matched row by row. Each point's error is modelled as Gaussian with
    ``sigma_lateral`` (m, scalar or (K,)) across its ray and ``sigma_range`` (m) along it;
    Gauss-Newton on the pose minimises the sum of squared Mahalanobis distances.
    """
    m = np.asarray(model, dtype=float)
    p = np.asarray(points, dtype=float)
    d = p / np.linalg.norm(p, axis=1, keepdims=True)
    sl = np.broadcast_to(np.asarray(sigma_lateral, dtype=float), (len(p),))
    ddt = d[:, :, None] * d[:, None, :]
    w = (np.eye(3) - ddt) / sl[:, None, None] ** 2 + ddt / sigma_range**2  # (K, 3, 3)
    r = T_camera_probe.rotation_matrix
    t = T_camera_probe.position.copy()
    for _ in range(iterations):
        rm = m @ r.T
        e = rm + t - p
        jac = np.zeros((len(p), 3, 6))
        jac[:, 0, 1], jac[:, 0, 2] = rm[:, 2], -rm[:, 1]  # d(c)/d(theta) = -[rm]x
        jac[:, 1, 0], jac[:, 1, 2] = -rm[:, 2], rm[:, 0]
        jac[:, 2, 0], jac[:, 2, 1] = rm[:, 1], -rm[:, 0]
        jac[:, :, 3:] = np.eye(3)
        jtw = np.swapaxes(jac, 1, 2) @ w
        h = np.einsum("kij,kjl->il", jtw, jac)
        g = np.einsum("kij,kj->i", jtw, e)
        try:
            delta = -np.linalg.solve(h, g)
        except np.linalg.LinAlgError:
            break
        theta = delta[:3]
        ang = float(np.linalg.norm(theta))
        if ang > 1e-12:
            kx = (
                np.array(
                    [[0, -theta[2], theta[1]], [theta[2], 0, -theta[0]], [-theta[1], theta[0], 0]]
                )
                / ang
            )
            dr = np.eye(3) + np.sin(ang) * kx + (1 - np.cos(ang)) * kx @ kx
            r = dr @ r
        t = t + delta[3:]
    return Pose(t, matrix_to_quat(r))

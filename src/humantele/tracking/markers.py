"""Marker correspondence and pose: candidate 3D points (camera frame) -> pose of the probe.

:func:`estimate_pose` is a pure function. It searches the assignments of candidate points to
the tool's markers whose pairwise distances agree with the tool geometry (so extra blobs and
up to ``M - min_visible`` missing markers are tolerated), fits each by SVD (Kabsch), and keeps
the one with the most markers and then the smallest residual. It refuses (returns None) when
the best fit's residual is too large, or when another assignment with as many markers gives a
different pose just as well (ambiguous): never a wrong pose given silently. A fit that leaves
a marker unmatched while a candidate lies on that marker's ray is refused too: the marker
was seen and did not fit, so the three that did are not to be trusted alone.

A fit that leaves markers unmatched (three of four) is weak evidence: two real markers and a
stray sphere (a second tool, a ring, a button) can fit within the tolerances. The caller can
pass ``explain_missing``: it is given the fitted places of the unmatched markers and says
whether the sensor shows a reason not to see each (something in front of it, or a marker
image the detector refused). Fits whose missing markers would have been in plain view are
refuted (:mod:`humantele.tracking.evidence` does this with the depth image).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from humantele.geometry import Pose, matrix_to_quat
from humantele.tracking.status import TrackingStatus
from humantele.tracking.tool import ToolDefinition, kabsch

LATERAL_SEEN = 0.004  # a candidate this close (m) to a missing marker's ray is that marker

# fitted centres (K, 3) of unmatched markers, camera frame, m -> (K,) bool: absence explained
ExplainMissing = Callable[[NDArray[np.float64]], NDArray[np.bool_]]


@dataclass(frozen=True)
class MatchParams:
    """Tolerances of the correspondence search, m."""

    distance_tol: float = 0.004  # |measured - model| pairwise distance allowed, m
    max_rms: float = 0.0015  # largest accepted RMS residual of the fit, m
    max_marker_error: float = 0.003  # largest accepted single-marker residual, m
    max_rms_partial: float = 0.0006  # ... RMS residual when markers are left unmatched, m
    refuse_seen_missing: bool = True  # refuse a fit whose unmatched marker has a candidate
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
    rotation: NDArray[np.float64] | None = None  # the same rotation as a 3x3 matrix

    @property
    def n_matched(self) -> int:
        return sum(1 for i in self.matched if i >= 0)


@dataclass(frozen=True)
class MatchResult:
    """Outcome of a match: status, the estimate when tracked, the number of fits tried,
    input rows dropped for not being finite, and fits refuted because a marker they leave
    unmatched would have been seen (``explain_missing``)."""

    status: TrackingStatus
    estimate: PoseEstimate | None
    n_hypotheses: int
    n_nonfinite: int = 0
    n_refuted: int = 0


def as_points(points: ArrayLike) -> NDArray[np.float64]:
    """Candidate points as an (N, 3) float array; anything else raises ValueError."""
    try:
        pts = np.asarray(points, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"points must be numbers shaped (N, 3), m: {exc}") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3) (x, y, z in m), got {pts.shape}")
    return pts


def _assignments(
    d_meas: NDArray[np.float64], d_model: NDArray[np.float64], tol: float, min_visible: int
) -> list[tuple[int, ...]]:
    """All assignments (tuple per model marker: candidate index or -1) that keep every pair of
    assigned markers within ``tol`` of the model distance and match >= min_visible markers."""
    m = d_model.shape[0]
    n = d_meas.shape[0]
    ok = (np.abs(d_meas[None, None, :, :] - d_model[:, :, None, None]) <= tol).tolist()
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
            if all(a < 0 or ok[j][i][a][c] for j, a in enumerate(current)):
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
    points: ArrayLike,
    tool: ToolDefinition,
    params: MatchParams | None = None,
    explain_missing: ExplainMissing | None = None,
) -> MatchResult:
    """Match candidate marker centres (N, 3) in the camera frame (m) to ``tool``.

    Rows with a NaN or infinite coordinate are dropped and counted (``n_nonfinite``); a
    shape other than (N, 3) raises ValueError. ``explain_missing``: see the module doc.
    ``matched`` indices refer to the rows as given (dropped rows included).
    """
    p = params or MatchParams()
    pts_in = as_points(points)
    finite = np.flatnonzero(np.all(np.isfinite(pts_in), axis=1))[: p.max_candidates]
    n_bad = len(pts_in) - int(np.all(np.isfinite(pts_in), axis=1).sum())
    pts = pts_in[finite]
    model = tool.markers
    if len(pts) < tool.min_visible:
        return MatchResult(TrackingStatus.LOST, None, 0, n_bad)
    d_meas = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    d_model = np.linalg.norm(model[:, None] - model[None], axis=-1)
    hyps = _assignments(d_meas, d_model, p.distance_tol, tool.min_visible)
    if not hyps:
        return MatchResult(TrackingStatus.LOST, None, 0, n_bad)
    n_refuted = 0
    hyp = np.array(hyps, dtype=np.intp)  # (H, M): candidate index per marker, -1 missing
    present = hyp >= 0
    counts = present.sum(axis=1)
    # most markers first: a fit with fewer markers is only looked at when none with more fits
    for k in sorted(set(counts.tolist()), reverse=True):
        rows = np.flatnonzero(counts == k)
        h = hyp[rows]
        marker = np.nonzero(present[rows])[1].reshape(len(rows), k)  # which markers, in order
        src = model[marker]  # (G, k, 3)
        dst = pts[np.take_along_axis(h, marker, axis=1)]
        r, t, rms = kabsch(src, dst)
        err = np.linalg.norm(np.einsum("gij,gnj->gni", r, src) + t[:, None] - dst, axis=-1)
        max_rms = p.max_rms if k == len(model) else min(p.max_rms, p.max_rms_partial)
        good = np.flatnonzero((rms <= max_rms) & (err.max(axis=1) <= p.max_marker_error))
        if good.size == 0:
            continue
        placed = model @ r[good].transpose(0, 2, 1) + t[good][:, None, :]  # (g, M, 3)
        if k < len(model):
            # a fit whose unmatched marker would be in plain view is no fit at all, nor one
            # whose unmatched marker was seen (a candidate on its ray) but did not fit
            ok = np.array(
                [
                    not (p.refuse_seen_missing and _missing_contradicted(pl, pr, pts, h_row, tool))
                    and (explain_missing is None or bool(np.all(explain_missing(pl[~pr]))))
                    for pl, pr, h_row in zip(placed, present[rows[good]], h[good], strict=True)
                ]
            )
            n_refuted += int(np.count_nonzero(~ok))
            good, placed = good[ok], placed[ok]
            if good.size == 0:
                continue
        j = int(np.argmin(rms[good]))
        best = good[j]
        # ambiguous: another assignment with as many markers fits as well but moves the tool
        moved = np.linalg.norm(placed - placed[j], axis=-1).max(axis=1)
        if np.any(moved > p.distinct_pose):
            return MatchResult(TrackingStatus.AMBIGUOUS, None, len(hyps), n_bad, n_refuted)
        pose = Pose(t[best], matrix_to_quat(r[best]))
        matched = tuple(int(finite[i]) if i >= 0 else -1 for i in hyp[rows[best]])
        est = PoseEstimate(pose, float(rms[best]), matched, r[best])
        return MatchResult(TrackingStatus.TRACKED, est, len(hyps), n_bad, n_refuted)
    return MatchResult(TrackingStatus.LOST, None, len(hyps), n_bad, n_refuted)


def _missing_contradicted(
    placed: NDArray[np.float64],
    present: NDArray[np.bool_],
    pts: NDArray[np.float64],
    used: NDArray[np.intp],
    tool: ToolDefinition,
) -> bool:
    """Whether the fit's own evidence contradicts a marker it leaves unmatched.

    ``placed`` (M, 3) the fitted marker centres, ``present`` (M,) which were matched,
    ``pts`` the candidates, ``used`` (M,) candidate index per marker (-1 missing). True when
    a candidate left out of the fit lies on a missing marker's ray (within ``LATERAL_SEEN``
    m) or within the tool's marker spacing of its fitted place (seen, did not fit), or when
    the fit puts a missing marker's image onto one of its matched markers' while other
    candidates are in view (one of them may be the marker: a stray then stands in for it).
    A marker hidden behind another with nothing else in view is the usual occlusion of a
    tool turned edge-on, and is kept.
    """
    missing = placed[~present]
    ray = missing / np.linalg.norm(missing, axis=1, keepdims=True)  # (K, 3)
    rest = np.delete(pts, used[used >= 0], axis=0)
    if len(rest) == 0:
        return False
    own = placed[present]
    if np.any(
        np.linalg.norm(np.cross(own[None], ray[:, None]), axis=-1) < 2.0 * tool.sphere_radius
    ):
        return True
    across = np.linalg.norm(np.cross(rest[None, :, :], ray[:, None, :]), axis=-1)
    near = np.linalg.norm(rest[None, :, :] - missing[:, None, :], axis=-1)
    return bool(np.any(across < LATERAL_SEEN) or np.any(near < tool.min_separation_mm / 1000.0))


def estimate_pose(
    points: ArrayLike,
    tool: ToolDefinition,
    params: MatchParams | None = None,
    explain_missing: ExplainMissing | None = None,
) -> PoseEstimate | None:
    """Pose of the probe in the camera frame from candidate marker centres (N, 3), m.

    Points may be in any order, include outliers and miss up to ``M - tool.min_visible``
    markers. Rows with a NaN or infinite coordinate are dropped (a detector's "no depth"
    rows); :func:`match_markers` counts them. Any shape but (N, 3) (N may be 0) raises
    ValueError. Returns None when no fit is trustworthy (too few markers, residual too large,
    ambiguous, or every fit refuted by ``explain_missing``). Without ``explain_missing`` a
    fit that leaves markers unmatched is not checked against the image: give it one whenever
    a depth image is at hand (the tracking pipeline does).
    """
    return match_markers(points, tool, params, explain_missing).estimate


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
    r, t = refine_rt(
        T_camera_probe.rotation_matrix,
        T_camera_probe.position,
        model,
        points,
        sigma_lateral,
        sigma_range,
        iterations,
    )
    return Pose(t, matrix_to_quat(r))


def refine_rt(
    rotation: NDArray[np.float64],
    translation: NDArray[np.float64],
    model: ArrayLike,
    points: ArrayLike,
    sigma_lateral: ArrayLike,
    sigma_range: float,
    iterations: int = 3,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`refine_pose` on a rotation matrix and translation (m); returns both refined."""
    m = np.asarray(model, dtype=float)
    p = np.asarray(points, dtype=float)
    k = len(p)
    d = p / np.linalg.norm(p, axis=1, keepdims=True)
    sl = np.broadcast_to(np.asarray(sigma_lateral, dtype=float), (k,))
    ddt = d[:, :, None] * d[:, None, :]
    w = (np.eye(3) - ddt) / sl[:, None, None] ** 2 + ddt / sigma_range**2  # (K, 3, 3)
    r = np.asarray(rotation, dtype=float)
    t = np.asarray(translation, dtype=float)
    jac = np.zeros((k, 3, 6))
    jac[:, :, 3:] = np.eye(3)
    for _ in range(iterations):
        rm = m @ r.T
        e = (rm + t - p).reshape(-1)
        # d(residual)/d(small rotation theta, applied on the left) = -[rm]x
        jac[:, 0, 1], jac[:, 0, 2] = rm[:, 2], -rm[:, 1]
        jac[:, 1, 0], jac[:, 1, 2] = -rm[:, 2], rm[:, 0]
        jac[:, 2, 0], jac[:, 2, 1] = rm[:, 1], -rm[:, 0]
        wj = (w @ jac).reshape(-1, 6)
        jf = jac.reshape(-1, 6)
        try:
            delta = -np.linalg.solve(jf.T @ wj, wj.T @ e)
        except np.linalg.LinAlgError:
            break
        r = _rotvec_matrix(delta[:3]) @ r
        t = t + delta[3:]
    return r, t


def _rotvec_matrix(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrix of a rotation vector (rad), Rodrigues' formula."""
    ang = math.sqrt(float(v @ v))
    if ang < 1e-12:
        return np.eye(3)
    x, y, z = v / ang
    kx = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(ang) * kx + (1.0 - math.cos(ang)) * (kx @ kx)

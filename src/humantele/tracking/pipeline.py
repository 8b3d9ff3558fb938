"""The tracking pipeline: frame -> blobs -> 3D marker centres -> correspondence -> pose.

Steps: threshold and contours (OpenCV), sub-pixel centroids, range from depth corrected from
the sphere's surface to its centre (:mod:`humantele.tracking.blobs`); matching to the tool and
an SVD fit with residual and ambiguity checks (:mod:`humantele.tracking.markers`); optionally
a maximum-likelihood refinement that trusts bearings more than ToF range; optionally the
alpha-beta filter. The status is explicit: ``tracked``, ``lost`` or ``ambiguous``; a pose is
given only when tracked. A fit that leaves a marker unmatched is kept only if the depth image
shows why that marker is unseen (:mod:`humantele.tracking.evidence`); frames without depth
then track only with every marker matched.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from pydantic import Field

from humantele.config import ConfigModel
from humantele.geometry import Pose, matrix_to_quat
from humantele.tracking.blobs import BlobParams, CentroidMethod, DepthMethod, detect_blobs
from humantele.tracking.evidence import FreeSpaceCheck
from humantele.tracking.filter import FilterConfig, PoseFilter
from humantele.tracking.frames import TrackingFrame
from humantele.tracking.markers import MatchParams, match_markers, refine_rt
from humantele.tracking.sphere import SphereFitParams
from humantele.tracking.status import TrackingStatus
from humantele.tracking.tool import ToolDefinition


class PipelineConfig(ConfigModel):
    """Detection, range and fit settings. IR in counts; sizes px; distances mm (config edge)."""

    threshold: float = Field(1000.0, gt=0, description="IR counts a marker pixel exceeds")
    centroid_floor: float = Field(400.0, ge=0, description="counts subtracted for weights")
    min_area: int = Field(3, ge=1)
    max_area: int = Field(600, ge=1)
    min_roundness: float = Field(0.45, ge=0, le=1)
    centroid: CentroidMethod = "weighted"
    depth: DepthMethod = "model"
    sphere_offset: float = Field(
        0.47, ge=-1, le=1, description='"sphere" depth: core range -> centre, x radius'
    )
    psf_sigma_px: float = Field(0.7, ge=0, le=5, description="camera blur; calibrate per device")
    saturation: float = Field(4095.0, gt=0, description="IR counts where pixels clip")
    min_coverage: float = Field(0.3, gt=0, le=1, description="model depth: pixels that vote")
    shape_tolerance: float = Field(
        0.35, gt=0, description="relative IR misfit of a pixel the sphere model calls bright"
    )
    max_ir_misfit: float = Field(
        0.06, gt=0, description="RMS IR misfit to the sphere model (x brightness): partly hidden"
    )
    paired_max_ir_misfit: float = Field(
        0.15, gt=0, description="max_ir_misfit for AB sampled at every other column, each "
        "over two (hl2ss depth SAME + AB H.26x): the model draws no such pairs")  # fmt: skip
    paired_shape_tolerance: float = Field(0.6, gt=0, description="shape_tolerance for those")
    min_range_m: float = Field(0.15, gt=0)
    max_range_m: float = Field(0.58, gt=0, description="farther markers are too small")
    range_mixing: Literal["linear", "phasor"] = Field(
        "phasor", description="model depth: an edge pixel's sphere and background returns "
        "summed as phasors (time of flight), or ranges mixed by brightness")  # fmt: skip
    unwrap: bool = True
    depth_wrap_m: float = Field(1.055, gt=0.1, description="range ambiguity, m (hl2ss alias)")
    refine: bool = True
    lateral_sigma_px: float = Field(0.05, gt=0)
    range_sigma_mm: float = Field(0.8, gt=0)
    iterations: int = Field(2, ge=1, le=10, description="Gauss-Newton steps of the refinement")
    distance_tol_mm: float = Field(4.0, gt=0)
    max_rms_mm: float = Field(1.5, gt=0)
    max_marker_error_mm: float = Field(3.0, gt=0)
    max_rms_partial_mm: float = Field(
        0.6, gt=0, description="max_rms for fits that leave a marker unmatched (3 points)"
    )
    verify_missing: bool = Field(
        True,
        description="refute fits whose unmatched marker is seen but does not fit, or which the "
        "depth image shows is not there",
    )
    free_space_margin_mm: float = Field(
        10.0, gt=0, description="depth farther than a missing marker's surface by this: clear"
    )


@dataclass(frozen=True)
class TrackingResult:
    """One frame's outcome. ``T_camera_probe`` is set only when ``status`` is ``tracked``;
    ``residual_m`` is the fit's RMS residual (NaN when not tracked); ``matched[i]`` the blob
    index of tool marker i (-1 missing); ``n_blobs`` candidate points found."""

    t: float
    status: TrackingStatus
    T_camera_probe: Pose | None
    residual_m: float
    matched: tuple[int, ...]
    n_blobs: int


class Tracker:
    """Runs the pipeline on frames of one tool."""

    def __init__(
        self,
        tool: ToolDefinition,
        config: PipelineConfig | None = None,
        filter_config: FilterConfig | None = None,
    ):
        self.tool = tool
        self.config = c = config or PipelineConfig()
        self.blob_params = BlobParams(
            threshold=c.threshold,
            centroid_floor=c.centroid_floor,
            min_area=c.min_area,
            max_area=c.max_area,
            min_roundness=c.min_roundness,
            centroid=c.centroid,
            depth=c.depth,
            sphere_offset=c.sphere_offset,
            min_range=c.min_range_m,
            max_range=c.max_range_m,
            unwrap=c.unwrap,
            depth_wrap_m=c.depth_wrap_m,
            sphere=SphereFitParams(
                psf_sigma_px=c.psf_sigma_px,
                saturation=c.saturation,
                min_coverage=c.min_coverage,
                shape_tolerance=c.shape_tolerance,
                max_ir_misfit=c.max_ir_misfit,
                phasor=c.range_mixing == "phasor",
            ),
        )
        self.paired_params = replace(
            self.blob_params,
            sphere=replace(
                self.blob_params.sphere,
                max_ir_misfit=c.paired_max_ir_misfit,
                shape_tolerance=c.paired_shape_tolerance,
            ),  # fmt: skip
        )
        self.match_params = MatchParams(
            distance_tol=c.distance_tol_mm / 1000.0,
            max_rms=c.max_rms_mm / 1000.0,
            max_marker_error=c.max_marker_error_mm / 1000.0,
            max_rms_partial=c.max_rms_partial_mm / 1000.0,
            refuse_seen_missing=c.verify_missing,
        )
        fc = filter_config or FilterConfig()
        self.filter = PoseFilter(fc) if fc.enabled else None
        self.counts = {str(s): 0 for s in TrackingStatus if s != TrackingStatus.PREDICTED}
        self.refuted = 0  # fits refuted because a marker they leave unmatched was not there

    def process(self, frame: TrackingFrame) -> TrackingResult:
        """Track the tool in one frame."""
        c = self.config
        params = self.paired_params if frame.ab_paired else self.blob_params
        blobs = detect_blobs(
            frame.ir, frame.depth_mm, frame.intrinsics, self.tool.sphere_radius, params
        )
        explain = None
        if c.verify_missing:
            if frame.depth_mm is None:
                explain = _never  # nothing to check a missing marker against
            else:
                explain = FreeSpaceCheck(
                    frame.depth_mm,
                    frame.intrinsics,
                    self.tool.sphere_radius,
                    margin_m=c.free_space_margin_mm / 1000.0,
                    wrap_m=c.depth_wrap_m,
                    min_range_m=c.min_range_m,
                )
        res = match_markers(blobs.points, self.tool, self.match_params, explain)
        self.counts[res.status] += 1
        self.refuted += res.n_refuted
        n = len(blobs.points)
        if res.estimate is None:
            return TrackingResult(frame.t, res.status, None, float("nan"), (), n)
        est = res.estimate
        pose = est.T_camera_probe
        if c.refine and est.rotation is not None:
            idx = np.array(est.matched)
            ok = idx >= 0
            pts = blobs.points[idx[ok]]
            sl = c.lateral_sigma_px / frame.intrinsics.fx * np.linalg.norm(pts, axis=1)
            r0, t0 = est.rotation, pose.position
            r, t = refine_rt(
                r0, t0, self.tool.markers[ok], pts, sl, c.range_sigma_mm / 1e3, c.iterations
            )
            cos_d = (np.trace(r @ r0.T) - 1.0) / 2.0
            if np.linalg.norm(t - t0) < 0.005 and cos_d > math.cos(math.radians(5.0)):
                pose = Pose(t, matrix_to_quat(r))  # never let a refinement run away
        if self.filter is not None:
            pose = self.filter.update(frame.t, pose)
        return TrackingResult(frame.t, TrackingStatus.TRACKED, pose, est.residual_m, est.matched, n)


def _never(centres: np.ndarray) -> np.ndarray:
    return np.zeros(len(centres), dtype=bool)

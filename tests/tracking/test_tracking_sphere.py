"""The sphere image model: tables, range of marker centres from ToF pixels, refusing cut spheres,
and calibrating the camera blur from IR frames alone."""

import numpy as np
import pytest

from humantele.geometry import Pose
from humantele.tracking.blobs import BlobParams, detect_blobs
from humantele.tracking.psf import estimate_psf_sigma
from humantele.tracking.sim import SimFrameConfig, SimFrameSource, default_sim_pose
from humantele.tracking.sphere import sphere_tables


def test_tables_are_a_blurred_disc_and_its_cap_depth():
    t = sphere_tables(0.7)
    r = np.array([2.5, 6.0])
    c, g = t.lookup(r, np.array([[0.0, 2.5, 9.0], [0.0, 6.0, 12.0]]))
    # middle of a big disc: covered, cap depth ~R; at the edge half covered; far: nothing
    assert c[1, 0] == pytest.approx(1.0, abs=1e-3) and 0.95 < g[1, 0] < 1.0
    assert c[0, 1] == pytest.approx(0.5, abs=0.05) and c[1, 1] == pytest.approx(0.5, abs=0.03)
    assert c[0, 2] < 1e-3 and c[1, 2] < 1e-3
    # blur averages the cap: a small disc's middle sees a shallower mean depth than a big one's
    assert g[0, 0] < g[1, 0]
    # sharper optics: more coverage just inside the edge
    assert sphere_tables(0.3).lookup(r[:1], np.array([[2.0]]))[0][0, 0] > c[0, 1]


def _marker_range_errors(cfg: SimFrameConfig, depth: str, n: int = 12):
    """Range error (m) of each detected marker centre against the truth, and the true range."""
    src = SimFrameSource(cfg)
    rng = np.random.default_rng(4)
    errs, dist = [], []
    for _ in range(n):
        base = default_sim_pose()
        pose = Pose(
            base.position + rng.uniform([-0.05, -0.05, -0.07], [0.05, 0.05, 0.08]), base.quaternion
        )
        f = src.render(pose)
        b = detect_blobs(
            f.ir, f.depth_mm, f.intrinsics, src.tool.sphere_radius, BlobParams(depth=depth)
        )
        true = pose.apply(src.tool.markers)
        for q in b.points:
            j = np.argmin(np.linalg.norm(true - q, axis=1))
            errs.append(np.linalg.norm(q) - np.linalg.norm(true[j]))
            dist.append(np.linalg.norm(true[j]))
    return np.array(errs), np.array(dist)


def test_model_range_is_unbiased_across_distance_where_the_fixed_offset_is_not():
    cfg = SimFrameConfig(seed=21, spurious_rate=0.0)
    e_model, d = _marker_range_errors(cfg, "model")
    e_core, d2 = _marker_range_errors(cfg, "sphere")
    near, far = d < 0.40, d > 0.44
    assert near.sum() > 5 and far.sum() > 5
    # measured: |bias| < 0.15 mm near and far, ~0.45 mm per-marker scatter
    assert abs(np.mean(e_model[near])) < 0.3e-3 and abs(np.mean(e_model[far])) < 0.3e-3
    assert np.sqrt(np.mean(e_model**2)) < 0.7e-3
    # the old fixed offset drifts with distance (about +0.4 mm near to -1 mm far)
    drift = np.mean(e_core[d2 < 0.40]) - np.mean(e_core[d2 > 0.44])
    assert drift > 0.6e-3
    assert np.sqrt(np.mean(e_model**2)) < 0.7 * np.sqrt(np.mean(e_core**2))


def test_a_sphere_cut_by_a_finger_is_refused_not_measured():
    src = SimFrameSource(SimFrameConfig(seed=3, spurious_rate=0.0, partial_occlusion_prob=1.0))
    whole = SimFrameSource(SimFrameConfig(seed=3, spurious_rate=0.0))
    refused = kept_bad = 0
    for i in range(10):
        pose = Pose(
            default_sim_pose().position + [0.004 * i, 0.0, 0.0], default_sim_pose().quaternion
        )
        f = src.render(pose)
        b = detect_blobs(f.ir, f.depth_mm, f.intrinsics, src.tool.sphere_radius)
        refused += b.not_sphere
        uv_true = f.intrinsics.project(pose.apply(src.tool.markers))
        for uv in b.uv:  # what is kept is where a sphere centre is (a slightly cut one at most)
            kept_bad += np.min(np.linalg.norm(uv_true - uv, axis=1)) > 0.5
        g = whole.render(pose)
        assert detect_blobs(g.ir, g.depth_mm, g.intrinsics, src.tool.sphere_radius).not_sphere == 0
    assert refused >= 10 and kept_bad == 0


def test_camera_blur_is_calibrated_from_ir_frames_alone():  # seconds of numpy, no process
    for psf in (0.7, 1.0):
        src = SimFrameSource(SimFrameConfig(seed=5, psf_sigma_px=psf))
        frames = [
            src.render(
                Pose(default_sim_pose().position + [0.01 * i, 0, 0], default_sim_pose().quaternion)
            )
            for i in range(5)
        ]
        assert estimate_psf_sigma(frames, src.tool.sphere_radius) == pytest.approx(psf, abs=0.05)
    with pytest.raises(ValueError):
        estimate_psf_sigma([], 0.0055)

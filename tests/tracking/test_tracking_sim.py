import numpy as np
import pytest

from humantele.geometry import Pose
from humantele.tracking.frames import FrameSourceUnavailable
from humantele.tracking.opencv_source import OpenCVFrameConfig, OpenCVFrameSource
from humantele.tracking.sim import SimFrameConfig, SimFrameSource, default_sim_pose
from humantele.tracking.sources import make_frame_source


def test_frames_are_deterministic_by_seed():
    a = [SimFrameSource(SimFrameConfig(seed=3)).read() for _ in range(1)]
    b = SimFrameSource(SimFrameConfig(seed=3))
    c = SimFrameSource(SimFrameConfig(seed=4))
    fb, fc = b.read(), c.read()
    np.testing.assert_array_equal(a[0].ir, fb.ir)
    np.testing.assert_array_equal(a[0].depth_mm, fb.depth_mm)
    assert not np.array_equal(fb.ir, fc.ir)


def test_markers_are_bright_at_their_projection_with_range_depth():
    src = SimFrameSource(SimFrameConfig(spurious_rate=0.0))
    f = src.read()
    assert f.ir.shape == (512, 512) and f.ir.dtype == np.uint16
    centres = f.T_camera_probe_true.apply(src.tool.markers)
    for c, (u, v) in zip(centres, f.intrinsics.project(centres), strict=True):
        win_ir = f.ir[int(v) - 1 : int(v) + 2, int(u) - 1 : int(u) + 2]
        win_d = f.depth_mm[int(v) - 1 : int(v) + 2, int(u) - 1 : int(u) + 2]
        assert win_ir.max() > 2000
        d = np.median(win_d[win_d > 0]) / 1000.0
        # the sphere's near surface: a little in front of its centre
        assert np.linalg.norm(c) - 0.012 < d < np.linalg.norm(c) + 0.004
    assert f.visible_true == (True, True, True, True)


def test_occluded_marker_is_not_drawn():
    src = SimFrameSource(SimFrameConfig(occluded_markers=[1], spurious_rate=0.0))
    f = src.read()
    assert f.visible_true == (True, False, True, True)
    u, v = f.intrinsics.project(f.T_camera_probe_true.apply(src.tool.markers[1]))
    assert f.ir[int(v) - 2 : int(v) + 3, int(u) - 2 : int(u) + 3].max() < 1000


def test_depth_wraps_beyond_the_ambiguity_range():
    src = SimFrameSource(SimFrameConfig(depth_wrap_m=0.3, spurious_rate=0.0))
    f = src.read()
    c = f.T_camera_probe_true.apply(src.tool.markers[0])
    u, v = f.intrinsics.project(c)
    d = f.depth_mm[int(round(v)), int(round(u))] / 1000.0
    assert d == pytest.approx(np.linalg.norm(c) - 0.3, abs=0.01)


def test_noise_scale_zero_gives_repeatable_marker_pixels():
    cfg = SimFrameConfig(noise_scale=0.0, spurious_rate=0.0)
    src = SimFrameSource(cfg)
    f1, f2 = src.read(), src.read()
    np.testing.assert_array_equal(f1.ir, f2.ir)


def test_render_at_a_given_pose_and_factory():
    src = make_frame_source(SimFrameConfig())
    assert isinstance(src, SimFrameSource)
    pose = Pose(default_sim_pose().position + [0.05, 0.0, 0.0], default_sim_pose().quaternion)
    f = src.render(pose, t=1.5)
    assert f.t == 1.5 and f.T_camera_probe_true is pose


def test_opencv_backend_without_camera_is_a_clear_error(tmp_path):
    with pytest.raises(FrameSourceUnavailable, match="cannot open camera .*use the 'sim'"):
        OpenCVFrameSource(OpenCVFrameConfig(device=str(tmp_path / "no_camera.avi"))).open()
    src = make_frame_source(OpenCVFrameConfig(device=str(tmp_path / "none.avi")))
    assert isinstance(src, OpenCVFrameSource)  # made, not opened: no camera needed yet
    with pytest.raises(FrameSourceUnavailable, match="not open"):
        src.read()
    with pytest.raises(FrameSourceUnavailable), src:
        pass
    with pytest.raises(TypeError, match="not a frame source configuration"):
        make_frame_source(object())  # type: ignore[arg-type]


def test_opencv_backend_reads_a_recorded_ir_video(tmp_path):
    import cv2

    path = str(tmp_path / "ir.avi")
    w = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 45, (64, 48), isColor=False)
    if not w.isOpened():
        pytest.skip("no MJPG writer in this OpenCV build")
    for i in range(3):
        img = np.zeros((48, 64), np.uint8)
        cv2.circle(img, (20 + 5 * i, 24), 3, 255, -1)
        w.write(img)
    w.release()
    src = OpenCVFrameSource(OpenCVFrameConfig(device=path, intrinsics={"width": 64, "height": 48}))
    src.open()
    frames = [src.read(t=float(i)) for i in range(4)]
    src.close()
    assert frames[0] is not None and frames[0].ir.shape == (48, 64)
    assert frames[0].ir.max() > 3000 and frames[0].depth_mm is None
    assert frames[3] is None and src.dropped == 1

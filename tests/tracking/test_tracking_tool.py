import numpy as np
import pytest

from humantele.config import ConfigError, load_config
from humantele.tracking.tool import ToolDefinition, kabsch, load_tool, self_match_residual


def test_default_tool_loads_in_metres():
    tool = load_tool()
    assert tool.markers.shape == (4, 3)
    np.testing.assert_allclose(tool.markers[0], [-0.026, 0.018, 0.002])
    assert tool.sphere_radius == pytest.approx(0.0055)
    np.testing.assert_allclose(tool.face_direction, [0, 0, -1])
    np.testing.assert_allclose(tool.tip, [0, 0, -0.15])


@pytest.mark.parametrize(
    "markers",
    [
        [[0, 0, 0], [50, 0, 0], [50, 50, 0], [0, 50, 0]],  # square
        [[0, 0, 0], [80, 0, 0], [80, 40, 0], [0, 40, 0]],  # rectangle: 180 deg symmetric
        [[0, 0, 0], [60, 0, 0], [45, 35, 0], [15, 35, 0]],  # isosceles trapezoid
        [[0, 0, 0], [60, 0, 0], [30, 52, 0], [30, 17, 40]],  # triangular pyramid
    ],
)
def test_symmetric_layouts_are_refused(markers):
    with pytest.raises(ValueError, match="ambiguous marker layout"):
        ToolDefinition(markers_mm=markers)


def test_mirror_symmetric_layout_refused_as_reflection():
    # non-planar, symmetric only by a mirror (x -> 40 - x swaps markers 0 and 1)
    markers = [[0, 0, 0], [40, 0, 0], [20, 45, 0], [20, 12, 30]]
    with pytest.raises(ValueError, match="a reflection maps markers"):
        ToolDefinition(markers_mm=markers, min_visible=4)


def test_layout_whose_subsets_look_alike_is_refused_when_three_may_be_visible():
    # two congruent triangles {0,1,2} and {1,2,3}-like layout: a parallelogram
    markers = [[0, 0, 0], [60, 0, 0], [80, 40, 0], [20, 40, 0]]
    with pytest.raises(ValueError, match="ambiguous"):
        ToolDefinition(markers_mm=markers)


def test_bad_tool_files_name_the_problem(tmp_path):
    f = tmp_path / "t.toml"
    f.write_text("markers_mm = [[0,0,0],[50,0,0],[0,60,0]]\n")
    with pytest.raises(ConfigError, match="at least 4 markers"):
        load_config(ToolDefinition, f)
    f.write_text("markers_mm = [[0,0,0],[10,0,0],[0,60,0],[70,80,10]]\n")
    with pytest.raises(ConfigError, match="min_separation_mm"):
        load_tool(f)
    with pytest.raises(ConfigError, match="known tools: .*probe_default"):
        load_tool("no_such_probe")


def test_kabsch_recovers_rotation_and_reports_reflection():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(5, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    r_true = q * np.sign(np.linalg.det(q))
    dst = src @ r_true.T + [1, 2, 3]
    r, t, rms = kabsch(src, dst)
    np.testing.assert_allclose(r, r_true, atol=1e-9)
    np.testing.assert_allclose(t, [1, 2, 3], atol=1e-9)
    assert rms < 1e-9
    mirrored = dst * [1, 1, -1]
    assert kabsch(src, mirrored)[2] > 0.1
    assert kabsch(src, mirrored, allow_reflection=True)[2] < 1e-9


def test_self_match_residual_of_default_tool_has_margin():
    rms, _ = self_match_residual(np.asarray(load_tool().markers_mm), 3)
    assert rms > 5.5  # mm; the layout was chosen for this

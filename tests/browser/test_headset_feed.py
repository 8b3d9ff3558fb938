"""The headset page in Chromium against a feed publishing known poses: where things are
drawn (the frame conversion), the colour cue, the not-live states, the calibration prompt,
bad input from pages."""

import json
import math

import numpy as np
import pytest
from pixels import GHOST_LEVEL, OUTLINE_LEVEL, changed, changed_near, handle_point, matrix, project

from humantele.geometry import Pose

GREEN, AMBER, RED, GREY = 0x2FBF71, 0xF2A900, 0xE5484D, 0x8B9096


@pytest.fixture(scope="module")
def run(browser_scenario):
    return browser_scenario("headset_feed")


def shot(run, view, name):
    return run.path(view["shots"][name])


def test_virtual_probe_drawn_where_the_pose_says(run):
    red = run.data["red"]
    v = red["virtual"]
    pose = Pose(v["position"], v["quaternion"])
    # The page took the feed's frame as is: y up, metres, quaternion (x, y, z, w).
    assert np.allclose(matrix(red["matrix"]["virtual"]), pose.as_matrix(), atol=1e-6)
    published = run.data["virtual_pose"]
    assert np.allclose(v["position"], published[0], atol=1e-5)
    assert np.allclose(v["quaternion"], published[1], atol=1e-9)
    # In the picture: up the handle, at the projected points, the probe is drawn.
    mask = changed(shot(run, red, "all"), shot(run, red, "virtual"))
    cam = red["camera"]
    # up the handle (the arrow may cover the face); all three reported when one fails
    handle = {up: project(cam, handle_point(v, up)) for up in (0.05, 0.08, 0.11)}
    near = {up: changed_near(mask, xy, 4) for up, xy in handle.items()}
    assert min(near.values()) > 0.5, (near, handle, int(mask.sum()))
    # Read as (w, x, y, z), the same numbers would put the handle elsewhere: nothing there.
    q = v["quaternion"]
    wrong = {"position": v["position"], "quaternion": [q[3], q[0], q[1], q[2]]}
    right_xy = np.array(project(cam, handle_point(v, 0.11)))
    wrong_xy = np.array(project(cam, handle_point(wrong, 0.11)))
    assert np.linalg.norm(right_xy - wrong_xy) > 30
    assert changed_near(mask, wrong_xy, 4) < 0.1
    # Everything that changed is near the probe (its body and beam), nothing elsewhere.
    corners = [
        Pose(v["position"], q).apply([sx * 0.03, sy * 0.02, z])
        for sx in (-1, 1) for sy in (-1, 1) for z in (0.07, -0.17)
    ]  # fmt: skip
    xy = np.array([project(cam, c) for c in corners])
    ys, xs = np.nonzero(mask)
    inside = (
        (xs >= xy[:, 0].min() - 10) & (xs <= xy[:, 0].max() + 10)
        & (ys >= xy[:, 1].min() - 10) & (ys <= xy[:, 1].max() + 10)
    )  # fmt: skip
    assert len(xs) > 500 and inside.mean() > 0.99


def test_ghost_and_outline_drawn(run):
    red = run.data["red"]
    cam = red["camera"]
    assert red["visible"] == {"virtual": True, "ghost": True, "outline": True}
    ghost = changed(shot(run, red, "all"), shot(run, red, "ghost"), GHOST_LEVEL)
    p = red["probe"]
    assert np.allclose(
        matrix(red["matrix"]["ghost"]), Pose(p["position"], p["quaternion"]).as_matrix(), atol=1e-6
    )
    for up in (0.05, 0.11):
        assert changed_near(ghost, project(cam, handle_point(p, up)), 4) > 0.5, up
    # The outline: the model's cross-section at the centre, projected, is where lines went.
    outline = changed(shot(run, red, "all"), shot(run, red, "outline"), OUTLINE_LEVEL)
    m = red["model"]
    T = Pose(m["center"], m["quaternion"])
    _, b, a = m["semi_axes"]
    ring = [T.apply([0.0, b * np.sin(t), a * np.cos(t)]) for t in np.linspace(0.3, 2.8, 12)]
    hits = [changed_near(outline, project(cam, pt), 3) > 0 for pt in ring]
    assert sum(hits) >= 9, hits
    assert np.allclose(matrix(red["matrix"]["outline"]), T.as_matrix(), atol=1e-6)


def test_colour_and_arrow_follow_the_alignment_error(run):
    want = {"green": GREEN, "amber": AMBER, "red": RED}
    for g in run.data["grades"]:
        assert g["colour"] == want[g["cue"]], g
        assert g["arrow"] == (g["mm"] >= 5.0), g  # the arrow shows the way unless on target
        assert g["hud"]["deg"] == f"{g['deg']:.1f}°"
    assert [g["cue"] for g in run.data["grades"]] == ["green", "amber", "amber", "red", "red"]
    assert run.data["grades"][0]["hud"]["headline"].startswith("On target")
    assert "along the arrow" in run.data["first_hud"]["headline"]
    assert "to the patient's left" in run.data["first_hud"]["detail"]


def test_not_live_says_why(run):
    d = run.data
    stopped = d["stopped"]
    assert stopped["guide"]["ageMs"] > 500  # greyed only once older than 0.5 s
    assert "No update from the sonographer" in stopped["detail"]
    assert stopped["colour"] == GREY
    assert d["resumed"]["guide"]["live"]
    assert d["old_pose"]["guide"]["ageMs"] >= 800
    assert "Connection to the sonographer lost" in d["link_down"]["detail"]
    assert "repositioning their hand" in d["clutch"]["detail"]
    for k in ("stopped", "old_pose", "link_down", "clutch"):
        assert (
            d[k]["headline"] == "Guide paused: not live"
            and "Hold the probe still" in d[k]["detail"]
        )


def test_calibration_prompt_and_refusal(run):
    c = run.data["calibrating"]
    assert c["headline"] == "Calibration 3 of 4: Right side"
    assert "extreme right side" in c["detail"]
    assert c["refusal"] == "Not taken: press again on the right side: it is 9 cm above the xiphoid"
    assert c["steps"] == ["done", "done", "now", ""]
    assert run.data["calibrating_virtual_visible"] is False
    assert run.data["outline_after_click"] is False


def test_bad_page_input_refused_counted_feed_goes_on(run):
    d = run.data
    refused = d["feed"]["refused"]
    assert d["bad_input_close_code"] == 1009  # too big: closed
    assert refused.get("malformed", 0) >= 5 and refused.get("too_big") == 1
    assert refused.get("flood", 0) >= 1 and refused.get("origin") == 1
    assert d["cross_origin"] == "refused"
    assert d["closed_tab_disconnects"] == 1
    assert d["messages_after"] > 0  # the first page still gets the feed
    headset_errors = [e for e in d["console_errors"] if "/feed" not in e and "404" not in e]
    assert headset_errors == []


def test_drawn_echoes_give_the_feed_latency(run):
    f = run.data["feed"]
    lat = run.data["latencies_ms"]
    assert f["echoes"] == len(lat) > 20
    # (a figure, written below, not a bound: software WebGL on a loaded machine is slow)
    assert 0 < f["draw_latency_p50_ms"] <= f["draw_latency_p95_ms"]
    assert all(math.isfinite(x) and x >= 0 for x in lat), lat
    (run.out_dir / "feed_latency.json").write_text(json.dumps({k: f[k] for k in (
        "echoes", "draw_latency_p50_ms", "draw_latency_p95_ms")}))  # fmt: skip


def test_pairing_asked_once_wrong_code_refused(run):
    d = run.data
    assert "pairing code" in d["pairing_asked"] and d["pairing_hides_hud"] == "needed"
    assert "did not accept" in d["pairing_wrong"]
    assert d["paired_form_hidden"] is True and d["paired_after_reload"] is True
    assert "#code" not in d["code_address"]  # taken out of the address bar once kept
    assert d["feed"]["refused"].get("unauthorized") == 1

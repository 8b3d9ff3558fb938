"""The headset page registering its XR space to the tracker's world, in real Chromium under
the IWER WebXR emulator, with the XR space offset and rotated from the world by a known
transform (scenarios/headset_registration.py): recovered within 2 mm / 1 deg, the guide
drawn through it, the watch saying "re-register" when the space jumps, the saved one
offered again."""

import math

import numpy as np
import pytest
from pixels import matrix

from humantele.geometry import Pose

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.fixture(scope="module")
def run(browser_scenario):
    return browser_scenario("headset_registration", timeout_s=300.0)


def pose(d) -> Pose:
    return Pose(d["position"], d["quaternion"])


def test_ar_without_a_registration_asks_for_one_and_draws_nothing_from_the_feed(run):
    h = run.data["needed"]
    assert h["headline"] == "Register this headset first" and h["buttons"] == ["register"]
    assert h["registration"]["state"] == "none"
    assert run.data["needed_root_visible"] is False
    # On the tablet (not presenting) the feed's world was drawn as it is.
    tablet = matrix(run.data["tablet_virtual"])
    assert run.data["tablet"]["cue"] != "register"
    assert np.allclose(tablet[:3, 3], run.data["virtual_world"])


def test_known_transform_recovered_within_2_mm_and_1_degree(run):
    truth, got = pose(run.data["T_world_xr_true"]), pose(run.data["T_world_xr"])
    dp, da = got.distance_to(truth)
    assert math.degrees(da) < 1.0
    # Position where it matters: over the work area (the targets, 36 x 20 cm, and 30 cm
    # around them); at the XR origin itself (a metre away, on the floor) it is levered by
    # the angle error, reported in docs/registration.md.
    targets = np.array(run.data["targets_xr"])
    work = np.vstack([targets, targets + [0, -0.3, 0], targets.mean(axis=0)])
    gaps = np.linalg.norm(got.apply(work) - truth.apply(work), axis=1) * 1000.0
    print(f"registration over the work area: max {gaps.max():.2f} mm, angle "
          f"{math.degrees(da):.3f} deg")  # fmt: skip
    assert gaps.max() < 2.0, gaps
    done = run.data["done"]
    assert done["headline"] == "Headset registered" and "residual" in done["detail"]
    assert done["registration"]["residualMm"] < 2.0
    assert run.data["stats_ar"]["counts"]["touches"] == 4  # three dwelt, one pressed


def test_the_guide_is_drawn_through_the_registration(run):
    truth = pose(run.data["T_world_xr_true"])
    drawn = matrix(run.data["virtual_xr"])  # the virtual probe's pose in the XR space
    want = truth.inverse().apply(run.data["virtual_world"])
    assert np.linalg.norm(drawn[:3, 3] - want) * 1000.0 < 2.0
    assert run.data["virtual_visible"] and run.data["following"]["guide"]["live"]


def test_watch_says_re_register_when_the_headsets_space_jumps(run):
    ok = run.data["watch_ok"]["registration"]
    assert ok["watch"] == "ok" and ok["driftMm"] < 5.0
    d = run.data["drifted"]
    assert d["headline"] == "Re-register the headset" and "moved 6" in d["detail"]
    assert d["registration"]["driftMm"] == pytest.approx(60, abs=5)
    assert run.data["drifted_virtual_visible"] is False  # a guide known misplaced: hidden


def test_saved_registration_offered_again_and_watched(run):
    r = run.data["reused"]["registration"]
    assert r["state"] == "registered" and r["watch"] == "ok"
    assert "saved" in r["message"]
    assert run.data["stats_ar"]["counts"]["hello"] == 2  # the page, then the page reloaded
    assert run.data["stats"]["bad_messages"] == {}
    assert run.data["feed"]["refused"].get("malformed", 0) == 0
    assert run.data["console_errors"] == []


def test_immersive_vr_where_ar_is_not_offered_banner_in_the_scene_air_tap_registers(run):
    """HoloLens 2's Edge offers immersive-vr only: the page enters it, draws the banner in
    the scene (no DOM overlay) and registers with the select gesture (an air tap) alone."""
    assert run.data["vr_mode"] == "immersive-vr"
    assert run.data["vr_needed"]["text"].startswith("Register this headset first\nAir tap")
    assert run.data["vr_done"]["text"].startswith("Headset registered\nRegistered: residual")
    truth, got = pose(run.data["T_world_xr_true"]), pose(run.data["vr_T_world_xr"])
    work = np.array(run.data["targets_xr"])
    assert np.linalg.norm(got.apply(work) - truth.apply(work), axis=1).max() * 1000.0 < 2.0
    assert math.degrees(got.distance_to(truth)[1]) < 1.0

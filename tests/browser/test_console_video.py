"""The console on received video with the default transport (WebCodecs) and with JPEG, in
headless Chromium (scenarios/console_video.py): no console work without a page, and freeze
and capture frame-exact (the captured frame is the one on screen)."""

import cv2
import numpy as np
import pytest

from humantele.video.counter import read_counter


@pytest.fixture(scope="module")
def run(browser_scenario):
    # (session_helpers.VIDEO_DEMO_TIMEOUT_S: the same run, whichever module asks first)
    return browser_scenario("console_video", timeout_s=900.0)


def _idle(d: dict) -> None:
    a, b = d["before"], d["after"]
    assert not a["subscribed"] and not b["subscribed"]
    assert a["us"] == b["us"] and a["pov"] == b["pov"]  # no frame taken by the console
    r0, r1 = d["received"]
    assert r1 > r0  # while the expert received frames


@pytest.mark.e2e
@pytest.mark.slow
def test_no_console_work_without_a_page(run):
    _idle(run.data["idle_before"])
    _idle(run.data["idle_after"])
    assert run.data["default"]["open"]["subscribed"] and run.data["default"]["open"]["us"] > 0


VISITS = [("default", "webcodecs"), ("jpeg", "jpeg")]  # (visit, the transport it must have)


@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.parametrize(("visit", "transport"), VISITS)
def test_received_video_is_drawn(run, visit, transport):
    d = run.data[visit]
    assert d["transport"] == transport
    assert d["pixels"]["pov"]["mean"] > 10.0 and d["pixels"]["us"]["w"] == 640
    assert [e for e in run.data["console_errors"] if "console" in e.lower()] == []


@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.parametrize("visit", [v for v, _ in VISITS])
def test_freeze_and_capture_keep_the_frame_on_screen(run, visit):
    d = run.data[visit]
    shown, cap = d["shown"], d["capture"]
    assert cap["ok"] and cap["seq"] == shown["seq"] == d["shown_after"]["seq"]
    on_screen = cv2.imread(str(run.path(d["png"])), cv2.IMREAD_COLOR)
    saved = cv2.imread(cap["file"], cv2.IMREAD_COLOR)
    assert on_screen.shape == saved.shape
    assert on_screen.mean() > 8.0  # frozen in contact: an image, not the black of no contact
    # the frame's own number, in the picture on screen and in the file
    assert read_counter(on_screen) == read_counter(saved) == shown["seq"]
    diff = np.abs(on_screen.astype(int) - saved.astype(int)).mean()
    assert diff < 4.0, diff  # the same picture (JPEG q88 and the page's YUV->RGB apart)

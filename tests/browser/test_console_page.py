"""The sonographer's console in headless Chromium over real sim video and a scripted session
(scenarios/console_page.py)."""

import pytest

from humantele.video.sim_ultrasound import SimUltrasound, SimUltrasoundConfig


@pytest.mark.slow
def test_console_page(browser_scenario):
    d = browser_scenario("console_page", timeout_s=300.0).data
    # The two videos play: the picture changes and is not black.
    for t in ("us", "pov"):
        before, after = d["pixels"]["before"][t], d["pixels"]["after"][t]
        assert after["mean"] > 10 and before["hash"] != after["hash"], (t, before, after)
    # The force plot moves with the measured force (4 +- 2 N).
    forces = [f for f in d["force_samples"] if f is not None]
    assert len(forces) > 40 and max(forces) - min(forces) > 1.0
    # The buttons reached the session and the page shows what it did.
    assert d["commands"] == [["scan", "start"], ["clutch", True], ["scan", "stop"]]
    assert d["scan_text"] == "Stop scan 1"
    # Freeze + cine + calipers: the distance is the image distance times the pixel spacing.
    assert d["cine"]["frames"] > 10 and d["cine"]["label"].startswith("-")
    c = d["caliper"]
    assert c["seq"] == d["cine"]["seq"]
    assert c["server_mm"] == pytest.approx(c["page_mm"], rel=1e-6)  # f32 on the wire
    assert c["server_mm"] == pytest.approx(c["asked_mm"], rel=0.01)  # clicks land on whole px
    assert c["label"] == pytest.approx(c["server_mm"])
    assert d["annotation"]["ok"] and d["annotation"]["detail"] == "lower pole, right kidney"
    assert d["capture"]["ok"]
    # The still, its pose and the clip of the cine's seconds before it (the page's default).
    assert [n.rsplit(".", 1)[1] for n in d["captures"]] == ["jpg", "json", "mp4"]
    # Stale video and a lost link are shown as such, never as live; and they clear.
    s = d["stale"]
    assert "No live ultrasound" in s["us"] and "last frame" in s["us"] and s["info"] == "not live"
    assert "disconnected" in s["link"] and s["align"].endswith("–") and s["bar"] == "–"
    assert "connected ·" in d["recovered_link"]
    # Bad pages: a second console and another site's page are refused, nonsense counted.
    assert d["second_has_state"] is False and d["cross_origin"] == "refused"
    r = d["stats"]["refused"]
    assert r["second_console"] >= 1 and r["origin"] >= 1 and r["malformed"] >= 3
    assert d["stats"]["us"]["drawn"] > 10
    # The page reads the frame counter back from what it drew (the glass-to-glass figure),
    # and covers the patch on screen.
    us = d["stats"]["us"]
    assert us["counter_read"] > 10 and us["counter_read"] >= 0.9 * us["drawn"]
    assert us["capture_to_draw_p95_ms"] is not None and d["counters"]["masked"]
    # The depth scale: 0 cm at the row of the probe's face, then every cm (on this screen),
    # where the sim's scan geometry puts each depth.
    c = d["counters"]
    labels = dict(c["scale"])
    assert sorted(labels)[:3] == [0, 1, 2] and max(labels) >= 15
    g = SimUltrasound(SimUltrasoundConfig()).geometry
    px = c["scale_h"] / c["image_h"]  # screen px per image row
    for cm in (0, 5, 10, 15):
        row = g.tip_to_pixel(0.0, cm / 100.0)[0]
        assert labels[cm] == pytest.approx((row + 0.5) * px, abs=0.5), cm
    # The console page itself logged no error (the refused second console and the other
    # site's page log their refusals, which is the point).
    # Without the key, or with another run's, the page says so and drives nothing; the key
    # leaves the address bar once the page has it.
    assert "no key" in d["no_key"] and "#key=" in d["no_key"]
    assert "missing or wrong" in d["wrong_key"] and "#key" not in d["wrong_key_address"]
    assert "#key" not in d["keyed_address"]
    assert d["stats"]["refused"]["unauthorized"] >= 1
    page_errors = [e for e in d["console_errors"] if e.startswith(d["stats"]["url"])]
    assert all("409" in e for e in page_errors), page_errors

"""``humantele demo`` with the sonographer's console and the headset page open in headless
Chromium, one run (scenarios/demo_pages.py). The console: its videos play, the state is
live, the scan button records scans, freeze + calipers measure right, tools are recorded, a
second console is refused, and the page shows the daemons' end as not live. The headset page:
served, following, and the feed's added latency (pose receipt to the page's draw call) from
its echoes (the figure on a quiet machine: scenarios/pages_bench.py)."""

import json
import math

import pytest


@pytest.fixture(scope="module")
def run(browser_scenario):
    return browser_scenario("demo_pages", timeout_s=900.0)


@pytest.mark.slow
def test_console_in_the_demo(run):
    d = run.data
    # The two received videos play: frames drawn, the picture changes, not black (the
    # ultrasound is dark until the probe presses, but has its depth scale and counter).
    for t, level in (("us", 0.0), ("pov", 10.0)):
        before, after = d["pixels"]["before"][t], d["pixels"]["after"][t]
        assert after["mean"] > level and before["hash"] != after["hash"], (t, before, after)
    # Without the video tracks the console draws a stand-in, and says so on each picture.
    sim = d["sim_label"]
    assert sim["video"] == "sim" and sim["name"] == "Ultrasound: SIMULATED"
    assert sim["band"].startswith("SIMULATED IMAGE, not the patient")
    live = d["state_live"]
    assert live["link"]["state"] == "connected" and live["servo"]["alive"]
    assert live["recording"]["on"]  # calibration: whatever the follower has reported so far
    assert live["calibration"]["state"] in ("not calibrated", "calibrating", "calibrated")
    assert d["plot_draws"] > 10
    # The scan button started and stopped scans, and the expert recorded them.
    first, second = d["scans_clicked"]
    assert d["scan_button"] == f"Stop scan {second}"
    events = [(s["event"], s["scan"]) for s in d["recorded_scans"]]
    assert ("start", first) in events and ("stop", first) in events
    assert ("start", second) in events
    # Freeze, cine, calipers: the distance is the pixel distance times the pixel spacing.
    assert d["cine"]["frames"] > 5 and d["cine"]["label"].startswith("-")
    c = d["caliper"]
    assert c["server_mm"] == pytest.approx(c["page_mm"], rel=1e-6)  # f32 on the wire
    assert c["server_mm"] == pytest.approx(c["asked_mm"], rel=0.01)
    assert d["annotation"]["ok"] and d["capture"]["ok"]
    rec = [e["event"] for e in d["recorded_console"]]
    # (the capture's clip is written off the loop: recorded when it is there)
    assert [e for e in rec if e != "clip"][:5] == [
        "freeze", "caliper", "annotation", "capture", "live"]  # fmt: skip
    assert "clip" in rec
    # A second console was refused and counted; the first went on.
    assert d["second_state"] is True
    stats = d["console_stats"]
    assert stats["refused"].get("second_console", 0) >= 1
    assert d["lost_overlay"] is True
    us = stats["us"]
    figure = {k: us[k] for k in ("seen_to_draw_p50_ms", "seen_to_draw_p95_ms",
                                 "capture_to_draw_p50_ms", "capture_to_draw_p95_ms")}  # fmt: skip
    figure["page_fps"] = d["page_fps"]
    (run.out_dir / "console_latency.json").write_text(json.dumps(figure))
    print(f"console: {figure}")
    assert all(math.isfinite(v) for v in figure.values() if isinstance(v, float))
    # The page logged nothing but the refused second console and its own reconnection
    # attempts once the demo had stopped.
    consoles = [e for e in d["console_errors"] if e.startswith(d["url"])]
    unexpected = [e for e in consoles if "409" not in e and "REFUSED" not in e]
    assert unexpected == []


@pytest.mark.slow
def test_demo_serves_the_headset_page_and_measures_the_feed_latency(run):
    d = run.data["headset"]
    assert d["following"]["guide"]["live"] and d["view"]["model"] is not None
    assert d["view"]["visible"]["virtual"] and d["view"]["visible"]["ghost"]
    feed = d["feed"]
    assert feed["page_url"].startswith("https://") and feed["refused_total"] == 0
    assert d["echoes_during"] > 0
    p50, p95 = feed["draw_latency_p50_ms"], feed["draw_latency_p95_ms"]
    # Measured and written below (a figure, not a bound: a loaded machine's software WebGL
    # drew 8 s late once in CI, and a test does not judge speed); echoed, so drawn.
    assert 0 < p50 <= p95 and math.isfinite(p95)
    figure = {"echoes": feed["echoes"], "draw_latency_p50_ms": p50, "draw_latency_p95_ms": p95,
              "page_fps": d.get("page_fps")}  # fmt: skip
    (run.out_dir / "headset_feed_latency.json").write_text(json.dumps(figure))
    print(f"headset feed latency (pose receipt to draw call): {figure}")
    assert [e for e in run.data["console_errors"] if e.startswith(d["url"])] == []

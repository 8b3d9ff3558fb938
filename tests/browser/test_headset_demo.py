"""``humantele demo`` with the headset page open: the page is served and follows, and the
feed's added latency (pose receipt to the page's draw call) is measured from its echoes.

The figure is printed and written to ``headset_feed_latency.json`` in the test's directory;
for docs/benchmarks.md run it on a quiet machine with
``python tests/browser/netns.py headset_demo --arg seconds=30``."""

import json

import pytest


@pytest.mark.slow
def test_demo_serves_the_headset_page_and_measures_the_feed_latency(browser_scenario):
    run = browser_scenario("headset_demo", timeout_s=300.0, seconds=5.0)
    d = run.data
    assert d["following"]["guide"]["live"] and d["view"]["model"] is not None
    assert d["view"]["visible"]["virtual"] and d["view"]["visible"]["ghost"]
    feed = d["feed"]
    assert feed["page_url"].startswith("https://") and feed["refused_total"] == 0
    assert d["echoes_during"] > 0
    p50, p95 = feed["draw_latency_p50_ms"], feed["draw_latency_p95_ms"]
    assert 0 < p50 <= p95 < 5000
    figure = {"echoes": feed["echoes"], "draw_latency_p50_ms": p50, "draw_latency_p95_ms": p95,
              "page_fps": d.get("page_fps")}  # fmt: skip
    (run.out_dir / "headset_feed_latency.json").write_text(json.dumps(figure))
    print(f"headset feed latency (pose receipt to draw call): {figure}")
    assert d["console_errors"] == []

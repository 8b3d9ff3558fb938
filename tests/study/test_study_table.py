"""The study's table from small recordings this test makes (known lag, offset, video gaps,
staleness), the freeze definition, the verdict and its causes, and the charts."""

import json

import numpy as np
import pytest

from humantele.recording import Recorder
from humantele.recording.synthetic import SyntheticSession, write_synthetic
from humantele.study import table

# humantele.study.charts is imported by the tests that use it: it imports matplotlib (0.9 s),
# which every xdist worker paid again when it collected this module

LAG_S, OFFSET_Y_MM = 0.4, 20.0
CONDITION = {"name": "c1", "delay_ms": 50.0, "jitter_ms": 0.0, "loss_pct": 2.0,
             "bandwidth_kbps": 0.0}  # fmt: skip
# write_synthetic: 30 s from t = 1000 (both clocks), 1 s gaps: scans 1001-1014.5, 1015.5-1029
SCAN1, SCAN2 = (1001.0, 1014.5), (1015.5, 1029.0)
HOLE = (1005.0, 1006.0)  # no US frame decoded in here (scan 1)


def _run_dir(tmp_path, name="c1-s1"):
    d = tmp_path / name
    d.mkdir()
    cfg = SyntheticSession(
        duration_s=30.0, n_scans=2, trajectory="sine", amplitude_mm=30.0, frequency_hz=0.25,
        lag_s=LAG_S, offset_mm=(0.0, OFFSET_Y_MM, 0.0), session_id="t1", expert_rate_hz=200.0,
    )  # fmt: skip
    write_synthetic(d / "session.expert.mcap", cfg, d / "session.follower.mcap")
    rec = Recorder(d / "session.extra.mcap", "demo", session_id="t1")
    for name, fps, age in (("us", 20.0, 0.100), ("pov", 25.0, 0.050)):
        for k, t in enumerate(np.arange(1000.0, 1030.0, 1.0 / fps)):
            if name == "us" and HOLE[0] < t < HOLE[1]:
                continue
            rec.write("/expert/video_frame", float(t),
                      {"stream": name, "seq": k, "event": "received", "age_s": age})  # fmt: skip
    for t in range(1001, 1031):  # once a second: stale 1 s in each report from 1017 to 1028
        stale = 1.0 if 1017 <= t <= 1028 else 0.0
        rec.write("/follower/latency", float(t), {"name": "pose_stale_s", "value_s": stale})
        rec.write("/follower/latency", float(t), {"name": "pose_one_way", "value_s": 0.06})
    rec.write("/follower/calibration", 990.0, {"event": "point", "landmark": "xiphoid"})
    rec.close()
    spec = {"condition": CONDITION, "seed": 1, "scans": 2, "scan_s": 13.5, "gap_s": 1.0,
            "video": True}  # fmt: skip
    demo = {"servo_rate_hz": 1000.0, "servo_overruns": 0, "link_connections": 2}
    summary = {"spec": spec, "demo": demo, "load_at_start": [3.5, 2.0, 1.0]}
    (d / "summary.json").write_text(json.dumps(summary))
    return d, summary


@pytest.fixture(scope="module")
def recorded_rows(tmp_path_factory):
    """The rows of one recorded run (:func:`_run_dir`), read once for the two tests that
    check them (neither changes them)."""
    d, summary = _run_dir(tmp_path_factory.mktemp("run"))
    return table.run_scans(d, summary)


def test_rows_from_a_recorded_run_give_the_known_answers(recorded_rows):
    rows = recorded_rows
    assert [r["scan"] for r in rows] == [1, 2]
    r1, r2 = rows
    assert r1["condition"] == "c1" and r1["delay_ms"] == 50.0 and r1["loss_pct"] == 2.0
    # alignment: the paper's figures, from humantele.analysis; the offset shows along y
    assert r1["mean_error_y_mm"] == pytest.approx(OFFSET_Y_MM, abs=0.5)
    assert r1["position_rmse_mm"] > r1["centered_position_rmse_mm"] > 5.0  # the lag's share
    # the lag that best explains the follower, and with it removed nothing is left
    assert r1["effective_lag_s"] == pytest.approx(LAG_S, abs=0.011)
    assert r1["lag_removed_centered_mm"] < 0.5
    # video: US 20 fps with one hole of HOLE -> one freeze of the gap around it
    gap = 1006.0 - 1004.95
    span = SCAN1[1] - SCAN1[0]
    assert r1["us_freezes_per_min"] == pytest.approx(60.0 / span)
    assert r1["us_frozen_pct"] == pytest.approx(100.0 * gap / span, abs=0.1)
    assert r1["pov_freezes_per_min"] == 0.0 and r1["pov_frozen_pct"] == 0.0
    assert r2["us_freezes_per_min"] == 0.0
    assert r1["us_age_p50_ms"] == pytest.approx(100.0) and r1["pov_age_p95_ms"] == pytest.approx(
        50.0
    )
    assert r1["us_fps"] == pytest.approx(20.0 - 20.0 / span, abs=0.2)
    # the pose stream: never stale in scan 1; 12 s of 13.5 in scan 2
    assert r1["stale_pct"] == 0.0
    assert r2["stale_pct"] == pytest.approx(100.0 * 12.0 / (SCAN2[1] - SCAN2[0]))
    assert r1["pose_age_p50_ms"] == pytest.approx(60.0)
    # set-up: the first landmark (990) to the model at the expert (scan 1 less 2 s)
    assert r1["setup_s"] == pytest.approx(SCAN1[0] - 2.0 - 990.0, abs=1e-3)
    assert r1["servo_rate_hz"] == 1000.0
    assert r1["link_drops"] == 1 and r1["load_1min"] == 3.5  # two connections: one drop


def test_the_condition_summary_and_the_markdown(recorded_rows, tmp_path):
    from humantele.study.charts import write_charts

    rows = recorded_rows
    summ = table.summarize(rows, [CONDITION, {**CONDITION, "name": "not-run"}])
    s, missing = summ
    assert s["scans"] == 2 and s["runs"] == 1
    assert s["stale_pct"] == pytest.approx(np.mean([r["stale_pct"] for r in rows]))
    assert s["stale_pct_sd"] == pytest.approx(np.std([r["stale_pct"] for r in rows], ddof=1))
    assert missing["scans"] == 0 and missing["follows"] is None
    md = table.markdown(rows, summ, "header line")
    assert md.startswith("header line")
    assert "| c1 | 50 | 2 | - | 2 |" in md  # the condition's row
    assert "31.9 ± 10.2" in md  # the 750 km study beside it
    assert md.count("\n| c1 | 1 | ") == 2  # per scan: two rows of seed 1
    assert "unimpaired link" not in md  # c1 is impaired: no baseline to judge the machine by
    base = {**s, "name": "lan", "delay_ms": 0.0, "loss_pct": 0.0, "us_frozen_pct": 40.0}
    assert "on the unimpaired link (lan) the picture is itself frozen 40 / 0 %" in (
        table.markdown(rows, [base])
    )
    paths = write_charts(summ, tmp_path / "img")
    assert [p.name for p in paths] == ["study_alignment_vs_delay.png", "study_freezes_vs_loss.png"]
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in paths)


def test_freezes_follow_the_webrtc_definition():
    t = np.arange(0.0, 10.0, 0.05)  # 20 fps
    f = table.freezes(t, 0.0, 10.0)
    assert f["freezes_per_min"] == 0.0 and f["frozen_pct"] == 0.0
    assert f["fps"] == pytest.approx(20.0)
    # a gap of 0.1 s is under 50 ms + 150 ms: not a freeze; one of 0.3 s is
    short = t[(t < 3.0) | (t > 3.01)]
    assert table.freezes(short, 0.0, 10.0)["freezes_per_min"] == 0.0
    long = t[(t < 2.99) | (t > 3.24)]  # 2.95 then 3.25
    f = table.freezes(long, 0.0, 10.0)
    assert f["freezes_per_min"] == pytest.approx(6.0)
    assert f["frozen_pct"] == pytest.approx(100.0 * 0.3 / 10.0, abs=0.01)
    assert table.freezes(np.array([]), 0.0, 10.0)["frozen_pct"] == 100.0  # no picture at all
    assert table.freezes(t, 0.0, 10.0)["frames"] == 200


def _cond(**kw):
    base = {"delay_ms": 300.0, "position_rmse_mm": 30.0, "centered_position_rmse_mm": 10.0,
            "effective_lag_s": 0.65, "lag_removed_centered_mm": 3.0, "mean_error_y_mm": 1.0,
            "stale_pct": 1.0, "us_frozen_pct": 2.0, "pov_frozen_pct": 1.0}  # fmt: skip
    return {**base, **kw}


def test_the_verdict_names_the_cause_from_the_figures():
    assert table.verdict(_cond()) == {"follows": True, "cause": ""}
    v = table.verdict(_cond(centered_position_rmse_mm=25.0))
    assert not v["follows"] and v["cause"].startswith("pose age")
    assert "300 ms" in v["cause"] and "0.65 s" in v["cause"]
    v = table.verdict(_cond(position_rmse_mm=60.0, lag_removed_centered_mm=30.0,
                            mean_error_y_mm=-45.0))  # fmt: skip
    assert not v["follows"] and "haptic model against the real surface" in v["cause"]
    v = table.verdict(_cond(stale_pct=80.0))
    assert not v["follows"] and v["cause"].startswith("pose staleness")
    v = table.verdict(_cond(us_frozen_pct=90.0))
    assert v["follows"] and v["cause"].startswith("video freezes")  # the expert's picture only
    v = table.verdict(_cond(stale_pct=30.0, link_drops=1))  # under half: it still follows
    assert v["follows"] and v["cause"].startswith("the link dropped and reconnected")
    v = table.verdict(_cond(position_rmse_mm=60.0, lag_removed_centered_mm=30.0))
    assert not v["follows"] and "no single cause" in v["cause"]


def test_where_it_breaks_is_the_first_condition_that_does_not_follow():
    def cond(name, delay, loss, centered, **kw):
        s = _cond(delay_ms=delay, centered_position_rmse_mm=centered, **kw)
        return {**s, "name": name, "loss_pct": loss, "bandwidth_kbps": 0.0,
                **table.verdict({**s, "delay_ms": delay})}  # fmt: skip

    summary = [
        cond("d0", 0.0, 0.0, 6.0), cond("d100", 100.0, 0.0, 10.0),
        cond("d200", 200.0, 0.0, 14.0), cond("d400", 400.0, 0.0, 22.0),
        cond("l5", 50.0, 5.0, 8.0), cond("l10", 50.0, 10.0, 8.0, stale_pct=70.0),
    ]  # fmt: skip
    b = table.breaking_points(summary)
    assert b["delay"]["name"] == "d400" and b["loss"]["name"] == "l10"
    # 6 + 0.04 mm/ms: the line crosses 18.5 mm at 312.5 ms
    assert b["delay_crossing_ms"] == pytest.approx(312.5)
    text = table.breaking_text(b)
    assert "stops following at 400 ms" in text and "at 10 %" in text and "pose staleness" in text
    fine = table.breaking_points(summary[:3])
    assert fine["delay"] is None and fine["largest_delay_ms"] == 200.0
    assert "still follows at the largest delay run, 200 ms" in table.breaking_text(fine)


def _run(name, delay, jitter=0.0, loss=0.0, kbps=0.0, **kw):
    """A synthetic condition row with its verdict, as summarize() makes it."""
    s = _cond(delay_ms=delay, **kw)
    return {**s, "name": name, "jitter_ms": jitter, "loss_pct": loss, "bandwidth_kbps": kbps,
            **table.verdict(s)}  # fmt: skip


def test_a_condition_that_changes_several_things_is_named_with_its_cause_not_an_axis():
    """Issue 31's run: the satellite link (300 ms, 1 % loss, 2000 kbit/s) broke on pose age;
    the summary had blamed loss ('stops following at 1 %') and said it still follows at the
    largest delay run, 4 ms, though 300 ms was run."""
    summary = [
        _run("lan", 0.0), _run("750km", 4.0, 1.5),
        _run("rural", 60.0, 20.0, loss=3.0, kbps=1500.0, us_frozen_pct=83.0),
        _run("lossy", 0.0, loss=15.0, us_frozen_pct=25.0),
        _run("satellite", 300.0, 30.0, loss=1.0, kbps=2000.0, centered_position_rmse_mm=23.6),
    ]  # fmt: skip
    b = table.breaking_points(summary)
    assert b["loss"] is None and b["largest_loss_pct"] == 15.0  # the loss-only condition
    assert b["delay"] is None and b["largest_delay_ms"] == 4.0
    assert b["bandwidth"] is None and b["thinnest_kbps"] is None
    assert [s["name"] for s in b["combined"]] == ["rural", "satellite"]
    text = table.breaking_text(b)
    assert "stops following at 1 %" not in text
    assert "still follows at the largest loss run, 15 % each way" in text
    sat = next(line for line in text.splitlines() if "satellite" in line)
    assert "300 ms ± 30, 1 % loss, 2000 kbit/s" in sat and "does not follow: pose age" in sat
    assert "bandwidth and delay and loss at once" in sat and "no single axis" in sat
    rural = next(line for line in text.splitlines() if "rural" in line)
    assert "it still follows (video freezes" in rural


def test_an_axis_counts_conditions_whose_other_impairments_were_harmless_alone():
    summary = [
        _run("lan", 0.0), _run("d50", 50.0, 5.0), _run("d400", 400.0, 40.0, stale_pct=80.0),
        _run("d50-l5", 50.0, 5.0, loss=5.0),
        _run("d50-l10", 50.0, 5.0, loss=10.0, stale_pct=70.0),
        _run("d400-l1", 400.0, 40.0, loss=1.0, stale_pct=90.0),  # 400 ms broke alone
        _run("cap1000", 0.0, kbps=1000.0), _run("cap300", 0.0, kbps=300.0, stale_pct=60.0),
        _run("d50-cap500", 50.0, 5.0, kbps=500.0),
    ]  # fmt: skip
    b = table.breaking_points(summary)
    assert b["delay"]["name"] == "d400"
    assert b["loss"]["name"] == "d50-l10"  # at 50 ms, which followed on its own
    assert b["bandwidth"]["name"] == "cap300" and b["thinnest_kbps"] == 500.0
    assert [s["name"] for s in b["combined"]] == ["d400-l1"]  # 400 ms alone did not follow
    text = table.breaking_text(b)
    assert "stops following at 300 kbit/s (cap300): pose staleness" in text
    assert "d400-l1 (400 ms ± 40, 1 % loss) changes delay and loss at once" in text


def test_the_thin_link_chart_is_drawn_from_capped_conditions(tmp_path):
    from humantele.study.charts import write_charts

    summary = []
    for loss in (0.0, 3.0, 10.0):
        for kbps in (500.0, 1000.0, 1500.0, 3000.0):
            s = _run(f"b{kbps:g}-l{loss:g}", 4.0, 1.5, loss=loss, kbps=kbps)
            s.update(
                us_live_pct=100.0 - loss * 3000.0 / kbps,
                us_age_p95_ms=40.0 + loss * 10,
                us_ssim=0.8 + kbps / 30000.0,
                loss_pct=loss,
                position_rmse_mm=30.0,
            )
            summary.append(
                {
                    **s,
                    **{
                        f"{k}_sd": None
                        for k in (
                            "us_live_pct",
                            "us_age_p95_ms",
                            "us_ssim",
                            "position_rmse_mm",
                            "centered_position_rmse_mm",
                        )
                    },
                }
            )
    paths = write_charts(summary, tmp_path)
    assert [p.name for p in paths][-1] == "study_us_thin_links.png"
    assert paths[-1].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "study_us_thin_links.png" not in [p.name for p in write_charts(summary[:1], tmp_path)]


def test_a_track_turned_off_reads_off_not_live():
    # the POV off sends one frame every 5 s: by the typical interval alone nothing froze
    off = np.arange(0.0, 12.0, 5.0)
    f = table.freezes(off, 0.0, 12.0)
    assert f["off"] is True and f["frozen_pct"] is None and f["freezes_per_min"] is None
    assert table.freezes(np.arange(0.0, 10.0, 0.25), 0.0, 10.0)["off"] is False  # 4 fps: live
    row = {"us_frozen_pct": 2.0, "us_off": False, "pov_frozen_pct": None, "pov_off": True}
    assert table._frozen(row, "us") == "2.0" and table._frozen(row, "pov") == "off"
    # a condition: off in all its scans, or in some (the mean is of the others)
    assert table._frozen({"scans": 2, "pov_off_scans": 2, "pov_frozen_pct": None}, "pov") == "off"
    some = table._frozen({"scans": 2, "pov_off_scans": 1, "pov_frozen_pct": 10.0}, "pov")
    assert some == "10.0 (off 1/2)"


def test_bounded_figures_keep_their_error_bars_within_their_bounds():
    from humantele.study.charts import clipped_errors

    below, above = clipped_errors([0.95, 0.5], [0.08, 0.08], 0.0, 1.0)
    assert above == pytest.approx([0.05, 0.08]) and below == pytest.approx([0.08, 0.08])
    below, above = clipped_errors([3.0, 99.0], [5.0, 5.0], 0.0, 100.0)
    assert below == pytest.approx([3.0, 5.0]) and above == pytest.approx([5.0, 1.0])
    assert clipped_errors([300.0], [500.0], 0.0, None) == [[300.0], [500.0]]

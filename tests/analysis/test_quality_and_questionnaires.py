"""Image-quality scores, Spearman, NASA-TLX and usability from CSV; clear errors on bad rows."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

# humantele.analysis.quality is imported by the tests that use it: it imports scipy.stats
# (1.5 s), which every xdist worker paid again when it collected this module
from humantele.analysis.questionnaires import (
    read_tlx,
    read_usability,
    summarize_tlx,
    summarize_usability,
)
from humantele.config import ConfigError

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_long_and_wide_layouts_read_the_same(tmp_path):
    from humantele.analysis.quality import read_scores

    wide = _write(tmp_path, "w.csv", "scan,target,R1,R2\n1,aorta,5,4\n1,ivc,0,3\n2,aorta,3,3\n")
    long = _write(
        tmp_path,
        "l.csv",
        "scan,target,rater,score\n1,aorta,R1,5\n1,aorta,R2,4\n1,ivc,R1,0\n1,ivc,R2,3\n"
        "2,aorta,R1,3\n2,aorta,R2,3\n",
    )
    assert sorted(read_scores(wide), key=repr) == sorted(read_scores(long), key=repr)


def test_summary_follows_the_papers_definitions(tmp_path):
    # 4 images x 2 raters; image (2, ivc) is missing for one rater -> not captured.
    from humantele.analysis.quality import read_scores, summarize_quality

    p = _write(
        tmp_path,
        "s.csv",
        "scan,target,R1,R2\n1,aorta,5,5\n1,ivc,4,2\n2,aorta,3,4\n2,ivc,0,4\n",
    )
    q = summarize_quality(read_scores(p))
    assert q["images"] == 4 and q["images_missing"] == 1 and q["images_captured"] == 3
    captured = np.array([5, 5, 4, 2, 3, 4])
    assert q["mean_captured"] == pytest.approx(captured.mean())
    assert q["sd_captured"] == pytest.approx(captured.std(ddof=1))
    assert q["share_ge3_all_raters"] == pytest.approx(2 / 3)  # (1,aorta), (2,aorta)
    assert q["share_5_all_raters"] == pytest.approx(1 / 3)
    assert q["score_counts"] == {"0": 1, "1": 0, "2": 1, "3": 1, "4": 3, "5": 2}
    assert q["scan_quality"] == {"1": pytest.approx(4.0), "2": pytest.approx(3.5)}
    without = summarize_quality(read_scores(p), exclude_scans=(1,))
    assert without["images"] == 2 and without["images_captured"] == 1


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("scan,target,R1\n1,aorta,6\n", "row 2: column 'R1': '6' is not an integer 0-5"),
        ("scan,target,R1\n1,aorta,4\n1,ivc,x\n", "row 3: column 'R1': 'x' is not a number"),
        ("scan,target,R1\n1,aorta,4.5\n", "row 2: column 'R1'"),
        ("scan,target,R1\n-1,aorta,4\n", "row 2: column 'scan'"),
        ("scan,target,R1\n1,,4\n", "row 2: column 'target': empty"),
        ("scan,target,R1\n1,aorta,4\n1,aorta,3\n", "row 3: scan 1 target 'aorta' rater 'R1' twice"),
        ("scan,target,rater,score\n1,a,R1,4\n1,b,R2,4\n", "no score from"),
        ("target,R1\na,4\n", "needs columns 'scan' and 'target'"),
        ("scan,target,R1\n1,aorta,4,5\n", "row 2: more cells"),
    ],
)
def test_bad_score_files_name_the_row_and_column(tmp_path, text, message):
    from humantele.analysis.quality import read_scores, summarize_quality

    p = _write(tmp_path, "bad.csv", text)
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        summarize_quality(read_scores(p))


def test_spearman_matches_known_values():
    from humantele.analysis.quality import spearman

    assert spearman([1, 2, 3, 4], [10, 20, 30, 40])["rho"] == pytest.approx(1.0)
    assert spearman([1, 2, 3, 4], [4, 3, 2, 1])["rho"] == pytest.approx(-1.0)
    r = spearman([1, 2, 3, 4, 5], [2, 1, 4, 3, 5])  # d^2 sum = 4: rho = 1 - 6*4/120 = 0.8
    assert r["rho"] == pytest.approx(0.8) and 0.0 < r["p"] < 1.0 and r["n"] == 5
    assert spearman([1, 2], [3, 4])["rho"] is None
    assert spearman([1, 1, 1], [3, 4, 5])["rho"] is None


def test_tlx_is_raw_unweighted(tmp_path):
    p = _write(
        tmp_path,
        "tlx.csv",
        "follower,mental,physical,temporal,performance,effort,frustration\n"
        "F1,10,20,30,40,50,60\nF2,30,20,10,0,50,100\n",
    )
    t = summarize_tlx(read_tlx(p))
    assert t["n"] == 2
    assert t["subscales"]["mental"]["mean"] == pytest.approx(20.0)
    assert t["subscales"]["frustration"]["sd"] == pytest.approx(np.std([60, 100], ddof=1))
    assert t["raw_tlx"]["mean"] == pytest.approx((35 + 35) / 2)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "mental,physical,temporal,performance,effort,frustration\n1,2,3,4,5,101\n",
            "row 2: column 'frustration': '101' is not a number 0-100",
        ),
        ("mental,physical,temporal,performance,effort\n1,2,3,4,5\n", "missing column"),
        (
            "mental,physical,temporal,performance,effort,frustration,mood\n1,2,3,4,5,6,7\n",
            "unknown column",
        ),
        (
            "follower,mental,physical,temporal,performance,effort,frustration\n"
            "Jane Doe,1,2,3,4,5,6\n",
            "row 2: column 'follower'",
        ),
    ],
)
def test_bad_tlx_files_name_the_problem(tmp_path, text, message):
    with pytest.raises(ConfigError, match=message):
        read_tlx(_write(tmp_path, "t.csv", text))


def test_usability_items_are_integers_0_to_4(tmp_path):
    head = "easy_to_use,follow_virtual,point_fitting,follow_instructions,learn_before,"
    head += "learn_quickly,cumbersome,confident\n"
    good = _write(tmp_path, "u.csv", head + "4,4,3,4,1,3,0,3\n3,4,4,4,2,4,1,4\n")
    u = summarize_usability(read_usability(good))
    assert u["items"]["easy_to_use"]["mean"] == pytest.approx(3.5)
    assert u["items"]["cumbersome"]["lower_is_better"] is True
    assert u["items"]["follow_virtual"]["share_agree"] == pytest.approx(1.0)
    with pytest.raises(ConfigError, match="row 2: column 'confident'"):
        read_usability(_write(tmp_path, "b.csv", head + "4,4,3,4,1,3,0,3.5\n"))


def test_the_example_files_are_valid():
    from humantele.analysis.quality import read_scores, summarize_quality

    q = summarize_quality(read_scores(EXAMPLES / "scores.csv"))
    assert q["images"] == 55 and q["raters"] == ["R1", "R2"]
    assert summarize_tlx(read_tlx(EXAMPLES / "nasa_tlx.csv"))["n"] == 10
    assert summarize_usability(read_usability(EXAMPLES / "usability.csv"))["n"] == 10

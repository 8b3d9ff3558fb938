"""`humantele analyze --rating-sheet` / `--ratings`: the blinded rating of the paper. A drawn
sheet hides the scans; a filled sheet is checked against its key and joined to the scans; a
perfect rater of the sim ultrasound's known quality gives the known answer."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

# humantele.analysis.rating is imported by the tests that use it: it imports scipy.stats
# (1.5 s), which every xdist worker paid again when it collected this module
from humantele.cli import main
from humantele.recording.synthetic import SyntheticSession, write_synthetic

QUALITY = [0.2, 0.8, 0.4, 1.0, 0.6]  # the sim US's known quality of each scan (0-1)


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "session.mcap"
    cfg = SyntheticSession(duration_s=26.0, n_scans=5, expert_rate_hz=200.0, tremor_mm=3.0,
                           tremor_deg=2.0, lag_s=0.2, us_quality=QUALITY, seed=3)  # fmt: skip
    write_synthetic(path, cfg)
    return path


def draw(recording: Path, tmp: Path, *extra: str) -> Path:
    sheet = tmp / "sheet.csv"
    assert main(["analyze", str(recording), "--rating-sheet", str(sheet), *extra]) == 0
    return sheet


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def fill(sheet: Path, score: dict[str, str], out: Path) -> Path:
    """The sheet with ``score[clip]`` in every rater column (the key copied beside it)."""
    from humantele.analysis.rating import key_path

    data = rows(sheet)
    raters = [k for k in data[0] if k != "clip"]
    with open(out, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["clip", *raters])
        for r in data:
            w.writerow([r["clip"], *[score[r["clip"]]] * len(raters)])
    key_path(out).write_bytes(key_path(sheet).read_bytes())
    return out


def test_the_sheet_hides_scan_session_and_participants(recording, tmp_path, capsys):
    from humantele.analysis.rating import ID_ALPHABET, key_path

    sheet = draw(recording, tmp_path, "--raters", "R1,R2")
    capsys.readouterr()
    data, key = rows(sheet), rows(key_path(sheet))
    assert list(data[0]) == ["clip", "R1", "R2"] and len(data) == 5
    assert all(r["R1"] == "" and r["R2"] == "" for r in data)
    assert {r["clip"] for r in data} == {r["clip"] for r in key}
    assert sorted(int(r["scan"]) for r in key) == [1, 2, 3, 4, 5]
    for r in data:  # random ids: nothing of the session, scan or participants in them
        assert len(r["clip"]) == 5 and set(r["clip"]) <= set(ID_ALPHABET)
    text = sheet.read_text()
    for secret in ("sim0001", "F01", "S1", "scan"):
        assert secret not in text
    # a second draw: other ids
    (tmp_path / "again").mkdir()
    other = draw(recording, tmp_path / "again")
    assert not {r["clip"] for r in rows(other)} & {r["clip"] for r in data}


def test_the_order_is_shuffled(recording, tmp_path):
    from humantele.analysis.rating import key_path

    orders = set()
    for seed in range(6):
        d = tmp_path / str(seed)
        d.mkdir()
        sheet = draw(recording, d, "--seed", str(seed))
        scan_of = {r["clip"]: int(r["scan"]) for r in rows(key_path(sheet))}
        orders.add(tuple(scan_of[r["clip"]] for r in rows(sheet)))
    assert len(orders) > 1  # 6 draws in one order by chance: (1/120)**5


def test_clips_are_copied_under_their_ids_and_a_missing_one_named(recording, tmp_path, capsys):
    from humantele.analysis.rating import key_path

    exported = tmp_path / "export"
    exported.mkdir()
    for scan in (1, 2, 3, 4):  # scan 5 not exported
        (exported / f"sim0001_scan{scan}_us.mp4").write_bytes(f"video {scan}".encode())
    sheet = draw(recording, tmp_path, "--clips", str(exported))
    err = capsys.readouterr().err
    key = {r["clip"]: int(r["scan"]) for r in rows(key_path(sheet))}
    clips = tmp_path / "sheet_clips"
    for clip, scan in key.items():
        f = clips / f"{clip}.mp4"
        assert f.read_bytes() == f"video {scan}".encode() if scan != 5 else not f.exists()
    missing = [line for line in err.splitlines() if "has no video" in line]
    assert len(missing) == 1 and "sim0001_scan5_us.mp4" in missing[0]


def test_a_perfect_rater_of_the_known_quality_gives_the_known_answer(recording, tmp_path, capsys):
    from humantele.analysis.rating import key_path

    sheet = draw(recording, tmp_path, "--raters", "A,B")
    key = rows(key_path(sheet))
    score = {r["clip"]: str(round(5 * QUALITY[int(r["scan"]) - 1])) for r in key}
    filled = fill(sheet, score, tmp_path / "filled.csv")
    capsys.readouterr()
    assert main(["analyze", str(recording), "--json"]) == 0
    sim = json.loads(capsys.readouterr().out)["quality"]
    assert sim["source"] == "sim"
    assert main(["analyze", str(recording), "--ratings", str(filled), "--json"]) == 0
    q = json.loads(capsys.readouterr().out)["quality"]
    assert q["source"] == "ratings" and q["raters"] == ["A", "B"]
    assert q["images"] == 5 and q["images_missing"] == 0
    assert q["mean_captured"] == pytest.approx(3.0)  # scores 1..5, each from both raters
    assert q["share_5_all_raters"] == pytest.approx(0.2)
    assert q["scan_quality"] == {f"sim0001/{s}": 5 * QUALITY[s - 1] for s in range(1, 6)}
    for metric, sp in q["spearman"].items():  # rated ranks = the known quality's ranks
        assert sp["n"] == 5 and sp["rho"] == pytest.approx(sim["spearman"][metric]["rho"])
    # and as text: the paper's image-quality lines
    assert main(["analyze", str(recording), "--ratings", str(filled)]) == 0
    out = capsys.readouterr().out
    assert "Image quality (0-5)" in out and "Spearman quality vs Position RMSE (mm)" in out


def bad_sheet(sheet: Path, tmp: Path, edit) -> Path:
    from humantele.analysis.rating import key_path

    data = rows(sheet)
    lines = [["clip", "rater1"]] + [[r["clip"], "3"] for r in data]
    edit(lines)
    out = tmp / "bad.csv"
    with open(out, "w", newline="") as f:
        csv.writer(f).writerows(lines)
    key_path(out).write_bytes(key_path(sheet).read_bytes())
    return out


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda L: L.pop(2), "1 of 5 clips not rated"),
        (lambda L: L.append(["ZZZZZ", "3"]), "clip 'ZZZZZ' is not in the key"),
        (lambda L: L.append(list(L[1])), "twice"),
        (lambda L: L[3].__setitem__(1, "good"), "'good' is not a number"),
        (lambda L: L[3].__setitem__(1, "7"), "'7' is not an integer 0-5"),
        (lambda L: L[3].__setitem__(1, "2.5"), "'2.5' is not an integer 0-5"),
        (lambda L: L[3].__setitem__(1, ""), "no score for clip"),
        (lambda L: L[0].__setitem__(0, "id"), "no 'clip' column"),
    ],
)
def test_a_bad_sheet_is_one_clear_line(recording, tmp_path, capsys, edit, message):
    sheet = draw(recording, tmp_path)
    bad = bad_sheet(sheet, tmp_path, edit)
    capsys.readouterr()
    assert main(["analyze", str(recording), "--ratings", str(bad)]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert len([line for line in err.splitlines() if line.strip()]) <= 2  # the prefix + the line


def test_a_foreign_file_or_a_sheet_without_key_is_one_line(recording, tmp_path, capsys):
    from humantele.analysis.rating import key_path

    foreign = tmp_path / "photo.csv"
    foreign.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00binary")
    assert main(["analyze", "--ratings", str(foreign)]) == 2
    err = capsys.readouterr().err
    assert "no key for" in err and "Traceback" not in err
    key_path(foreign).write_text("not,a,key\n1,2,3\n")
    assert main(["analyze", "--ratings", str(foreign)]) == 2
    err = capsys.readouterr().err
    assert "not a rating key" in err and "Traceback" not in err
    sheet = draw(recording, tmp_path)  # a real key beside a binary sheet
    key_path(foreign).write_bytes(key_path(sheet).read_bytes())
    capsys.readouterr()
    assert main(["analyze", "--ratings", str(foreign)]) == 2
    err = capsys.readouterr().err
    assert "not a CSV text file" in err and "Traceback" not in err


def test_a_sheet_is_never_overwritten(recording, tmp_path, capsys):
    draw(recording, tmp_path)
    assert main(["analyze", str(recording), "--rating-sheet", str(tmp_path / "sheet.csv")]) == 2
    assert "exists" in capsys.readouterr().err

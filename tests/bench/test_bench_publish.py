"""``bench.publish``: how every bench ends (its section written unless --no-write, where it
went said unless --json, the JSON summary last), and ``bench.save_chart``."""

from __future__ import annotations

import argparse
import json

from humantele.bench import publish, pyplot, save_chart
from humantele.report import section_rows, write_section


def _args(**kw) -> argparse.Namespace:
    return argparse.Namespace(**{"no_write": False, "json": False, **kw})


def test_writes_its_section_keeps_the_others_and_says_where(tmp_path, capsys):
    md = tmp_path / "benchmarks.md"
    write_section("other", "## other\n\nkept", md)
    publish("mine", "## mine\n\n| a | b |\n|---|---|\n| 1 | 2 |", {"x": 1}, _args(), md)
    assert capsys.readouterr().out.splitlines() == [f"wrote {md}"]  # no JSON without --json
    text = md.read_text()
    assert "kept" in text and section_rows("mine", 2, md) == [["1", "2"]]


def test_json_is_the_last_line_and_alone_with_json(tmp_path, capsys):
    md = tmp_path / "benchmarks.md"
    publish("mine", "## mine", {"x": 1.5, "path": tmp_path}, _args(json=True), md)
    lines = capsys.readouterr().out.splitlines()
    assert json.loads(lines[-1]) == {"x": 1.5, "path": str(tmp_path)} and len(lines) == 1
    assert "## mine" in md.read_text()


def test_no_write_leaves_the_file_alone(tmp_path, capsys):
    md = tmp_path / "benchmarks.md"
    publish("mine", "## mine", {"x": 1}, _args(no_write=True, json=True), md)
    assert not md.exists()
    assert json.loads(capsys.readouterr().out) == {"x": 1}


def test_always_json_prints_it_without_the_flag_and_a_bench_without_the_flag(tmp_path, capsys):
    md = tmp_path / "benchmarks.md"
    publish("mine", "## mine", [1, 2], _args(no_write=True), md, always_json=True)
    assert capsys.readouterr().out.splitlines() == ["[1, 2]"]
    publish("mine", "## mine", None, argparse.Namespace(no_write=False), md)  # no --json option
    assert capsys.readouterr().out.splitlines() == [f"wrote {md}"]


def test_save_chart_makes_the_folder_and_closes_the_figure(tmp_path):
    plt = pyplot()
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    path = save_chart(fig, tmp_path / "img" / "chart.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not plt.fignum_exists(fig.number)

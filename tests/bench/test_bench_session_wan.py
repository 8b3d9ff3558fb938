"""`humantele bench session` through coturn and the WAN emulator, its options and its table."""

import json

import pytest

from humantele.bench import session
from humantele.cli import main
from humantele.transport.turnserver import TurnServer

needs_turn = pytest.mark.skipif(
    not TurnServer.available(),
    reason="no turnserver (system package coturn)",
)


@needs_turn
@pytest.mark.slow
@pytest.mark.whole_session  # one at a time across the lanes (tests/session_slot.py)
def test_bench_session_through_turn_and_the_delay_relay(capsys):
    argv = ["bench", "session", "--seconds", "1", "--rate", "200", "--json", "--no-write"]
    assert main([*argv, "--delay-ms", "10", "--loss", "1", "--seed", "5"]) == 0
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert s["link"] == "TURN + 10 ms, 1 % loss"
    assert s["turn"] is True
    assert s["ice_pair"] == {"expert": "relay/relay", "follower": "relay/relay"}
    assert s["netem"]["delay_s"] == pytest.approx(0.010) and s["netem"]["loss"] == 0.01
    relay = s["relay"]
    assert relay["clients"] >= 1 and relay["up"]["forwarded"] >= 150
    assert relay["up"]["held_mean_s"] >= 0.010
    assert relay["up"]["lost"] + relay["down"]["lost"] >= 1  # ~1 % of a few hundred each way
    assert 80.0 < s["delivered_pct"] <= 100.0
    assert 8.0 <= s["pose_age_ms"]["p50"] <= 150.0  # 10 ms one way, busy machine above
    assert s["rtt_ms"] >= 19.0  # the sync's round trip crosses the emulator both ways


def test_bad_emulator_options_fail_before_starting_anything(capsys):
    base = ["bench", "session", "--no-write"]
    assert main([*base, "--loss", "150"]) == 2
    assert "--loss 150" in capsys.readouterr().err
    assert main([*base, "--delay-ms", "-3"]) == 2
    assert "--delay-ms -3" in capsys.readouterr().err
    assert main([*base, "--load", "-1"]) == 2
    assert "--load -1" in capsys.readouterr().err


@pytest.mark.parametrize(
    "flags, label",
    [
        ([], "loopback"),
        (["--turn"], "TURN (coturn)"),
        (["--delay-ms", "4", "--jitter-ms", "1.5"], "TURN + 4 +- 1.5 ms, 0 % loss"),
        (["--loss", "2"], "TURN + 0 ms, 2 % loss"),
        (["--delay-ms", "4", "--loss", "1", "--load", "4"], "TURN + 4 ms, 1 % loss, load 4"),
        (["--load", "2", "--fifo"], "loopback, load 2, FIFO sender"),
    ],
)
def test_link_labels_name_the_link(flags, label):
    import argparse

    p = argparse.ArgumentParser()
    session.add_arguments(p)
    assert session.link_label(p.parse_args(flags)) == label


def _row(label: str, value: str) -> list[str]:
    return [label, value, *["x"] * (len(session.HEADER) - 2)]


def test_a_run_replaces_its_own_row_and_keeps_the_others(tmp_path):
    from humantele.report import markdown_table, section_rows, write_section

    path = tmp_path / "benchmarks.md"
    old = [_row("loopback", "1"), _row("TURN (coturn)", "2")]
    write_section("session", "## s\n\n" + markdown_table(session.HEADER, old), path)
    write_section("other", "## o\n\n" + markdown_table(session.HEADER, [_row("alien", "9")]), path)
    rows = section_rows(session.SECTION, len(session.HEADER), path)
    assert rows == old  # only this section's rows, header and rule skipped
    merged = session.merge_rows(rows, _row("TURN (coturn)", "3"))
    assert [r[:2] for r in merged] == [["loopback", "1"], ["TURN (coturn)", "3"]]
    merged = session.merge_rows(merged, _row("TURN + 4 ms, 0 % loss", "4"))
    assert [r[0] for r in merged] == ["loopback", "TURN (coturn)", "TURN + 4 ms, 0 % loss"]
    assert section_rows(session.SECTION, len(session.HEADER), tmp_path / "missing.md") == []


def test_rows_of_an_older_table_layout_are_not_kept(tmp_path):
    from humantele.report import markdown_table, section_rows, write_section

    path = tmp_path / "benchmarks.md"
    write_section("session", markdown_table(["link", "a"], [["loopback", "1"]]), path)
    assert section_rows(session.SECTION, len(session.HEADER), path) == []

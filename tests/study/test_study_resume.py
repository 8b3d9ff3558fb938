"""A study is resumable: recorded runs are skipped, unfinished ones moved aside and run again,
a run recorded with other settings refused; a failed run is reported and the rest go on."""

import asyncio
import io
import json

import pytest

from humantele.config import ConfigError
from humantele.study import cli
from humantele.study.conditions import load_conditions

TEXT = """
[study]
scans = 1
scan_s = 5.0
seeds = [1, 2]

[[condition]]
name = "a"
delay_ms = 10.0

[[condition]]
name = "b"
delay_ms = 200.0
"""


def _study(tmp_path, text=TEXT):
    (tmp_path / "c.toml").write_text(text)
    return load_conditions(tmp_path / "c.toml")


class FakeChildren:
    """Stands in for the session child: records what ran, writes its summary (or fails)."""

    def __init__(self, fail: set[str] = frozenset()) -> None:
        self.ran: list[str] = []
        self.fail = fail

    async def __call__(self, run, study, out):
        self.ran.append(run.run_id)
        d = out / run.run_id
        d.mkdir(parents=True)
        await asyncio.sleep(0)
        if run.run_id in self.fail:
            return False, "demo exit code 1", None
        summary = {"spec": run.spec(study.study),
                   "demo": {"servo_rate_hz": 1000.0, "servo_overruns": 0}}  # fmt: skip
        (d / "summary.json").write_text(json.dumps(summary))
        return True, "", summary


def _run(study, out, todo, jobs=1, children=None, monkeypatch=None):
    monkeypatch.setattr(cli, "_run_child", children)
    progress = cli.Progress(len(study.runs()), len(study.runs()) - len(todo), jobs, io.StringIO())
    asyncio.run(cli.run_all(study, out, todo, jobs, progress))
    return progress


def test_a_second_call_skips_what_is_recorded_and_runs_the_rest(tmp_path, monkeypatch):
    study, out = _study(tmp_path), tmp_path / "out"
    done, todo = cli.plan(study, out)
    assert done == [] and [r.run_id for r in todo] == ["a-s1", "a-s2", "b-s1", "b-s2"]
    children = FakeChildren(fail={"b-s1"})
    p = _run(study, out, todo, 2, children, monkeypatch)
    assert sorted(children.ran) == ["a-s1", "a-s2", "b-s1", "b-s2"]
    assert (p.done, p.failed) == (3, 1)
    assert "b-s1: FAILED: demo exit code 1" in p.stream.getvalue()
    # again: only the failed run (its directory, unfinished, is moved aside)
    done, todo = cli.plan(study, out)
    assert [r.run_id for r in done] == ["a-s1", "a-s2", "b-s2"]
    assert [r.run_id for r in todo] == ["b-s1"]
    assert [x.name.split(".incomplete-")[0] for x in out.glob("b-s1.incomplete-*")] == ["b-s1"]
    children = FakeChildren()
    p = _run(study, out, todo, 1, children, monkeypatch)
    assert children.ran == ["b-s1"] and (p.done, p.failed, p.skipped) == (1, 0, 3)
    done, todo = cli.plan(study, out)
    assert len(done) == 4 and todo == []


def test_a_run_recorded_with_other_settings_is_refused(tmp_path, monkeypatch):
    study, out = _study(tmp_path), tmp_path / "out"
    _, todo = cli.plan(study, out)
    _run(study, out, todo, 1, FakeChildren(), monkeypatch)
    changed = _study(tmp_path, TEXT.replace("delay_ms = 200.0", "delay_ms = 250.0"))
    with pytest.raises(ConfigError, match="b-s1.*other settings"):
        cli.plan(changed, out)
    # a new seed is simply more runs
    more = _study(tmp_path, TEXT.replace("seeds = [1, 2]", "seeds = [1, 2, 3]"))
    done, todo = cli.plan(more, out)
    assert len(done) == 4 and [r.run_id for r in todo] == ["a-s3", "b-s3"]


def test_the_progress_line_counts_and_estimates():
    p = cli.Progress(4, 1, 1, io.StringIO())
    p.done, p.walls = 1, [60.0]
    p.running = {"b-s1": p.t0}
    line = p.line(now=p.t0 + 20.0)
    assert "2/4 runs (1 recorded before, 0 failed)" in line
    assert "running: b-s1 20 s" in line
    assert "ETA 1:40" in line  # 40 s left of the running one, then one more of 60 s

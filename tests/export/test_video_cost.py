"""`python -m humantele.export.video_cost`: replays recorded frames through the recorder
and reports CPU and MB per minute (the figure is not asserted: a busy machine; its parts are)."""

from __future__ import annotations

import json

import pytest
from video_fixtures import write_video

from humantele.export.video_cost import main


def test_it_reports_the_cost_of_the_recorded_frames(tmp_path, capsys):
    path = tmp_path / "v.expert.mcap"
    frames = write_video(path, "vc01", 10.0, 20, streams=("us", "pov"))
    assert main([str(path), "--seconds", "0.5"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["frames"] == 2 * 11  # both streams, 0 to 0.5 s at 20 fps
    sizes = sum(len(d) for d, _ in frames[:11]) * 2
    assert r["encoded_mb_per_min"] == pytest.approx(sizes / 1e6 * 60 / 0.5, rel=0.01)
    assert r["video_mb_per_min"] > 0 and "cpu_percent_core" in r and "loadavg" in r


def test_a_recording_without_video_is_one_line(tmp_path):
    from humantele.recording.synthetic import SyntheticSession, write_synthetic

    path = tmp_path / "old.mcap"
    write_synthetic(path, SyntheticSession(duration_s=4.0, expert_rate_hz=50.0))
    with pytest.raises(SystemExit, match="no encoded video recorded"):
        main([str(path)])

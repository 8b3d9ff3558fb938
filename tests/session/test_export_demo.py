"""The whole path on the demo with its video tracks: the expert records every US and POV frame
as received, `humantele export` makes the MP4s and the Foxglove file, and an exported frame
is the frame the expert decoded (aiortc's own decoder on the same bytes), up to H.264's loss."""

from __future__ import annotations

import os
import subprocess
import sys

import av
import pytest
from aiortc.codecs.vpx import Vp8Decoder
from aiortc.jitterbuffer import JitterFrame

from humantele.export.source import load
from humantele.export.video import first_decodable
from humantele.recording import read_recording
from humantele.video.fidelity import psnr


@pytest.mark.slow
def test_demo_video_recorded_at_full_rate_exports_the_frames_the_expert_decoded(demo_run, tmp_path):
    """The shared demo run (session_helpers.demo_run: configs/demo.toml, recorded)."""
    assert demo_run.returncode == 0, demo_run.err[-3000:]
    env = {k: v for k, v in os.environ.items() if k != "HUMANTELE_TOKEN"}
    files = list(demo_run.recordings)
    sessions, problems = load(files)
    assert problems == []
    (es,) = sessions
    (expert_file,) = [f for f in files if ".expert." in f.name]
    rec = read_recording(expert_file)
    for name in ("us", "pov"):  # every frame the expert's jitter buffer released, recorded
        stream = es.video[name]
        # (how many depends on the machine's load: the follower lowers the rate when busy)
        assert stream.codec == "vp8" and len(stream.frames) > 10
        assert stream.frames[0].keyframe
        # Capture times are recorded from the stream's first frame timing and clock sync on
        # (how many frames come before them depends on the machine's load): the export
        # estimates exactly those first ones, and every later frame has its own.
        timed = ["t_capture" in s for s in rec.samples(f"/expert/{name}_video")]
        first = timed.index(True)
        assert all(timed[first:]) and stream.estimated == first < len(timed) // 2
    out = tmp_path / "export"
    exp = subprocess.run(
        [sys.executable, "-m", "humantele", "export", *map(str, files), "--out", str(out)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert exp.returncode == 0, exp.stderr[-3000:]
    assert "Traceback" not in exp.stderr
    (iv,) = es.scans
    base = f"{es.session_id}_scan{iv.scan}"
    assert (out / f"{base}.mcap").stat().st_size > 10_000
    frames = es.video["us"].frames
    dec, expert = Vp8Decoder(), []
    for f in frames[first_decodable(frames, iv.start) :]:
        if f.t > iv.stop:
            break
        pics = dec.decode(JitterFrame(f.data, 0))
        if f.t >= iv.start:
            expert += [p.to_ndarray(format="bgr24") for p in pics]
    with av.open(str(out / f"{base}_us.mp4")) as c:
        exported = [p.to_ndarray(format="bgr24") for p in c.decode(video=0)]
    # every frame of the scan, however many a loaded machine captured (3: first, middle, last)
    assert len(exported) == len(expert) >= 3
    for k in (0, len(expert) // 2, len(expert) - 1):
        assert psnr(expert[k], exported[k]) > 35.0

"""`humantele demo --replay FILE`: a clinic recorded once with `humantele devices record` (here
from the replayed clinic of replayed_clinic.py: the technician's four landmark presses, then
resting on the abdomen) runs the demo with the follower on the real backends reading the file,
looped (each round ~10 s; a press missed while the sensing starts comes round again): it
calibrates from the recorded presses, follows the expert's poses, loads no
simulator; a file that is not a device recording is one clear line."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from replayed_clinic import calibration_presses, follower_config, make_recording, replay_env
from session_helpers import read_json

from humantele.devices import record as record_cmd
from humantele.follower.sim_world import SimWorld
from humantele.tracking.hl2ss_replay import Hl2ssReplayServer

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.whole_session]


def record_clinic(tmp_path, monkeypatch):
    """The recorded clinic as `humantele devices record` writes it (the board's calibration
    kept in it)."""
    world = SimWorld()
    targets, end = calibration_presses(world, hover_s=1.0)
    rec = make_recording(tmp_path, end + 2.0, targets, world, save_ahat=False)
    records, cal = rec.records, rec.calibration
    for name, value in replay_env(rec.dir).items():
        monkeypatch.setenv(name, value)
    monkeypatch.syspath_prepend(replay_env(rec.dir)["PYTHONPATH"].split(":")[0])
    monkeypatch.delitem(sys.modules, "hid", raising=False)
    with Hl2ssReplayServer([records], cal, rate_hz=45.0) as server:
        cfg = tmp_path / "follower.toml"
        cfg.write_text(follower_config(rec.dir, server.port, tmp_path / "unused"))
        counts, _notes = record_cmd.record(
            cfg, tmp_path / "clinic.mcap", duration=120,
            until=lambda c: c.get("ahat", 0) >= len(records) - 2 and c.get("pov", 0) > 20,
        )  # fmt: skip
    assert counts["ahat"] >= len(records) - 2 and counts["force"] > 100
    return tmp_path / "clinic.mcap"


def test_demo_replays_a_recorded_clinic_through_the_real_backends(tmp_path, monkeypatch):
    mcap = record_clinic(tmp_path, monkeypatch)
    # Ctrl-C once the follower is calibrated and following (--duration only bounds it).
    demo = subprocess.Popen(
        [sys.executable, "-m", "humantele", "demo", "--replay", str(mcap), "--duration", "240",
         "--json", "--keep"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
        env=dict(os.environ, TMPDIR=str(tmp_path)),
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 240
        while demo.poll() is None and time.monotonic() < deadline:
            stats = [read_json(p) for p in tmp_path.glob("humantele-demo-*/follower.json")]
            if any(f.get("calibrated") and f.get("poses_received", 0) > 100 for f in stats):
                break
            time.sleep(0.5)
        demo.send_signal(signal.SIGINT)
        out, err = demo.communicate(timeout=60)
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.communicate()
    assert demo.returncode == 0, err[-3000:]
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["calibrated"] is True, err[-3000:]
    assert summary["poses_received"] > 100
    assert summary["exit_codes"] == {"expert": 0, "follower": 0}
    # a session recording, or any other file, is not a device recording: one line, exit 2
    bad = tmp_path / "notes.mcap"
    bad.write_bytes(b"not an mcap")
    run = subprocess.run([sys.executable, "-m", "humantele", "demo", "--replay", str(bad)],
                         capture_output=True, text=True, timeout=60)  # fmt: skip
    assert run.returncode == 2 and "--replay" in run.stderr and "Traceback" not in run.stderr

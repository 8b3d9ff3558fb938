"""A recording survives SIGKILL of its daemon, and any truncation of the file."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from humantele.recording import Recorder, read_recording

CHILD = textwrap.dedent(
    """
    import sys, time
    from humantele.recording import Recorder
    rec = Recorder(sys.argv[1], "expert")
    i = 0
    next_t = time.monotonic()
    while True:
        rec.write("/expert/pose", time.time(), {"position": [i, 0, 0], "quaternion": [0, 0, 0, 1]})
        if i % 22 == 0:
            rec.write("/follower/latency", time.time(), {"name": "n", "value_s": float(i)})
        if i == 200:
            print("ready", flush=True)
        i += 1
        next_t += 0.001
        time.sleep(max(0.0, next_t - time.monotonic()))
    """
)


@pytest.mark.e2e  # runs a recording Python process (the fast lane leaves it out)
def test_sigkill_loses_at_most_the_last_half_second(tmp_path):
    path = tmp_path / "killed.mcap"
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout.readline().strip() == "ready"
        time.sleep(1.2)
        t_kill = time.time()
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(10)
    rec = read_recording(path)
    assert not rec.complete and rec.problem
    t = rec.times("/expert/pose")
    seq = np.array([p[0] for p in rec.column("/expert/pose", "position")])
    assert len(t) > 200
    np.testing.assert_array_equal(seq, np.arange(len(seq)))  # nothing lost in between
    assert t[-1] >= t_kill - 0.5, f"lost {t_kill - t[-1]:.3f} s before the kill"


def test_any_truncation_reads_back_a_prefix(tmp_path):
    path = tmp_path / "full.mcap"
    with Recorder(path, "expert") as rec:
        for i in range(3000):
            rec.write("/expert/pose", i * 1e-3, {"position": [i, 0, 0], "quaternion": [0, 0, 0, 1]})
            if i % 500 == 0:
                time.sleep(0.25)  # several chunks
    data = path.read_bytes()
    previous = -1
    for cut in np.linspace(0, len(data), 40).astype(int)[1:]:
        part = tmp_path / f"cut{cut}.mcap"
        part.write_bytes(data[:cut])
        try:
            rec = read_recording(part)
        except OSError:
            assert cut < 64  # only a cut inside the header is unreadable
            continue
        seq = [s["position"][0] for s in rec.samples("/expert/pose")]
        assert seq == list(range(len(seq)))
        assert len(seq) >= previous
        previous = len(seq)
    assert previous == 3000

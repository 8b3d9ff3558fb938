"""``--cpu-durations=N`` (tests/cpu_durations.py): the tests that used the most CPU, listed by
the CPU they used, not by the time they took."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
BURN_S = 0.3

EXAMPLE = f"""
import subprocess, sys, time

def test_burns():
    t = time.process_time()
    while time.process_time() - t < {BURN_S}:
        pass

def test_sleeps():
    time.sleep({BURN_S})

def test_a_child_burns():  # a child it waits for: reaped, so counted
    subprocess.run([sys.executable, "-c", "import time\\nt = time.process_time()\\n"
                    "while time.process_time() - t < {BURN_S}: pass"], check=True)
"""


@pytest.mark.e2e  # runs pytest in a process (the fast lane leaves it out)
def test_tests_are_listed_by_the_cpu_they_used_with_their_reaped_children(tmp_path):
    (tmp_path / "test_example.py").write_text(EXAMPLE)
    env = dict(
        os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])
    )
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "cpu_durations", "--cpu-durations=3",
         "-p", "no:cacheprovider", "test_example.py"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr
    rows = re.findall(r"^\s*([\d.]+) CPU-s  test_example\.py::(\w+)$", run.stdout, re.M)
    cpu = {name: float(s) for s, name in rows}
    assert set(cpu) == {"test_burns", "test_sleeps", "test_a_child_burns"}, run.stdout
    assert cpu["test_burns"] >= BURN_S and cpu["test_a_child_burns"] >= BURN_S
    assert cpu["test_sleeps"] < BURN_S / 2
    assert [name for _, name in rows][-1] == "test_sleeps"  # the most first
    assert "CPU-s in all 3 tests" in run.stdout

"""tools/suite_cpu.py: the CPU of a command's whole process tree, by kind (issue 33)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "suite_cpu.py"
sys.path.insert(0, str(TOOL.parent))

import suite_cpu  # noqa: E402

# A parent that burns ~0.6 s of CPU in a child it waits for, and leaves an orphan that burns
# ~0.6 s more after the parent exits (the subreaper gets it back and counts it).
BURN = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.6: pass\n"
TREE = f"""
import subprocess, sys
subprocess.run([sys.executable, "-c", {BURN!r}])
subprocess.Popen([sys.executable, "-c", "import time; time.sleep(0.3)\\n" + {BURN!r}],
                 start_new_session=True)
"""


def test_kinds_from_names_and_command_lines():
    k = suite_cpu.kind_of
    assert k("humantele-sensi", ["humantele-sensing"]) == "sensing"
    assert k("humantele-servo", []) == "servo"
    assert k("humantele-video", []) == "video" and k("humantele-csim", []) == "video"
    chrome = "/usr/lib/chromium/chromium"
    assert k("chromium", [chrome, "--type=gpu-process"]) == "chromium gpu"
    assert k("chromium", [chrome, "--type=renderer"]) == "chromium renderer"
    assert k("chromium", [chrome, "--type=utility"]) == "chromium other"
    py = "/usr/bin/python3"
    assert k("python3", [py, "-m", "humantele", "follower", "--room", "x"]) == "follower"
    assert k("python3", [py, "-m", "humantele", "expert"]) == "expert"
    assert k("python3", [py, "-m", "humantele", "demo"]) == "other"
    assert k("python3", [py, "-m", "pytest", "-q"]) == "pytest"
    worker = [py, "-u", "-c", "import sys;exec(eval(sys.stdin.readline()))"]  # an xdist worker
    assert k("python3", worker) == "pytest"
    assert k("turnserver", ["turnserver", "-n"]) == "other"


def test_a_slice_of_the_reference_reads_as_the_whole():
    ref = suite_cpu.Reference()
    whole_from_one, whole_from_four = ref.cpu_s(1), ref.cpu_s(4)
    assert 0.5 < whole_from_one / whole_from_four < 2.0  # (not 1/20: read as the whole)
    line = suite_cpu.host_speed_line(0.6, 0.7, [0.65, 0.9, 0.62])
    assert "0.60 CPU-s before" in line and "0.70 after" in line
    assert "during it 0.65 (median of 3, slowest 0.90)" in line


@pytest.mark.e2e  # runs tools/suite_cpu.py and its process tree (the fast lane leaves it out)
def test_a_tree_s_cpu_is_counted_with_its_orphans(tmp_path):
    out = tmp_path / "cpu.json"
    r = subprocess.run(
        [sys.executable, str(TOOL), "--interval", "0.05", "--json", str(out), "--reference",
         "1", "--probe-every", "0.2", "--", sys.executable, "-c", TREE],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    data = json.loads(out.read_text())
    # two burners of 0.6 s each (CPU time, whatever the machine's load) and the interpreters
    assert 1.2 <= data["cpu_s"] < 10.0, data
    assert data["still_running"] == 0 and data["samples"] >= 1
    assert "total" in r.stderr and "CPU-s" in r.stderr
    # the host's speed, timed before, during (a slice every 0.2 s, each read as the whole)
    # and after in the tool's own process: not in the command's CPU-s (counted, the timings
    # would add twice ``before`` and more to the burners')
    ref = data["reference_cpu_s"]
    assert ref["before"] > 0.05 and ref["after"] > 0.05 and data["cpu_s"] < 1.2 + ref["before"]
    assert len(ref["during"]) >= 2 and min(ref["during"]) > 0.05
    assert "host speed: the reference workload took" in r.stderr and "during it" in r.stderr
    fail = subprocess.run(
        [sys.executable, str(TOOL), "--reference", "0", "--", sys.executable, "-c",
         "raise SystemExit(3)"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert fail.returncode == 3  # the command's exit code is the tool's

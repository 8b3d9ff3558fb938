"""A scenario's demo started in a process group of its own (``stage.DemoRun``, ``own_group``)
is noted in the scenario's output, and ends with the runner's group when the scenario is
killed on its deadline (netns.run_scenario), not at its own ``--duration``."""

import os
import subprocess
import sys

from netns import GROUPS_FILE, kill_groups, own_groups


def test_a_noted_own_group_is_killed_with_the_runner(tmp_path):
    child = subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(120)"], start_new_session=True
    )
    (tmp_path / GROUPS_FILE).write_text(f"{child.pid}\n")
    assert own_groups(tmp_path) == [child.pid] == [os.getpgid(child.pid)]
    kill_groups([*own_groups(tmp_path), 2**22 + 7])  # a group long gone is fine
    assert child.wait(timeout=30) == -9


def test_no_file_no_groups(tmp_path):
    assert own_groups(tmp_path) == []

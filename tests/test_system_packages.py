"""One list of the Debian packages the tests use (.ci/run's APT_PACKAGES, installed by
tools/install_system_packages.sh, which CI runs and the README names), every package a skip
reason names on it, and the run's last line counting such skips (tests/conftest.py)."""

import re
import subprocess
from pathlib import Path
from types import SimpleNamespace

from system_packages import (
    INSTALL_SYSTEM_PACKAGES,
    skipped_for_system_packages,
    system_packages_line,
)

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "tools" / "install_system_packages.sh"


def listed() -> list[str]:
    res = subprocess.run([str(SCRIPT), "--list"], capture_output=True, text=True, check=True)
    return res.stdout.split()


def test_the_script_lists_ci_s_packages_and_ci_and_the_readme_use_it():
    packages = listed()
    assert {"chromium", "coturn", "libopenigtlink-dev", "g++"} <= set(packages)
    ci = (REPO / ".ci" / "run").read_text()
    assert re.search(r"^tools/install_system_packages\.sh$", ci, re.M)
    assert INSTALL_SYSTEM_PACKAGES in (REPO / "README.md").read_text()


def test_every_package_a_skip_reason_names_is_installed_by_the_script():
    packages = set(listed())
    named: dict[str, set[str]] = {}
    for path in REPO.joinpath("tests").rglob("*.py"):
        if "vendor" in path.parts or path.name in ("system_packages.py", Path(__file__).name):
            continue
        for m in re.finditer(r"\(system packages? ([^()\"]+)\)", path.read_text()):
            for pkg in m.group(1).split():
                named.setdefault(pkg, set()).add(path.name)
    assert {"chromium", "coturn", "libopenigtlink-dev"} <= set(named)
    assert not {p: f for p, f in named.items() if p not in packages}


def _skip(reason: str):
    return SimpleNamespace(longrepr=("f.py", 1, f"Skipped: {reason}"))


def test_the_last_line_counts_skips_by_package():
    reports = [
        _skip("no turnserver (system package coturn)"),
        _skip("no turnserver (system package coturn)"),
        _skip("no Chromium (system packages chromium fonts-liberation)"),
        _skip("no privilege for SCHED_FIFO here"),
    ]
    counts = skipped_for_system_packages(reports)
    assert counts[None] == 3 and counts["coturn"] == 2 and counts["fonts-liberation"] == 1
    line = system_packages_line(reports)
    assert line.startswith("3 tests skipped for want of system packages: chromium (1), coturn (2)")
    assert line.endswith(INSTALL_SYSTEM_PACKAGES)
    assert system_packages_line([_skip("no privilege for SCHED_FIFO here")]) is None

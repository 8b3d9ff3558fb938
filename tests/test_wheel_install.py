"""The package installs from a wheel and runs outside the source checkout.

Builds a wheel of this checkout (from a copy, so the checkout gets no build/ or egg-info),
installs it without dependencies into a fresh venv that sees the system's site-packages (the
dependencies are installed there already), and runs ``humantele demo --json`` until poses flow
from a directory far from the checkout, without PYTHONPATH: the named definitions (the
probe's tool, ...) must come from the installed package's data, not from the repository.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import venv
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "src" / "humantele"

pytestmark = pytest.mark.slow


def _clean_env(home: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV"))}
    env["HOME"] = str(home)  # the follower's state (calibration, certificate) goes here
    return env


def _run(cmd: list[str], cwd: Path, env: dict[str, str], timeout: float):
    res = subprocess.run(
        cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False
    )
    assert res.returncode == 0, f"{' '.join(cmd)}\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    return res


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "humantele-src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    shutil.copytree(
        REPO / "src", src / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info")
    )
    out = tmp / "dist"
    env = _clean_env(tmp)
    _run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(out), str(src)],
        tmp,
        env,
        timeout=300,
    )
    (whl,) = out.glob("humantele-*.whl")
    return whl


def test_wheel_holds_every_data_file_of_the_package_and_nothing_from_configs(wheel: Path):
    names = set(zipfile.ZipFile(wheel).namelist())
    data = {
        p.relative_to(PACKAGE.parent).as_posix()
        for p in PACKAGE.rglob("*")
        if p.is_file() and p.suffix not in (".py", ".pyc") and "__pycache__" not in p.parts
    }
    assert "humantele/defaults/tools/probe_default.toml" in data
    assert "humantele/follower/web/index.html" in data
    missing = sorted(data - names)
    assert not missing, f"package data not in the wheel (add to pyproject's globs): {missing}"
    assert not [n for n in names if n.startswith("configs/")]


def test_installed_wheel_runs_the_demo_outside_the_checkout(wheel: Path, tmp_path: Path):
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(system_site_packages=True, with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    env = _clean_env(tmp_path)
    _run(
        [sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps",
         str(wheel)],
        tmp_path,
        env,
        timeout=300,
    )  # fmt: skip
    work = tmp_path / "elsewhere"
    work.mkdir()
    where = _run(
        [str(py), "-c", "import humantele.tracking.tool as t; print(t.__file__); "
         "print(t.load_tool('probe_default').markers.shape)"],
        work,
        env,
        timeout=60,
    ).stdout.split()  # fmt: skip
    assert Path(where[0]).is_relative_to(env_dir), where  # the wheel's copy, not the checkout
    assert where[1:] == ["(4,", "3)"]
    # The installed demo, stopped (SIGTERM) once the status line shows poses flowing.
    demo = subprocess.Popen(
        [str(env_dir / "bin" / "humantele"), "demo", "--duration", "120", "--json"],
        cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    watchdog = threading.Timer(180.0, demo.kill)  # never hang the suite
    watchdog.start()
    try:
        for line in demo.stderr:  # every 2 s; ends early if the demo does
            if "link connected" in line and "poses 0 Hz" not in line:
                break
        demo.send_signal(signal.SIGTERM)
        out, err = demo.communicate(timeout=60)
    finally:
        watchdog.cancel()
        if demo.poll() is None:
            demo.kill()
            demo.wait()
    assert demo.returncode == 0, f"{out[-3000:]}\n{err[-3000:]}"
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["exit_codes"] == {"expert": 0, "follower": 0}
    assert summary["poses_sent"] > 0 and summary["poses_received"] > 0
    assert not (work / "configs").exists()

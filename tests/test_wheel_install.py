"""The package installs from a wheel and runs outside the source checkout.

Builds a wheel and a source distribution of this checkout (from a copy, so the checkout gets no
build/ or egg-info), checks that neither holds the vendored hl2ss client (its licence is not
the project's: NOTICE),
installs it without dependencies into a fresh venv that sees the site-packages of the
environment the tests run in (the dependencies are installed there already, be it a venv, the
system's or the user's), and runs ``humantele demo --json`` until poses flow
from a directory far from the checkout, without PYTHONPATH: the named definitions (the
probe's tool, ...) must come from the installed package's data, not from the repository.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tarfile
import threading
import time
import venv
import zipfile
from pathlib import Path

import pytest

from humantele.demo_status import poses_flowing

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


def running_site_packages() -> list[str]:
    """The site-packages folders of the interpreter running the tests, wherever they are (its
    venv's, the system's, the user's), in its order; not the checkout (an editable install
    reaches it through a .pth file in one of them, which a plain path line does not run)."""
    return [p for p in sys.path if Path(p).name in ("site-packages", "dist-packages")]


def _see_running_site_packages(py: Path) -> None:
    """Make the venv of ``py`` see the running environment's packages: a .pth file in its own
    site-packages (after it, so the wheel installed there comes first)."""
    purelib = subprocess.run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True, text=True, check=True, env=_clean_env(py.parent),
    ).stdout.strip()  # fmt: skip
    (Path(purelib) / "humantele-test-deps.pth").write_text("\n".join(running_site_packages()))


@pytest.fixture(scope="module")
def checkout_copy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the checkout (tests and the vendored hl2ss client included), without git's
    and the tools' caches, to build from."""
    src = tmp_path_factory.mktemp("checkout") / "humantele-src"
    ignore = ("__pycache__", "*.egg-info", ".git", ".pytest_cache", ".ruff_cache", "build",
              "dist", ".venv", "runs")  # fmt: skip
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(*ignore))
    assert (src / "tests" / "devices" / "vendor" / "hl2ss" / "hl2ss.py").exists()
    return src


@pytest.fixture(scope="module")
def wheel(checkout_copy: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("wheel")
    out = tmp / "dist"
    env = _clean_env(tmp)
    _run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(out),
         str(checkout_copy)],
        tmp,
        env,
        timeout=300,
    )  # fmt: skip
    (whl,) = out.glob("humantele-*.whl")
    return whl


# hl2ss's client (BSD-3-Clause with the Commons Clause, tests only: NOTICE) by its files' names
HL2SS_FILES = ("hl2ss.py", "hl2ss_lnm.py", "hl2ss_3dcv.py", "hl2ss_dp.py")


def _foreign(names: list[str]) -> list[str]:
    """The archive's names that are hl2ss's files: under a vendor/hl2ss folder, or named as
    one of them and not a module of our own (``bench/hl2ss.py`` is ours)."""
    own = {p.relative_to(PACKAGE.parent).as_posix() for p in PACKAGE.rglob("*.py")}
    return [
        n for n in names
        if "vendor/hl2ss" in n or (Path(n).name in HL2SS_FILES and n.split("/", 1)[-1] not in own
                                   and n not in own)
    ]  # fmt: skip


def test_the_source_distribution_holds_the_package_and_not_the_vendored_hl2ss_client(
    checkout_copy: Path, tmp_path: Path
):
    out = tmp_path / "sdist"
    _run(
        [sys.executable, "-c", "import sys; from setuptools import build_meta as b; "
         "print(b.build_sdist(sys.argv[1]))", str(out)],
        checkout_copy,
        _clean_env(tmp_path),
        timeout=300,
    )  # fmt: skip
    (sdist,) = out.glob("humantele-*.tar.gz")
    with tarfile.open(sdist) as tar:
        names = tar.getnames()
    assert any(n.endswith("src/humantele/follower/web/index.html") for n in names)
    assert not _foreign(names), _foreign(names)


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
    assert not _foreign(sorted(names)), _foreign(sorted(names))  # built from the whole checkout


@pytest.mark.e2e
@pytest.mark.whole_session  # one at a time across the lanes (tests/session_slot.py)
def test_installed_wheel_runs_the_demo_outside_the_checkout(wheel: Path, tmp_path: Path):
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    _see_running_site_packages(py)
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
    # The installed demo, stopped (SIGTERM) once the status line shows poses flowing. Its
    # output is read by threads into lists (all of it is kept for the failure message), its
    # run directory (the daemons' logs, kept when it fails) is made under tmp_path, and its
    # process group is killed whatever happens.
    env["TMPDIR"] = str(tmp_path / "tmp")
    (tmp_path / "tmp").mkdir()
    demo = subprocess.Popen(
        [str(env_dir / "bin" / "humantele"), "demo", "--duration", "120", "--json"],
        cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,
    )  # fmt: skip
    out: list[str] = []
    err: list[str] = []
    readers = [
        threading.Thread(target=lambda: out.extend(demo.stdout), daemon=True),
        threading.Thread(target=lambda: err.extend(demo.stderr), daemon=True),
    ]
    for r in readers:
        r.start()

    def report() -> str:
        logs = "".join(
            f"\n--- {log} (last 40 lines)\n" + "".join(log.read_text().splitlines(True)[-40:])
            for log in sorted((tmp_path / "tmp").glob("humantele-demo-*/*.log"))
        )
        return (
            f"exit code {demo.returncode}\n--- stdout\n{''.join(out)[-3000:]}\n--- stderr\n"
            f"{''.join(err)[-6000:]}{logs}"
        )

    def flowing() -> bool:
        return any(poses_flowing(ln) for ln in list(err))

    try:
        # Bounded by the demo's progress: it prints a status line every 2 s and gives up on
        # a daemon that does not start within 120 s (exit 1, said on stderr).
        t_end = time.monotonic() + 300.0
        while not flowing() and demo.poll() is None and time.monotonic() < t_end:
            time.sleep(0.2)
        assert flowing(), f"poses never flowed\n{report()}"
        demo.send_signal(signal.SIGTERM)
        demo.wait(120)  # the demo's daemons get 20 s each to stop
        for r in readers:
            r.join(10)
    finally:
        if demo.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(demo.pid, signal.SIGKILL)
            demo.wait()
        with contextlib.suppress(ProcessLookupError):  # what it left behind, if anything
            os.killpg(demo.pid, signal.SIGKILL)
    assert demo.returncode == 0, report()
    summary = json.loads("".join(out).strip().splitlines()[-1])
    assert summary["exit_codes"] == {"expert": 0, "follower": 0}, report()
    assert summary["poses_sent"] > 0 and summary["poses_received"] > 0
    assert not (work / "configs").exists()

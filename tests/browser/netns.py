"""Run a browser scenario in a fresh network namespace; the host side of the browser tests.

A *scenario* is a module in ``tests/browser/scenarios/`` with ``async def run(ctx) -> dict``.
:func:`run_scenario` starts ``runner.py`` under ``unshare -n`` (only loopback inside, so
Chromium cannot reach outside hosts), where the scenario gets a :class:`stage.Ctx`: headless
Chromium driven by playwright, and whatever it starts inside the namespace (the daemons, the
demo, a feed). The scenario's dict comes back as JSON, with its screenshots and logs in
``out_dir``; an exception in the scenario fails the test with its traceback and the logs.

From a shell (e.g. the feed latency on a quiet machine)::

    python tests/browser/netns.py headset_latency --arg seconds=30
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
SCENARIOS = HERE / "scenarios"  # scenarios/<name>.py, each with ``async def run(ctx) -> dict``
CHROMIUM_PATHS = ("/usr/lib/chromium/chromium", "/usr/bin/chromium")


def chromium_path() -> str | None:
    """Debian's Chromium (``apt-get install chromium``), or None."""
    for p in CHROMIUM_PATHS:
        if os.access(p, os.X_OK):
            return p
    return None


def unshare_command() -> list[str] | None:
    """``unshare -n`` as root, ``unshare -r -n`` (a user namespace) otherwise; None if this
    machine cannot make a network namespace."""
    exe = shutil.which("unshare")
    if exe is None or shutil.which("ip") is None:
        return None
    cmd = [exe, "-n"] if os.geteuid() == 0 else [exe, "-r", "-n"]
    try:
        ok = subprocess.run([*cmd, "true"], capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        ok = False
    return cmd if ok else None


def skip_reason() -> str | None:
    """Why the browser tests cannot run here, or None."""
    if chromium_path() is None:
        return "no Chromium (system packages chromium fonts-liberation)"
    try:
        import playwright  # noqa: F401
    except ImportError:
        return "no playwright (pip install -e '.[test]')"
    if unshare_command() is None:
        return "cannot make a network namespace: unshare -n and ip (system package iproute2)"
    return None


@dataclass
class ScenarioResult:
    """What a scenario returned, and where its files are."""

    data: dict
    out_dir: Path
    logs: dict[str, str] = field(default_factory=dict)

    def path(self, name: str) -> Path:
        return self.out_dir / name


class ScenarioError(AssertionError):
    pass


def _logs(out_dir: Path, tail: int = 4000) -> dict[str, str]:
    logs = {}
    for p in sorted(out_dir.rglob("*.log")):
        logs[str(p.relative_to(out_dir))] = p.read_text(errors="replace")[-tail:]
    return logs


GROUPS_FILE = "own_groups"  # in a scenario's output: the process groups of its own-group demos


def own_groups(out_dir: Path) -> list[int]:
    """The process groups a scenario's demos started on their own (``stage.DemoRun``, noted
    in :data:`GROUPS_FILE`)."""
    try:
        text = (out_dir / GROUPS_FILE).read_text()
    except OSError:
        return []
    return [int(x) for x in text.split() if x.isdigit()]


def kill_groups(pgids: list[int]) -> None:
    """SIGKILL each process group; one already gone is fine."""
    for pgid in pgids:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(pgid, signal.SIGKILL)


def run_scenario(
    name: str, out_dir: Path, args: dict | None = None, timeout_s: float = 240.0
) -> ScenarioResult:
    """Run ``scenarios/<name>.py`` in a fresh network namespace; its dict, or ScenarioError
    with the traceback and the logs of everything it started."""
    cmd = unshare_command()
    if cmd is None:
        raise RuntimeError(skip_reason() or "no network namespace")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "args.json").write_text(json.dumps(args or {}))
    runner = [sys.executable, str(HERE / "runner.py"), name, str(out_dir)]
    with open(out_dir / "runner.log", "wb") as log:
        proc = subprocess.Popen(
            [*cmd, *runner], stdout=log, stderr=subprocess.STDOUT, start_new_session=True
        )
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise ScenarioError(
                f"scenario {name} did not finish in {timeout_s} s\n" + _format(_logs(out_dir))
            ) from None
        finally:  # also on Ctrl-C: Chromium and the daemons go with the runner's group,
            # and a demo started in a group of its own (stage.DemoRun, own_group) with it
            kill_groups([proc.pid, *own_groups(out_dir)])
            proc.wait()
    try:
        result = json.loads((out_dir / "result.json").read_text())
    except (OSError, ValueError):
        result = {"error": f"no result (runner exit code {proc.returncode})"}
    logs = _logs(out_dir)
    if "error" in result:
        raise ScenarioError(f"scenario {name} failed:\n{result['error']}\n" + _format(logs))
    return ScenarioResult(result["data"], out_dir, logs)


def _format(logs: dict[str, str]) -> str:
    return "\n".join(f"--- {k} ---\n{v}" for k, v in logs.items())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenario", help="a module of tests/browser/scenarios")
    parser.add_argument("--out", help="directory for the result, screenshots and logs")
    parser.add_argument("--arg", action="append", default=[], help="KEY=VALUE (JSON or text)")
    parser.add_argument(
        "--timeout", type=float, default=1800.0, help="s (the A/B bench takes ~10 min)"
    )
    a = parser.parse_args()
    reason = skip_reason()
    if reason:
        print(f"cannot run: {reason}", file=sys.stderr)
        return 2
    args = {}
    for kv in a.arg:
        k, _, v = kv.partition("=")
        try:
            args[k] = json.loads(v)
        except ValueError:
            args[k] = v
    out = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix=f"humantele-{a.scenario}-"))
    result = run_scenario(a.scenario, out, args, a.timeout)
    print(json.dumps(result.data, indent=1))
    print(f"files in {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

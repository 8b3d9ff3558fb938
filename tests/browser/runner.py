"""Inside the network namespace: bring loopback up, run one scenario, write ``result.json``.

Usage (by :func:`netns.run_scenario`): ``runner.py SCENARIO OUT_DIR`` under ``unshare -n``.
"""

from __future__ import annotations

import asyncio
import importlib.util
import json
import subprocess
import sys
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from stage import Ctx  # noqa: E402


def bring_up_loopback() -> None:
    """``lo`` up, and a second loopback address: aioice gathers no candidate on 127.0.0.1
    alone."""
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    subprocess.run(["ip", "addr", "add", "127.0.0.2/8", "dev", "lo"], check=True)


def load(name: str):
    path = HERE / "scenarios" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"scenario_{name}", path)
    if spec is None or spec.loader is None:
        raise FileNotFoundError(f"no scenario {path}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


async def main(name: str, out_dir: Path) -> dict:
    args = json.loads((out_dir / "args.json").read_text())
    module = load(name)
    async with Ctx(out_dir, args) as ctx:
        data = await module.run(ctx)
        data.setdefault("console_errors", ctx.console_errors)
        ctx.mark("end")
        data.setdefault("marks", ctx.marks)
        return data


if __name__ == "__main__":
    scenario, out = sys.argv[1], Path(sys.argv[2])
    try:
        bring_up_loopback()
        result = {"data": asyncio.run(main(scenario, out))}
    except BaseException:  # everything goes back to the test, with the traceback
        result = {"error": traceback.format_exc()}
    (out / "result.json").write_text(json.dumps(result, indent=1, default=str))

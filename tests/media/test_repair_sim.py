"""tools/repair_sim.py, the repair path on a simulated clock (docs/video.md, "Fifth pass"):
deterministic for a seed, so its figures are the parts' and not the machine's."""

from __future__ import annotations

import argparse
import asyncio
import importlib.util
from pathlib import Path

TOOL = Path(__file__).resolve().parents[2] / "tools" / "repair_sim.py"


def _sim():
    spec = importlib.util.spec_from_file_location("repair_sim", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(loss: float, dup: bool, renack: bool, seconds: float = 30.0) -> dict:
    sim = _sim()
    args = argparse.Namespace(delay_ms=60.0, jitter_ms=20.0, loss=loss, packets=6,
                              playout_ms=250.0)  # fmt: skip
    return asyncio.run(sim.Sim(args, 1, dup, renack).run(seconds))


def test_without_loss_nothing_is_repaired_copied_or_frozen():
    r = _run(0.0, True, True, 10.0)
    assert r["given_up"] == r["repairs"] == r["dups"] == 0 and r["frozen"] == 0.0
    assert len(r["ages"]) >= 195  # 20 fps for 10 s, all shown


def test_copies_of_repairs_give_up_fewer_gaps_on_the_rural_link():
    base = _run(3.0, False, False, 40.0)
    both = _run(3.0, True, True, 40.0)
    assert base["repairs"] > 60 and base["dups"] == 0
    assert both["given_up"] < base["given_up"] and both["dups"] > 0.5 * both["repairs"]
    assert both["dup_bytes"] < 0.08 * both["bytes"]  # the copies: repairs only

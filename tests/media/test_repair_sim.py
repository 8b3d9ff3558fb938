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


def _run(
    loss: float,
    dup: bool,
    renack: bool,
    seconds: float = 30.0,
    fec: bool = False,
    delay_ms: float = 60.0,
    packets: int = 6,
    seed: int = 1,
) -> dict:
    sim = _sim()
    args = argparse.Namespace(delay_ms=delay_ms, jitter_ms=20.0 if delay_ms else 0.0, loss=loss,
                              packets=packets, playout_ms=250.0, fec_group=8)  # fmt: skip
    return asyncio.run(sim.Sim(args, seed, dup, renack, fec).run(seconds))


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


def test_parity_rebuilds_most_losses_with_no_round_trip_and_freezes_less():
    """The rural link (3 %) and 15 % loss on no delay, 4 packets a frame (the US at its floor):
    with a parity per frame most lost packets are rebuilt, few are repaired by a round trip,
    fewer gaps are given up and the picture freezes less; without loss a parity costs its
    bytes and nothing is rebuilt."""
    for loss, delay, seconds in ((3.0, 60.0, 60.0), (15.0, 0.0, 30.0)):
        base = _run(loss, False, False, seconds, delay_ms=delay, packets=4)
        fec = _run(loss, False, False, seconds, fec=True, delay_ms=delay, packets=4)
        assert base["recovered"] == 0 and base["parity_bytes"] == 0
        assert fec["recovered"] > fec["repairs"] and fec["repairs"] < 0.5 * base["repairs"]
        assert fec["nacks_spared"] > 0.3 * fec["recovered"]  # aiortc's NACK at the gap held
        assert fec["given_up"] < base["given_up"] and fec["frozen"] < base["frozen"]
        assert 0.2 < fec["parity_bytes"] / fec["bytes"] < 0.4  # a parity per 4 packets
    clean = _run(0.0, False, False, 10.0, fec=True)
    assert clean["recovered"] == clean["repairs"] == 0 and clean["frozen"] == 0.0
    assert clean["parity_bytes"] > 0.1 * clean["bytes"]

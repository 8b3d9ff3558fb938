"""One run of the study: a whole recorded session on one condition, in its own process.

``python -m humantele.study.session RUN_DIR`` reads ``RUN_DIR/run.json`` (the run's spec,
:meth:`humantele.study.conditions.Run.spec`) and composes the pieces the demo and
``bench video link`` already use:

- a coturn ``turnserver`` on loopback and the user-space WAN emulator
  (:class:`humantele.transport.netem.UdpRelay`) in front of it on the expert's side, so each
  direction crosses the emulator once: the condition's one-way delay, jitter (correlated over
  50 ms, FIFO), loss and bandwidth cap each way, seeded by the run's seed; both daemons are
  ``relay_only``;
- ``humantele demo`` (:func:`humantele.demo.run_demo`): the signaling server, the expert with
  its 1 kHz servo and the scripted sonographer, the follower with the simulated clinic, video
  on, recording to ``RUN_DIR/session.{expert,follower}.mcap``; the expert runs the study's
  scans (``[expert.scans]``: ``scans`` of ``scan_s``, ``gap_s`` apart, the first 2 s after the
  patient model arrives); the simulated devices and novice are seeded by the run's seed.

The run stops once the expert has stopped its last scan (read from its stats file: the demo's
run directory is made under ``RUN_DIR/tmp``), by the SIGTERM the demo handles (a clean stop:
both daemons say bye and close their recordings), or at ``setup_timeout_s`` + the scans'
length at the latest. It writes ``RUN_DIR/summary.json`` (the demo's summary, the emulator's
counters, wall time, the load average) when the session ran and both recordings exist, or
``RUN_DIR/failed.json`` with the reason. The TURN password is written only into a private
temporary directory, removed after the run.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

START_AFTER_MODEL_S = 2.0  # [expert.scans] start_after_model_s: scan 1 this long after the model
RECORD_BASE = "session.mcap"  # the demo's --record: session.expert.mcap, session.follower.mcap
POLL_S = 0.25
# The US picture's SSIM (humantele.study.quality) compares the expert's recorded encoded US
# frames with the follower's JPEG of the same captures: both must be recorded.
RECORD_US_HZ = 2.0


def _toml(v: object) -> str:
    return json.dumps(v)  # a JSON string or number is a TOML one


def _ice_lines(role: str, server: Any | None) -> str:
    if server is None:
        return ""
    cred = server.credential.get_secret_value() if server.credential else ""
    return (
        f"relay_only = true\n[[{role}.link.ice_servers]]\nurls = [{_toml(server.urls[0])}]\n"
        f"username = {_toml(server.username or '')}\ncredential = {_toml(cred)}\n"
    )


def write_configs(d: Path, spec: dict, ice: dict[str, Any] | None) -> Path:
    """expert.toml, follower.toml and demo.toml of one run in ``d`` (made 0700: the TURN
    credential is in them); returns the demo's file."""
    d.mkdir(parents=True, exist_ok=True)
    os.chmod(d, 0o700)
    ice = ice or {}
    seed, video = int(spec["seed"]), bool(spec["video"])
    (d / "expert.toml").write_text(
        f"[expert.link]\npose_rate_hz = 100.0\n{_ice_lines('expert', ice.get('expert'))}\n"
        "[expert.scans]\nenabled = true\n"
        f"start_after_model_s = {START_AFTER_MODEL_S}\nlength_s = {float(spec['scan_s'])}\n"
        f"repeat = true\ngap_s = {float(spec['gap_s'])}\n"
        f"[expert.video]\nenabled = {str(video).lower()}\nrecord_frames = true\n"
        "record_encoded = true\n"
        f'[servo.device]\nbackend = "sim"\nseed = {seed}\n'
    )
    (d / "follower.toml").write_text(
        f"[follower.link]\n{_ice_lines('follower', ice.get('follower'))}\n"
        f"[follower.video]\nenabled = {str(video).lower()}\n"
        f"record_us_hz = {RECORD_US_HZ}\nrecord_pov_hz = 0.0\n"
        f'[follower.clinic]\nbackend = "sim"\n[follower.clinic.novice]\nseed = {seed}\n'
        f'[sensing.camera]\nbackend = "sim"\nseed = {seed}\n'
        f'[sensing.force.sensor]\nbackend = "sim"\nseed = {seed}\n'
    )
    (d / "demo.toml").write_text(
        f"[demo]\nexpert_config = {_toml(str(d / 'expert.toml'))}\n"
        f"follower_config = {_toml(str(d / 'follower.toml'))}\n"
        'follower_id = "F1"\nsonographer_id = "S1"\n'
    )
    return d / "demo.toml"


def netem_config(spec: dict):
    """The emulator's settings of the run (ms, % and kbit/s to SI)."""
    from humantele.transport.netem import NetemConfig

    c = spec["condition"]
    return NetemConfig(
        delay_s=c["delay_ms"] * 1e-3,
        jitter_s=c["jitter_ms"] * 1e-3,
        loss=c["loss_pct"] / 100.0,
        bandwidth_kbps=c["bandwidth_kbps"],
        seed=int(spec["seed"]),
    )


def scans_done(stats: dict | None, scans: int) -> bool:
    """The expert's stats say its last scan has stopped."""
    return bool(stats) and int(stats.get("scans_started") or 0) >= scans and not stats.get("scan")


async def stop_when_scans_done(tmp: Path, scans: int, out: dict) -> None:
    """SIGTERM this process (the demo stops cleanly) once the expert has stopped scan
    ``scans``; ``out["stopped_after_scans"]`` says it did."""
    from humantele.runtime.stats import read_stats

    while True:
        await asyncio.sleep(POLL_S)
        for path in tmp.glob("humantele-demo-*/expert.json"):
            if scans_done(read_stats(path), scans):
                out["stopped_after_scans"] = True
                os.kill(os.getpid(), signal.SIGTERM)
                return


async def run_session(run_dir: Path, spec: dict) -> dict:
    """Run the session; its summary (see the module docstring)."""
    from humantele.demo import run_demo
    from humantele.transport.netem import UdpRelay
    from humantele.transport.turnserver import TurnServer

    tmp = run_dir / "tmp"
    tmp.mkdir(exist_ok=True)
    tempfile.tempdir = str(tmp)  # the demo's run directory (its stats files) is made here
    netem = netem_config(spec)
    scans_s = spec["scans"] * spec["scan_s"] + (spec["scans"] - 1) * spec["gap_s"]
    duration = spec.get("setup_timeout_s", 180.0) + START_AFTER_MODEL_S + scans_s + 10.0
    watch: dict[str, Any] = {"stopped_after_scans": False}
    load0 = os.getloadavg()
    t0 = time.monotonic()
    async with contextlib.AsyncExitStack() as stack:
        turn = await stack.enter_async_context(TurnServer())
        relay = await stack.enter_async_context(UdpRelay((turn.host, turn.port), netem))
        ice = {"expert": turn.ice_server(*relay.address), "follower": turn.ice_server()}
        conf_dir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="conf-")))
        config = write_configs(conf_dir, spec, ice)
        demo_args = argparse.Namespace(
            config=str(config), duration=duration, json=True, room=None, keep=False,
            log_level="WARNING", record=str(run_dir / RECORD_BASE),
        )  # fmt: skip
        watcher = asyncio.create_task(stop_when_scans_done(tmp, int(spec["scans"]), watch))
        out = io.StringIO()
        try:
            code = await run_demo(demo_args, out=out)
        finally:
            watcher.cancel()
        counters = relay.counters.as_dict()
    lines = out.getvalue().strip().splitlines()
    summary = json.loads(lines[-1]) if lines else {}
    return {
        "spec": spec,
        "exit_code": code,
        "stopped_after_scans": watch["stopped_after_scans"],
        "wall_s": round(time.monotonic() - t0, 2),
        "load_at_start": [round(v, 2) for v in load0],
        "load_at_end": [round(v, 2) for v in os.getloadavg()],
        "netem": netem.model_dump(),
        "relay": counters,
        "demo": summary,
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def _write_json(path: Path, data: dict) -> None:
    part = path.with_suffix(".part")
    part.write_text(json.dumps(data, indent=1), encoding="utf-8")
    part.replace(path)  # atomic: a run is done only once its whole summary is there


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="humantele.study.session")
    p.add_argument("run_dir", type=Path)
    args = p.parse_args(argv)
    run_dir: Path = args.run_dir
    spec = json.loads((run_dir / "run.json").read_text(encoding="utf-8"))
    try:
        summary = asyncio.run(run_session(run_dir, spec))
    except Exception as exc:  # the parent reports it and runs the next condition
        _write_json(run_dir / "failed.json", {"reason": f"{type(exc).__name__}: {exc}"})
        raise
    finally:
        from humantele.runtime.process import ignore_stop_signals

        ignore_stop_signals()
    recorded = all((run_dir / f"session.{r}.mcap").exists() for r in ("expert", "follower"))
    if summary["exit_code"] != 0 or not recorded or not summary["stopped_after_scans"]:
        why = (
            f"demo exit code {summary['exit_code']}"
            if summary["exit_code"] != 0
            else "no recordings"
            if not recorded
            else "the scans did not all finish in time"
        )
        _write_json(run_dir / "failed.json", {"reason": why, "summary": summary})
        return 1
    _write_json(run_dir / "summary.json", summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())

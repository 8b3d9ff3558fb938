"""The demo's plan (``humantele demo``, :mod:`humantele.demo`): from its arguments and its
``[demo]`` section (configs/demo.toml), what it starts: the run directory, the children's
environment (the signaling token, the pages' key and pairing code: never printed), each
daemon's command with its configuration (the follower's on a replayed clinic with
``--replay``; the sim ultrasound's scale for the expert's console) and the recordings'
files with ``--record``. Nothing is started here: a refused argument or file is a
ConfigError (exit code 2) before any process runs."""

from __future__ import annotations

import argparse
import json
import os
import secrets
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import field_validator

from humantele.recording.schemas import check_participant_id
from humantele.runtime.process import PARENT_PID_ENV
from humantele.signaling.messages import TOKEN_ENV
from humantele.web.credential import CONSOLE_KEY_ENV, PAIRING_CODE_ENV, new_code, new_key


def _demo_config_model():
    from pydantic import Field

    from humantele.config import ConfigModel

    class DemoConfig(ConfigModel):
        """``[demo]`` of configs/demo.toml; relative paths are from the file's directory's
        parent (the repository root for configs/demo.toml) or the current directory."""

        room: str = Field("demo", pattern=r"^[A-Za-z0-9_.-]{1,64}$")
        expert_config: str | None = None
        follower_config: str | None = None
        # Pseudonyms recorded with --record: the simulated follower and sonographer.
        follower_id: str = "F0"
        sonographer_id: str = "S0"

        @field_validator("follower_id", "sonographer_id")
        @classmethod
        def _pseudonym(cls, v: str, info: Any) -> str:
            return check_participant_id(v, info.field_name)

    return DemoConfig


def _resolve(path: str | None, base: Path) -> str | None:
    if not path:
        return None
    p = Path(path).expanduser()
    for cand in (p, base / p):
        if cand.exists():
            return str(cand.resolve())
    from humantele.config import ConfigError

    raise ConfigError(f"{path}: no such configuration file (from the [demo] section)")


def recording_paths(record: str | Path) -> dict[str, Path]:
    """The files the daemons record to for ``--record FILE``; ConfigError (exit code 2) when
    one exists (never overwritten) or its directory is missing or not writable. ``FILE`` a
    directory (or ending in ``/``): ``session-<date>-<time>`` files in it. The daemons check
    again (and the disk space) when they open them."""
    from humantele.config import ConfigError
    from humantele.recording import role_path

    base = Path(record).expanduser()
    if str(record).endswith(("/", os.sep)) or base.is_dir():  # a directory: a file in it
        if not base.is_dir():
            raise ConfigError(f"--record: no directory {base}")
        base = base / time.strftime("session-%Y%m%d-%H%M%S.mcap")
    paths = {role: role_path(base, role) for role in ("expert", "follower")}
    for path in paths.values():
        parent = path.parent
        if path.exists():
            raise ConfigError(f"--record: {path} exists (a recording is never overwritten)")
        if not parent.is_dir():
            raise ConfigError(f"--record: no directory {parent} for {path}")
        if not os.access(parent, os.W_OK):
            raise ConfigError(f"--record: directory {parent} is not writable")
    return paths


def replay_follower_config(recording: str, run_dir: Path) -> str:
    """A follower configuration (written in ``run_dir``) whose clinic is ``recording``
    replayed through the real backends: tracker, force board and, if recorded, video.
    ConfigError (exit code 2) for a file that is not a device recording."""
    from humantele.config import ConfigError
    from humantele.recording.device_file import DeviceRecordingError, open_recording

    path = Path(recording).resolve()
    try:
        info = open_recording(path).info
    except (OSError, DeviceRecordingError) as exc:
        raise ConfigError(f"--replay: {exc}") from None
    devices = set(info.get("devices", "").split(","))
    if "ahat" not in devices or "force" not in devices:
        raise ConfigError(f"--replay: {path} has no tracker frames and force reports to replay")
    file = json.dumps(str(path))
    text = (
        '[follower.clinic]\nbackend = "devices"\n'
        f'[sensing.camera]\nbackend = "replay"\nfile = {file}\nloop = true\n'
        f'[sensing.force.sensor]\nbackend = "replay"\nfile = {file}\nloop = true\n'
    )
    video = {"us", "pov"} <= devices
    text += f"[follower.video]\nenabled = {str(video).lower()}\n"
    if video:
        for track in ("us", "pov"):
            text += f'[follower.video.{track}]\nbackend = "replay"\nfile = {file}\nloop = true\n'
    out = run_dir / "follower-replay.toml"
    out.write_text(text, encoding="utf-8")
    return str(out)


def us_scale(follower_config: str | None) -> tuple[tuple[float, float], float] | None:
    """(row, col) mm per pixel and the row (px) of depth 0 of the follower's ultrasound when
    it is the sim one (the demo tells the expert's console: its calipers and its depth
    scale); None for a real source."""
    from humantele.config import load_config
    from humantele.follower.daemon import FollowerConfig
    from humantele.video.scan import ScanGeometry
    from humantele.video.sim_ultrasound import SimUltrasoundConfig

    cfg = load_config(FollowerConfig, follower_config, "follower" if follower_config else None)
    c = cfg.video.us
    if not isinstance(c, SimUltrasoundConfig):
        return None
    g = ScanGeometry(c.probe, c.width, c.height, c.depth_m, c.fov_deg, c.radius_m,
                     c.aperture_m, c.beams, c.samples)  # fmt: skip
    return g.pixel_spacing_mm, g.depth_origin_row


@dataclass
class DemoPlan:
    """What the demo starts: the run directory (logs, stats, the follower's state), the
    children's environment (the token, the pages' key and code: never printed), each
    daemon's command (after ``python -m humantele``, before the link's arguments) and its
    stats file, and the recordings (role -> path; empty without ``--record``)."""

    room: str
    run_dir: Path
    token: str
    env: dict[str, str]
    cmds: dict[str, list[str]]
    stats: dict[str, Path]
    rec_paths: dict[str, Path]


def plan_demo(args: argparse.Namespace) -> DemoPlan:
    """The demo's plan from its arguments and ``[demo]`` config (refused: ConfigError)."""
    from humantele.config import load_config

    cfg = load_config(_demo_config_model(), args.config, "demo" if args.config else None)
    base = Path(args.config).resolve().parent.parent if args.config else Path.cwd()
    child_configs = {
        "expert": _resolve(cfg.expert_config, base),
        "follower": _resolve(cfg.follower_config, base),
    }
    record = getattr(args, "record", None)
    rec_paths = recording_paths(record) if record else {}
    run_dir = Path(tempfile.mkdtemp(prefix="humantele-demo-"))
    token = secrets.token_urlsafe(24)
    env = dict(os.environ)
    env[TOKEN_ENV] = token
    env[PARENT_PID_ENV] = str(os.getpid())
    env.setdefault(CONSOLE_KEY_ENV, new_key())  # the demo prints the pages' addresses with them
    env.setdefault(PAIRING_CODE_ENV, new_code())
    cmds = {
        "follower": [
            "follower", "--state-dir", str(run_dir / "follower-state"), "--feed-port", "0",
        ],
        "expert": ["expert", "--console-port", "0"],
    }  # fmt: skip
    if getattr(args, "replay", None):
        child_configs["follower"] = replay_follower_config(args.replay, run_dir)
    for role, path in child_configs.items():
        if path:
            cmds[role] += ["--config", path]
    if getattr(args, "igtl_port", None) is not None:
        cmds["follower"] += ["--igtl-port", str(args.igtl_port)]
    scale = us_scale(child_configs["follower"])
    if scale is not None:  # the console's calipers and depth scale on the sim ultrasound
        spacing, depth0 = scale
        cmds["expert"] += ["--us-pixel-spacing-mm", *(f"{v:.9g}" for v in spacing),
                           "--us-depth-origin-row", f"{depth0:.6g}"]  # fmt: skip
    if rec_paths:  # one file per daemon, one session id
        ids = ["--session-id", secrets.token_hex(6), "--follower-id", cfg.follower_id,
               "--sonographer-id", cfg.sonographer_id]  # fmt: skip
        for role in cmds:
            cmds[role] += ["--record", str(rec_paths[role]), *ids]
    stats = {role: run_dir / f"{role}.json" for role in ("expert", "follower")}
    return DemoPlan(args.room or cfg.room, run_dir, token, env, cmds, stats, rec_paths)

"""``humantele devices check``: what is connected, and a few samples from each device.

For each device family the check opens the backend the configuration names (the expert's
``[servo.device]``; the follower's ``[sensing.camera]`` and ``[sensing.force]``), reads a few
samples and prints one summary line, or the device's own error message saying what to do.
It also lists the HID devices the system shows (with read permission or not) and whether the
OpenHaptics library can be found. Exit status: 0 when every checked device gave samples.

    humantele devices check                       # the default (sim) devices
    humantele devices check --expert-config configs/expert.toml \\
                            --follower-config configs/follower.toml --samples 20
"""

from __future__ import annotations

import argparse
import ctypes.util
import json
import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Check:
    """One device's outcome: ``ok``, the backend, a one-line summary, the samples' figures."""

    device: str
    backend: str
    ok: bool
    summary: str
    figures: dict[str, Any] = field(default_factory=dict)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION")
    p = sub.add_parser("check", help="list devices and read a few samples from each")
    p.add_argument("--expert-config", help="TOML with [servo.device] (the haptic device)")
    p.add_argument("--follower-config", help="TOML with [sensing] (tracker camera, force)")
    p.add_argument("--samples", type=int, default=10, help="samples to read per device")
    p.add_argument("--only", choices=["haptic", "tracker", "force", "hid"], action="append",
                   help="check only these (repeatable)")  # fmt: skip
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    from humantele.devices import hl2ss_calibration, record

    hl2ss_calibration.add_parser(sub)
    record.add_parser(sub)


def list_hid() -> list[dict[str, Any]]:
    """HID devices the system shows: ids, names, path and whether this user may open it."""
    try:
        import hid
    except ImportError:
        return []
    out = []
    for d in hid.enumerate():
        path = d.get("path", b"")
        p = path.decode(errors="replace") if isinstance(path, bytes) else str(path)
        out.append({
            "vendor_id": f"0x{d.get('vendor_id', 0):04x}",
            "product_id": f"0x{d.get('product_id', 0):04x}",
            "product": d.get("product_string") or "",
            "manufacturer": d.get("manufacturer_string") or "",
            "path": p,
            "readable": os.access(p, os.R_OK | os.W_OK) if p.startswith("/dev/") else None,
        })  # fmt: skip
    return out


def check_haptic(config: Any, n: int) -> Check:
    """Open the haptic device, read ``n`` states (1 ms apart), command zero force, close."""
    from humantele.haptics.devices import DeviceError, make_device

    backend = str(getattr(config, "backend", getattr(config, "kind", "?")))
    try:
        dev = make_device(config)
        dev.open()
    except (DeviceError, OSError, ValueError) as exc:
        return Check("haptic device", backend, False, str(exc))
    try:
        states = []
        t_first = time.monotonic() + 2.0  # a driver may take a moment to deliver its first state
        while len(states) < n:
            time.sleep(0.001)
            try:
                states.append(dev.read())
            except DeviceError:
                if states or time.monotonic() > t_first:
                    raise
                continue
            dev.command_force((0.0, 0.0, 0.0))
    except DeviceError as exc:
        return Check("haptic device", backend, False, str(exc))
    finally:
        dev.close()
    p = np.array([s.position for s in states]) * 1e3
    figs = {"samples": len(states), "position_mm": [round(float(v), 2) for v in p[-1]],
            "spread_mm": round(float(np.ptp(p, axis=0).max()), 3),
            "buttons": int(states[-1].buttons), "has_force": bool(dev.has_force)}  # fmt: skip
    extra = []
    for attr in ("calibration", "model", "force_limit_n", "continuous_force_n"):
        if getattr(dev, attr, None) not in (None, ""):
            extra.append(f"{attr} {getattr(dev, attr)}")
    summary = (f"{len(states)} states, stylus at {figs['position_mm']} mm (spread "
               f"{figs['spread_mm']} mm), buttons {figs['buttons']}"
               + (", " + ", ".join(extra) if extra else ""))  # fmt: skip
    ok = all(s.is_finite() for s in states)
    return Check("haptic device", backend, ok, summary if ok else "non-finite states", figs)


def check_tracker(config: Any, tool: str, n: int, anchor: str = "device") -> Check:
    """Open the tracker camera, read ``n`` frames, run the tracker on them. With
    ``anchor = "device"`` (``[sensing] camera_anchor``: each frame places the camera, the
    headset's rig pose with hl2ss) a real camera's stream in which no frame had the camera's
    pose fails: the follower could place no probe with it (hl2ss: the headset not located,
    or mode 0)."""
    from humantele.tracking.frames import FrameSourceUnavailable
    from humantele.tracking.pipeline import Tracker
    from humantele.tracking.sources import make_frame_source
    from humantele.tracking.tool import load_tool

    backend = config.backend
    try:
        src = make_frame_source(config)
        src.open()
    except (FrameSourceUnavailable, OSError, ValueError) as exc:
        return Check("tracker camera", backend, False, str(exc))
    tracker = Tracker(load_tool(tool))
    frames, tracked, with_pose = 0, 0, 0
    last = None
    try:
        for _ in range(n):
            f = src.read()
            if f is None:
                continue
            frames += 1
            last = f
            tracked += tracker.process(f).status == "tracked"
            with_pose += f.T_world_camera is not None
    finally:
        src.close()
    if last is None:
        return Check("tracker camera", backend, False, f"no frame in {n} reads")
    valid = None if last.depth_mm is None else float(np.mean(last.depth_mm > 0))
    figs = {"frames": frames, "size": list(last.ir.shape[::-1]), "ir_max": int(last.ir.max()),
            "depth_valid": None if valid is None else round(valid, 3),
            "tracked": tracked, "camera_pose": with_pose}  # fmt: skip
    depth = "no depth" if valid is None else f"depth valid {100 * valid:.0f} %"
    summary = (f"{frames}/{n} frames {figs['size'][0]}x{figs['size'][1]}, IR max "
               f"{figs['ir_max']}, {depth}, probe tracked in {tracked}, camera pose in "
               f"{with_pose}")  # fmt: skip
    no_pose = dict(getattr(src, "no_pose", {}) or {})
    figs["no_pose"] = no_pose
    if anchor == "device" and backend != "sim" and with_pose == 0:  # (the sim clinic places
        # its simulated camera itself; its bare frame source carries no pose)
        why = ", ".join(f"{k} {v}" for k, v in no_pose.items()) or "none given"
        summary += (f": no frame carried the camera's pose ({why}), so no probe can be placed "
                    "in the world; is the headset tracking its surroundings (hl2ss mode 1), or "
                    'is the camera fixed ([sensing] camera_anchor = "fixed")?')  # fmt: skip
        return Check("tracker camera", backend, False, summary, figs)
    return Check("tracker camera", backend, True, summary, figs)


def check_force(config: Any, n: int) -> Check:
    """Open the force sensor, read ``n`` readings."""
    from humantele.forcesense.hid import ForceSensorUnavailable
    from humantele.forcesense.sensors import make_force_sensor

    sensor_cfg = config.sensor
    backend = sensor_cfg.backend
    try:
        sensor = make_force_sensor(sensor_cfg)
        sensor.open()
    except (ForceSensorUnavailable, OSError, ValueError) as exc:
        return Check("force sensor", backend, False, str(exc))
    readings = []
    try:
        for k in range(n):
            r = sensor.read(time.monotonic() if backend != "sim" else k * 0.01)
            if r is not None:
                readings.append(r)
            time.sleep(0.005)
    finally:
        sensor.close()
    dropped = dict(getattr(sensor, "dropped", {}) or {})
    if not readings:
        return Check("force sensor", backend, False,
                     f"no reading in {n} reads (dropped: {dropped or 'none'})")  # fmt: skip
    d = np.array([r.differential for r in readings])
    ok = bool(np.all(np.isfinite(d)))
    figs = {"readings": len(readings), "pairs": int(d.shape[1]),
            "differential_mT": [round(float(v), 3) for v in d[-1]],
            "noise_mT": round(float(d.std(axis=0).max()), 4),
            "temperature_c": round(float(readings[-1].temperature_c), 2),
            "dropped": dropped}  # fmt: skip
    summary = (f"{len(readings)}/{n} readings, {figs['pairs']} pairs, noise "
               f"{figs['noise_mT']} mT, {figs['temperature_c']} deg C"
               + (f", dropped {dropped}" if dropped else ""))  # fmt: skip
    return Check("force sensor", backend, ok, summary, figs)


def _expert_device(path: str | None) -> Any:
    from humantele.config import load_config
    from humantele.haptics.servo_config import ServoConfig

    return load_config(ServoConfig, path, "servo" if path else None).device


def _sensing(path: str | None) -> Any:
    from humantele.config import load_config
    from humantele.follower.sensing import SensingConfig

    return load_config(SensingConfig, path, "sensing" if path else None)


def _tool(path: str | None) -> str:
    """The probe's tool ([follower] tool of the follower's file; the default probe without)."""
    from humantele.config import read_config_file
    from humantele.tracking.tool import DEFAULT_TOOL

    if path is None:
        return DEFAULT_TOOL
    follower = read_config_file(path).get("follower", {})
    return str(follower.get("tool", DEFAULT_TOOL)) if isinstance(follower, dict) else DEFAULT_TOOL


def run_checks(args: argparse.Namespace) -> tuple[list[Check], dict[str, Any]]:
    only = set(args.only or ["haptic", "tracker", "force", "hid"])
    n = max(1, int(args.samples))
    checks: list[Check] = []
    if "haptic" in only:
        checks.append(check_haptic(_expert_device(args.expert_config), n))
    sensing = _sensing(args.follower_config) if {"tracker", "force"} & only else None
    if "tracker" in only:
        checks.append(check_tracker(sensing.camera, _tool(args.follower_config), n,
                                    sensing.camera_anchor))  # fmt: skip
    if "force" in only:
        checks.append(check_force(sensing.force, n))
    system: dict[str, Any] = {}
    if "hid" in only:
        system["hid"] = list_hid()
        system["openhaptics_libHD"] = ctypes.util.find_library("HD")
        system["touch_driver"] = ctypes.util.find_library("PhantomIOLib42")
        from humantele.haptics.devices.touchx import gtdd_home_problem

        system["gtdd_home"] = os.environ.get("GTDD_HOME")
        system["gtdd_home_problem"] = gtdd_home_problem()
    return checks, system


def run(args: argparse.Namespace) -> int:
    if getattr(args, "action", None) == "hl2ss-calibration":
        from humantele.devices import hl2ss_calibration

        return hl2ss_calibration.run(args)
    if getattr(args, "action", None) == "record":
        from humantele.devices import record

        return record.run(args)
    if getattr(args, "action", None) != "check":
        print(
            "usage: humantele devices check [--expert-config F] [--follower-config F]\n"
            "       humantele devices hl2ss-calibration --host H --out FILE\n"
            "       humantele devices record --follower-config F --out REC.mcap [--duration S]"
        )
        return 2
    checks, system = run_checks(args)
    if args.json:
        print(json.dumps({"checks": [c.__dict__ for c in checks], **system}, default=str))
    else:
        for c in checks:
            mark = "ok  " if c.ok else "FAIL"
            print(f"[{mark}] {c.device} ({c.backend}): {c.summary}")
        if "hid" in system:
            hids = system["hid"]
            print(f"HID devices seen: {len(hids)}")
            for h in hids:
                perm = {True: "", False: "  (no permission: see examples/udev)", None: ""}
                print(f"  {h['vendor_id']}:{h['product_id']} {h['manufacturer']} "
                      f"{h['product']} {h['path']}{perm[h['readable']]}")  # fmt: skip
            lib = system["openhaptics_libHD"]
            print(f"OpenHaptics libHD: {lib or 'not found (only needed for the touchx backend)'}")
            drv = system["touch_driver"]
            print(
                "3D Systems Touch driver (libPhantomIOLib42.so): "
                f"{drv or 'not found (the touchx backend needs it for a Touch / Touch X)'}"
            )
            print(f"GTDD_HOME: {system['gtdd_home_problem'] or system['gtdd_home']}")
    return 0 if all(c.ok for c in checks) else 1


__all__ = ["Check", "check_force", "check_haptic", "check_tracker", "list_hid", "run"]

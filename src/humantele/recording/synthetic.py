"""A simulated session written as a real recording, with a known alignment error.

The expert's virtual probe follows a smooth trajectory (or a pure sine, for answers that can be
computed by hand) sampled at the servo rate on the expert's clock. The simulated follower holds
the real probe at the virtual pose ``lag_s`` earlier, plus a constant offset (position in the
patient frame, rotation in the probe frame: ``R_real = R_virtual(t - lag) R_offset``) and a
band-limited tremor; the tracker samples it at 45 Hz on the follower's clock, which is offset
(and may drift) from the expert's, with measurement noise and lost frames (``tracked`` false,
pose left at zero so an analysis that does not skip them is visibly wrong). The follower also
records clock-sync estimates (offset + noise, with a round trip) once a second.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.spatial.transform import Rotation

from humantele.config import ConfigModel
from humantele.recording.writer import McapLog, _session_metadata

EPOCH_NS = 1_700_000_000 * 10**9  # log times: a fixed wall-clock origin, deterministic files


class SyntheticSession(ConfigModel):
    """What to simulate. Lengths in mm and angles in degrees (edge units: a test's knobs)."""

    duration_s: float = Field(60.0, gt=0.0)
    n_scans: int = Field(1, ge=1)
    first_scan: int = Field(1, ge=0)
    expert_rate_hz: float = Field(1000.0, gt=0.0)
    tracking_rate_hz: float = Field(45.0, gt=0.0)
    trajectory: Literal["smooth", "sine"] = "smooth"
    amplitude_mm: float = Field(30.0, ge=0.0)
    rotation_amplitude_deg: float = Field(15.0, ge=0.0, lt=90.0)
    frequency_hz: float = Field(0.2, gt=0.0, description="sine frequency; smooth: the highest")
    offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_offset_deg: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="rotation vector of R_offset (probe frame), deg"
    )
    lag_s: float = Field(0.0, ge=0.0)
    tremor_mm: float = Field(0.0, ge=0.0, description="RMS per axis")
    tremor_deg: float = Field(0.0, ge=0.0, description="RMS per axis of the rotation vector")
    tracking_noise_mm: float = Field(0.0, ge=0.0, description="RMS per axis")
    tracking_noise_deg: float = Field(0.0, ge=0.0)
    dropout: float = Field(0.0, ge=0.0, lt=1.0, description="share of frames not tracked")
    sensing_gaps: list[tuple[float, float]] = Field(
        [], description="(s from the start, s long): no tracker frame at all (sensing killed)"
    )
    clock_offset_s: float = Field(0.0, description="expert clock minus follower clock, s")
    clock_drift_ppm: float = 0.0
    sync_period_s: float = Field(1.0, gt=0.0)
    sync_noise_s: float = Field(0.0005, ge=0.0)
    record_clock_sync: bool = True
    record_scan_events: bool = Field(True, description="False: no /expert/scan start/stop")
    follower_id: str = "F01"
    sonographer_id: str = "S1"
    session_id: str = "sim0001"
    seed: int = 0
    batch_max_samples: int = Field(100, ge=1)
    us_quality: list[float] | None = Field(
        None, description="sim US image quality (0-1) of each scan's frames, 10 per second"
    )


@dataclass
class SyntheticTruth:
    """What was simulated: scan intervals (expert clock) and sample counts."""

    scans: list[tuple[int, float, float]] = field(default_factory=list)
    n_expert: int = 0
    n_tracking: int = 0
    n_tracked: int = 0


T0_EXPERT = 1000.0  # the expert clock at the session's start, s


def virtual_pose(
    cfg: SyntheticSession, t: NDArray[np.float64]
) -> tuple[NDArray[np.float64], Rotation]:
    """The expert's virtual probe (position m, rotation) at expert times ``t`` (s)."""
    tau = t - T0_EXPERT
    amp = cfg.amplitude_mm / 1000.0
    ang = np.radians(cfg.rotation_amplitude_deg)
    base = np.array([0.0, 0.15, 0.0])
    if cfg.trajectory == "sine":
        w = 2.0 * np.pi * cfg.frequency_hz
        pos = base + np.outer(amp * np.sin(w * tau), [1.0, 0.0, 0.0])
        rotvec = np.outer(ang * np.sin(w * tau), [0.0, 1.0, 0.0])
        return pos, Rotation.from_rotvec(rotvec)
    rng = np.random.default_rng(cfg.seed + 7919)
    freqs = rng.uniform(0.2, 1.0, size=(2, 3, 3)) * cfg.frequency_hz
    phases = rng.uniform(0, 2 * np.pi, size=(2, 3, 3))
    waves = np.sin(2 * np.pi * freqs[..., None] * tau + phases[..., None]).sum(axis=2) / 3.0
    pos = base + amp * waves[0].T
    return pos, Rotation.from_rotvec(ang * waves[1].T)


def _band_noise(rng: np.random.Generator, t: NDArray[np.float64], rms: float) -> NDArray:
    """(N, 3) sum of 8 sinusoids per axis, 1-8 Hz, RMS ``rms`` per axis."""
    if rms == 0.0:
        return np.zeros((len(t), 3))
    k = 8
    f = rng.uniform(1.0, 8.0, size=(3, k, 1))
    ph = rng.uniform(0, 2 * np.pi, size=(3, k, 1))
    return (rms * np.sqrt(2.0 / k) * np.sin(2 * np.pi * f * t + ph).sum(axis=1)).T


def write_synthetic(
    path: str | Path, cfg: SyntheticSession | None = None, follower_path: str | Path | None = None
) -> SyntheticTruth:
    """Write the simulated session to ``path`` (one file, role "synthetic"), or the expert's topics
    to ``path`` and the follower's to ``follower_path`` (two files, as two daemons would)."""
    cfg = cfg or SyntheticSession()
    rng = np.random.default_rng(cfg.seed)
    truth = SyntheticTruth()

    # Expert: virtual probe at the servo rate, on the expert clock.
    n_e = int(round(cfg.duration_s * cfg.expert_rate_hz)) + 1
    t_e = T0_EXPERT + np.arange(n_e) / cfg.expert_rate_hz
    p_v, r_v = virtual_pose(cfg, t_e)
    q_v = r_v.as_quat()
    truth.n_expert = n_e

    # Follower clock: t_f = t_e - offset + drift * (t_e - T0).
    drift = cfg.clock_drift_ppm * 1e-6

    def to_follower(te: NDArray) -> NDArray:
        return te - cfg.clock_offset_s + drift * (te - T0_EXPERT)

    def to_expert(tf: NDArray) -> NDArray:
        return (tf + cfg.clock_offset_s + drift * T0_EXPERT) / (1.0 + drift)

    # Tracker frames at 45 Hz on the follower clock, covering the session.
    tf0 = float(to_follower(np.array([T0_EXPERT]))[0])
    n_f = int(cfg.duration_s * cfg.tracking_rate_hz)
    t_f = tf0 + (np.arange(n_f) + 0.5) / cfg.tracking_rate_hz
    te_f = to_expert(t_f)
    p_lag, r_lag = virtual_pose(cfg, te_f - cfg.lag_s)
    r_off = Rotation.from_rotvec(np.radians(cfg.rotation_offset_deg))
    tremor_p = _band_noise(rng, te_f, cfg.tremor_mm / 1000.0)
    tremor_r = Rotation.from_rotvec(_band_noise(rng, te_f, np.radians(cfg.tremor_deg)))
    p_real = p_lag + np.asarray(cfg.offset_mm) / 1000.0 + tremor_p
    r_real = r_lag * r_off * tremor_r
    p_meas = p_real + rng.normal(0.0, cfg.tracking_noise_mm / 1000.0, size=p_real.shape)
    r_meas = r_real * Rotation.from_rotvec(
        rng.normal(0.0, np.radians(cfg.tracking_noise_deg), size=(n_f, 3))
    )
    tracked = rng.random(n_f) >= cfg.dropout
    p_meas[~tracked] = 0.0
    q_meas = r_meas.as_quat()
    q_meas[~tracked] = [0.0, 0.0, 0.0, 1.0]
    since = te_f - T0_EXPERT
    measured = np.ones(n_f, dtype=bool)  # frames outside the sensing gaps
    for a, d in cfg.sensing_gaps:
        measured &= ~((since >= a) & (since < a + d))
    truth.n_tracking, truth.n_tracked = int(measured.sum()), int((tracked & measured).sum())

    # Scans: equal slices of the session with 1 s before, between and after.
    gap = 1.0
    length = (cfg.duration_s - gap * (cfg.n_scans + 1)) / cfg.n_scans
    if length <= 0:
        raise ValueError("duration_s too short for n_scans (1 s gaps)")
    events: list[tuple[float, str, float, dict[str, Any]]] = []
    for k in range(cfg.n_scans):
        start = T0_EXPERT + gap + k * (length + gap)
        scan = cfg.first_scan + k
        truth.scans.append((scan, start, start + length))
        ids = {"follower_id": cfg.follower_id, "sonographer_id": cfg.sonographer_id}
        if cfg.record_scan_events:
            events.append((start, "/expert/scan", start, {"event": "start", "scan": scan, **ids}))
            events.append(
                (start + length, "/expert/scan", start + length, {"event": "stop", "scan": scan})
            )
        if cfg.us_quality is not None:  # the sim US known answer, follower clock
            q = float(cfg.us_quality[k % len(cfg.us_quality)])
            for n, te in enumerate(np.arange(start + 0.05, start + length, 0.1)):
                tf = float(to_follower(np.array([te]))[0])
                frame = {"stream": "us", "seq": n + 1, "event": "captured", "quality": q}
                events.append((float(te), "/follower/video_frame", tf, frame))

    # Clock sync estimates (follower side) and a few slower streams.
    for tf in np.arange(tf0, tf0 + cfg.duration_s, cfg.sync_period_s):
        te = float(to_expert(np.array([tf]))[0])
        rtt = 0.02 + abs(rng.normal(0.0, 0.005))
        est = te - tf + rng.normal(0.0, cfg.sync_noise_s)
        if cfg.record_clock_sync:
            events.append((te, "/follower/clock_sync", tf, {"offset_s": est, "rtt_s": rtt}))
        events.append((te, "/expert/latency", te, {"name": "pose_one_way", "value_s": rtt / 2}))
        events.append((te, "/expert/servo_stats", te, {"rate_hz": cfg.expert_rate_hz}))
    events.append(
        (
            T0_EXPERT,
            "/follower/ellipsoid",
            tf0,
            {"center": [0.0, 0.0, 0.0], "semi_axes": [2.0, 0.15, 0.17]},
        )
    )

    md = {"session_id": cfg.session_id, "follower_id": cfg.follower_id}
    md["sonographer_id"] = cfg.sonographer_id
    logs = {}
    if follower_path is None:
        logs["expert"] = logs["follower"] = McapLog(
            path, _session_metadata("synthetic", **md), batch_max_samples=cfg.batch_max_samples
        )
    else:
        logs["expert"] = McapLog(
            path, _session_metadata("expert", **md), batch_max_samples=cfg.batch_max_samples
        )
        logs["follower"] = McapLog(
            follower_path,
            _session_metadata("follower", **md),
            batch_max_samples=cfg.batch_max_samples,
        )

    def ns(te: float) -> int:
        return EPOCH_NS + int(round((te - T0_EXPERT) * 1e9))

    pos_l, quat_l = p_v.tolist(), q_v.tolist()
    expert_stream = (
        (t, "/expert/pose", t, {"position": pos_l[i], "quaternion": quat_l[i]})
        for i, t in enumerate(t_e.tolist())
    )
    pm, qm, tr = p_meas.tolist(), q_meas.tolist(), tracked.tolist()
    probe_stream = (
        (
            te,
            "/follower/probe_pose",
            tf,
            {"position": pm[j], "quaternion": qm[j], "tracked": tr[j]},
        )
        for j, (te, tf) in enumerate(zip(te_f.tolist(), t_f.tolist(), strict=True))
        if measured[j]
    )
    events.sort(key=lambda e: e[0])
    merged = heapq.merge(expert_stream, probe_stream, iter(events), key=lambda e: e[0])
    for te, topic, t_local, payload in merged:
        role = "expert" if topic.startswith("/expert/") else "follower"
        logs[role].append(topic, t_local, payload, ns(te))
    for log in {id(v): v for v in logs.values()}.values():
        log.close()
    return truth

"""The headset's XR space registered to the tracker's world (``T_world_xr``).

The headset page draws in its WebXR reference space (``local-floor``: the headset's own,
y up, metres); everything the follower publishes is in the tracker's world. They are two
spaces: the page must draw ``T_xr_world @ X`` for a world pose ``X``. This module finds
``T_world_xr`` (maps XR coordinates into the world), keeps it per headset and watches it:

- **Touching targets** (what the project uses; docs/registration.md says why): the page
  shows a few targets in its XR space; the technician holds the tracked probe's tip on each
  (still for ``dwell_s``, or presses); each target's XR position is paired with the tip the
  tracker measures then (world). :func:`fit_rigid` solves the rigid transform by least
  squares (Kabsch/Umeyama without scale) and its residual; :func:`refusal` refuses a fit
  that is degenerate, above ``max_residual_mm`` or tilted (both spaces are y up).
- **Saved per headset** (the id the page sends) under the follower's ``state_dir``
  (``headsets.json``) and offered again when that headset's page says hello.
- **Watched**: the headset's pose is known in both spaces at once, the WebXR viewer pose
  in XR space (``viewer_pose`` from the page) and the rig pose the tracker's device reports
  in the world (``TrackingFrame.T_world_rig``). With the registration and the fixed
  viewer-to-rig offset ``T_viewer_rig`` (calibrated once per headset, right after its first
  touch registration) ``T_world_xr @ T_xr_viewer @ T_viewer_rig`` must equal ``T_world_rig``;
  when their median gap over the last samples passes ``watch_mm``/``watch_deg`` the page
  says "re-register".
- The trajectory method (no touching, once the offset is known): :func:`fit_from_trajectories`.

Units SI (m, rad, s) inside; mm and degrees only in what the page shows. Quaternions
(x, y, z, w). Times: the daemon's monotonic clock (``clock``, the one its ticks use).
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from humantele.config import ConfigModel
from humantele.geometry import Pose, matrix_to_quat, quat_normalize

log = logging.getLogger(__name__)

HEADSETS_FILE = "headsets.json"
UP = np.array([0.0, 1.0, 0.0])
TIP_KEPT_S = 3.0  # tip and rig poses kept this long (s)
LATE_PRESS_S = 2.0  # a press this soon after the dwell took the last target: crossed it (s)
STATES_KEPT = 16  # headsets whose last state is kept (a page may send any id)


class RegistrationConfig(ConfigModel):
    """Registering the headset's XR space to the tracker's world (``[follower.registration]``)."""

    max_residual_mm: float = Field(
        6.0, gt=0, le=100, description="refuse a fit whose RMS residual is above this (mm)"
    )
    min_points: int = Field(3, ge=3, le=8, description="touches needed for a fit")
    min_spread_mm: float = Field(
        40.0, gt=0, le=1000, description="refuse targets closer to a line than this (mm)"
    )
    max_tilt_deg: float = Field(
        10.0, gt=0, le=180, description="refuse a fit tilting 'up' more than this (180: off)"
    )
    dwell_s: float = Field(1.0, gt=0, le=10, description="tip held still this long: taken")
    dwell_mm: float = Field(2.0, gt=0, le=50, description="'still': RMS about the mean (mm)")
    tip_max_age_s: float = Field(
        0.25, gt=0, le=5, description="a press takes the tip only if measured this recently"
    )
    distance_check_mm: float = Field(
        20.0, gt=0, le=500,
        description="refuse a touch whose distances to the taken ones differ from the "
        "targets' by more than this (mm): a rigid move keeps distances",
    )  # fmt: skip
    watch_mm: float = Field(20.0, gt=0, le=1000, description="'re-register' beyond this (mm)")
    watch_deg: float = Field(3.0, gt=0, le=180, description="'re-register' beyond this (deg)")
    watch_samples: int = Field(15, ge=1, le=1000, description="median over this many pairs")
    pair_within_s: float = Field(
        0.05, gt=0, le=1, description="a viewer pose pairs with a rig pose this close in time"
    )
    offset_samples: int = Field(
        20, ge=1, le=1000, description="pairs averaged for the viewer-to-rig offset"
    )


# --- the solvers ---------------------------------------------------------------------------


class DegenerateRegistration(ValueError):
    """The points cannot fix a rigid transform (too few, or on a line); the message says why."""


@dataclass(frozen=True)
class RigidFit:
    """A least-squares ``T_world_xr``: per-point residuals (m), their RMS (m), and how much
    the fit tilts the XR space's up axis away from the world's (rad)."""

    T_world_xr: Pose
    residuals_m: tuple[float, ...]
    rms_m: float
    tilt_rad: float

    @property
    def n(self) -> int:
        return len(self.residuals_m)


def _points(a: ArrayLike, name: str) -> NDArray[np.float64]:
    p = np.asarray(a, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise DegenerateRegistration(f"{name}: need (n, 3) points, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise DegenerateRegistration(f"{name}: points must be finite")
    return p


def fit_rigid(
    points_xr: ArrayLike, points_world: ArrayLike, min_spread_m: float = 0.04
) -> RigidFit:
    """``T_world_xr`` minimising ``sum |T p_xr - p_world|^2`` (Kabsch/Umeyama, no scale).

    Raises :class:`DegenerateRegistration` for fewer than 3 pairs or XR points closer to a
    line than ``min_spread_m`` (RMS distance from their best line, m): such points leave a
    rotation about that line free."""
    a, b = _points(points_xr, "XR points"), _points(points_world, "world points")
    if a.shape != b.shape:
        raise DegenerateRegistration(f"{len(a)} XR points but {len(b)} world points")
    if len(a) < 3:
        raise DegenerateRegistration(f"{len(a)} points: a rigid fit needs at least 3")
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    da, db = a - ca, b - cb
    sv = np.linalg.svd(da, compute_uv=False)
    off_line = math.sqrt(float(sv[1] ** 2 + sv[2] ** 2) / len(a))
    if off_line < min_spread_m:
        raise DegenerateRegistration(
            f"the targets lie on a line ({off_line * 1000:.0f} mm off it, "
            f"need {min_spread_m * 1000:.0f} mm): the rotation about it is free"
        )
    U, _, Vt = np.linalg.svd(db.T @ da)  # cross-covariance, world x XR
    d = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = U @ np.diag([1.0, 1.0, d]) @ Vt  # the nearest rotation (no reflection)
    t = cb - R @ ca
    res = np.linalg.norm(a @ R.T + t - b, axis=1)
    up = R @ UP
    tilt = math.acos(max(-1.0, min(1.0, float(up @ UP))))
    T = Pose(t, matrix_to_quat(R))
    return RigidFit(T, tuple(float(r) for r in res), float(np.sqrt(np.mean(res**2))), tilt)


def refusal(fit: RigidFit, config: RegistrationConfig) -> str | None:
    """Why ``fit`` is not good enough to use (one sentence for the technician), or None."""
    rms_mm = fit.rms_m * 1000.0
    if rms_mm > config.max_residual_mm:
        worst = int(np.argmax(fit.residuals_m))
        return (
            f"residual {rms_mm:.1f} mm RMS is above {config.max_residual_mm:g} mm "
            f"(worst: target {worst + 1}, {fit.residuals_m[worst] * 1000:.0f} mm off): "
            "touch the targets again, holding the tip on the centre of each"
        )
    tilt_deg = math.degrees(fit.tilt_rad)
    if tilt_deg > config.max_tilt_deg:
        return (
            f"the fit tilts 'up' by {tilt_deg:.0f} degrees (both spaces are level; at most "
            f"{config.max_tilt_deg:g}): a touch was probably taken at the wrong target"
        )
    return None


def average_poses(poses: list[Pose]) -> Pose:
    """The mean of nearby poses: mean position, and the rotation nearest the mean matrix."""
    if not poses:
        raise ValueError("no poses to average")
    p = np.mean([q.position for q in poses], axis=0)
    M = np.mean([q.rotation_matrix for q in poses], axis=0)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0]) @ Vt
    return Pose(p, matrix_to_quat(R))


def viewer_rig_offset(T_world_xr: Pose, T_xr_viewer: list[Pose], T_world_rig: list[Pose]) -> Pose:
    """``T_viewer_rig`` (the rig frame in the WebXR viewer's) from simultaneous pairs and a
    registration: the one-time offset calibration."""
    if len(T_xr_viewer) != len(T_world_rig):
        raise ValueError("the two trajectories need as many poses each")
    return average_poses(
        [(T_world_xr @ v).inverse() @ r for v, r in zip(T_xr_viewer, T_world_rig, strict=True)]
    )


def fit_from_trajectories(
    T_xr_viewer: list[Pose], T_world_rig: list[Pose], T_viewer_rig: Pose
) -> Pose:
    """``T_world_xr`` from the headset's two trajectories (simultaneous poses, same length)
    with a known viewer-to-rig offset, no touching: each pair gives
    ``T_world_rig @ T_viewer_rig^-1 @ T_xr_viewer^-1``; their mean."""
    if len(T_xr_viewer) != len(T_world_rig) or not T_xr_viewer:
        raise ValueError("the two trajectories need as many poses each, at least one")
    T_rig_viewer = T_viewer_rig.inverse()
    return average_poses(
        [r @ T_rig_viewer @ v.inverse() for v, r in zip(T_xr_viewer, T_world_rig, strict=True)]
    )


def _nearest_rotation(M: NDArray[np.float64]) -> NDArray[np.float64]:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0]) @ Vt


def solve_trajectories(
    T_xr_viewer: list[Pose], T_world_rig: list[Pose], min_turn_rad: float = 0.35
) -> tuple[Pose, Pose]:
    """``(T_world_xr, T_viewer_rig)`` from the headset's two trajectories alone: the
    robot-world/hand-eye problem ``B_i = Z A_i X`` (``A_i = T_xr_viewer``, ``B_i =
    T_world_rig``, ``Z = T_world_xr``, ``X = T_viewer_rig``), linear least squares on the
    rotations (the null vector of the stacked Kronecker system, each block made a rotation),
    then on the translations. Needs the head turned about two or more axes (by at least
    ``min_turn_rad`` between the poses); raises :class:`DegenerateRegistration` otherwise."""
    if len(T_xr_viewer) != len(T_world_rig) or len(T_xr_viewer) < 3:
        raise DegenerateRegistration("need 3 or more simultaneous pose pairs")
    RA = [a.rotation_matrix for a in T_xr_viewer]
    RB = [b.rotation_matrix for b in T_world_rig]
    rel = [RA[0].T @ r for r in RA[1:]]  # the head's turns from the first pose (viewer)
    axes = np.array([
        np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) for r in rel
    ])  # fmt: skip
    sv = np.linalg.svd(axes, compute_uv=False)
    if len(sv) < 2 or sv[1] < 2.0 * math.sin(min_turn_rad):
        raise DegenerateRegistration(
            "the head turned about one axis only (or too little): turn it about two"
        )
    # R_Z R_A - R_B R_Y = 0 with R_Y = R_X^T; vec() column-major.
    eye = np.eye(3)
    rows = [
        np.hstack([np.kron(ra.T, eye), -np.kron(eye, rb)]) for ra, rb in zip(RA, RB, strict=True)
    ]
    _, _, Vt = np.linalg.svd(np.vstack(rows))
    v = Vt[-1]
    Rz, Ry = v[:9].reshape(3, 3, order="F"), v[9:].reshape(3, 3, order="F")
    if np.linalg.det(Rz) < 0:
        Rz, Ry = -Rz, -Ry
    Rz, Rx = _nearest_rotation(Rz), _nearest_rotation(Ry).T
    # t_B = R_Z R_A t_X + R_Z t_A + t_Z
    M = np.vstack([np.hstack([Rz @ ra, eye]) for ra in RA])
    rhs = np.concatenate(
        [b.position - Rz @ a.position for a, b in zip(T_xr_viewer, T_world_rig, strict=True)]
    )
    sol, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    return Pose(sol[3:], matrix_to_quat(Rz)), Pose(sol[:3], matrix_to_quat(Rx))


# --- what a page sends ---------------------------------------------------------------------

Coord = Annotated[float, Field(ge=-100.0, le=100.0, allow_inf_nan=False)]  # m
Unit = Annotated[float, Field(ge=-1.0, le=1.0, allow_inf_nan=False)]
Vec3 = tuple[Coord, Coord, Coord]
HeadsetId = Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]{1,64}$")]


class RegistrationMessage(BaseModel):
    """From a page: ``hello`` (this headset's page is open: offer its saved registration),
    ``start`` (register with these ``targets``, XR space, m, in order), ``take`` (take the
    tip now for the target asked), ``cancel``, ``reset`` (the page's XR space was reset:
    the registration no longer holds)."""

    model_config = ConfigDict(extra="forbid", strict=True)
    type: Literal["registration"]
    action: Literal["hello", "start", "take", "cancel", "reset"]
    headset: HeadsetId
    targets: list[Vec3] | None = Field(None, min_length=3, max_length=8)


class ViewerPoseMessage(BaseModel):
    """From a page in AR: the WebXR viewer's pose in its XR space (``T_xr_viewer``)."""

    model_config = ConfigDict(extra="forbid", strict=True)
    type: Literal["viewer_pose"]
    headset: HeadsetId
    position: Vec3
    quaternion: tuple[Unit, Unit, Unit, Unit]


PageMessage = Annotated[RegistrationMessage | ViewerPoseMessage, Field(discriminator="type")]
PAGE_MESSAGE = TypeAdapter(PageMessage)
PAGE_TYPES = ("registration", "viewer_pose")


# --- saved per headset ---------------------------------------------------------------------


def _pose_fields(T: Pose) -> dict[str, list[float]]:
    return {"position": T.position.tolist(), "quaternion": T.quaternion.tolist()}


def _pose_from(d: Any) -> Pose:
    return Pose(np.asarray(d["position"], dtype=float), quat_normalize(d["quaternion"]))


class HeadsetStore:
    """``headsets.json`` in the state dir: per headset id, its registration (``T_world_xr``,
    residual, when) and its viewer-to-rig offset. A file that cannot be read is set aside
    (``load_error``), never fatal."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.load_error = ""
        self.save_error = ""
        self.entries: dict[str, dict[str, Any]] = {}
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            if not isinstance(data, dict):
                raise ValueError("not a JSON object")
            for hid, e in data.items():
                _pose_from(e["T_world_xr"])  # checked now, not at use
                if e.get("T_viewer_rig") is not None:
                    _pose_from(e["T_viewer_rig"])
                self.entries[str(hid)] = e
        except FileNotFoundError:
            pass
        except (OSError, ValueError, KeyError, TypeError) as exc:
            self.entries = {}
            self.load_error = f"{path}: {exc}"
            log.warning("follower: headset registrations not read (%s)", self.load_error)

    def get(self, headset: str) -> dict[str, Any] | None:
        return self.entries.get(headset)

    def put(self, headset: str, entry: dict[str, Any]) -> bool:
        """Keep and write (atomically); False (and ``save_error``) when it cannot be written."""
        self.entries[headset] = entry
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_suffix(".tmp")
            tmp.write_text(json.dumps(self.entries, indent=1), encoding="utf-8")
            os.replace(tmp, self.path)
            self.save_error = ""
            return True
        except OSError as exc:
            self.save_error = f"{self.path}: {exc.strerror or exc}"
            log.warning("follower: headset registration not saved (%s)", self.save_error)
            return False


# --- the follower's side of the page's registration ----------------------------------------


@dataclass
class _Collecting:
    """A registration in progress: the targets (XR) and the tips taken for them (world)."""

    headset: str
    targets: NDArray[np.float64]
    taken: list[NDArray[np.float64]]
    refused: str = ""
    start_tip: NDArray[np.float64] | None = None  # where the tip was at start (world)
    armed: bool = False  # the tip has left where it was at start: a dwell may count


class HeadsetRegistration:
    """The follower's side of the headset page's registration (module docstring).

    ``publish(kind, fields)``: the feed's publish (``registration`` objects to the pages);
    ``on_page_message(msg)``: a page's ``registration`` / ``viewer_pose`` message (a dict;
    bad ones are counted in ``bad_messages``); ``on_measurement(t, tip_world, T_world_rig)``
    with each tracker measurement (world, m; None when not measured). ``clock``: the
    daemon's monotonic clock, the one ``t`` is on."""

    def __init__(
        self,
        config: RegistrationConfig | None,
        state_dir: str | Path,
        publish: Callable[[str, dict[str, Any]], None],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config or RegistrationConfig()
        self.publish = publish
        self.clock = clock
        self.store = HeadsetStore(Path(state_dir).expanduser() / HEADSETS_FILE)
        self.tips: deque[tuple[float, NDArray[np.float64]]] = deque()
        self.rigs: deque[tuple[float, Pose]] = deque()
        self.collecting: _Collecting | None = None
        self.finished: tuple[str, float] | None = None  # (headset, when) the last collection ended
        self.active: dict[str, Pose] = {}  # headset -> T_world_xr in use this session
        self.drift: dict[str, deque[tuple[float, float]]] = {}  # (m, rad) per headset
        self.offset_pairs: dict[str, list[tuple[Pose, Pose]]] = {}
        self.counts: Counter[str] = Counter()
        self.bad_messages: Counter[str] = Counter()
        self.last: dict[str, Any] = {}  # the last published state (any headset)
        self.states: OrderedDict[str, dict[str, Any]] = OrderedDict()  # the last, per headset
        self.last_fit: RigidFit | None = None

    @classmethod
    def attach(cls, follower_config: Any, feed: Any) -> HeadsetRegistration:
        """One for the follower daemon: its ``registration`` settings, kept under its
        ``state_dir``, publishing to ``feed`` (a :class:`~humantele.follower.feed.RendererFeed`)
        and taking the page messages it routes (``feed.page_handler``)."""
        reg = cls(follower_config.registration, follower_config.state_dir, feed.publish)
        feed.page_handler = reg.on_page_message
        return reg

    # --- from the tracker ----------------------------------------------------------------

    def on_measurement(self, t: float, tip_world: Pose | None, T_world_rig: Pose | None) -> None:
        """One tracker measurement at ``t`` (s): the probe tip and the headset's rig pose,
        world frame (None: not measured in this frame)."""
        if tip_world is not None:
            self.tips.append((t, np.array(tip_world.position, dtype=float)))
        if T_world_rig is not None:
            self.rigs.append((t, T_world_rig))
        for q in (self.tips, self.rigs):
            while q and q[0][0] < t - TIP_KEPT_S:
                q.popleft()
        if self.collecting is not None and tip_world is not None:
            self._dwell(t)

    # --- from the page -------------------------------------------------------------------

    def on_page_message(self, msg: dict[str, Any]) -> None:
        """A page's ``registration`` or ``viewer_pose`` message; a bad one is counted."""
        try:  # as JSON: the page's own types (strict: no strings for numbers)
            m = PAGE_MESSAGE.validate_json(json.dumps(msg, allow_nan=False))
        except (ValidationError, TypeError, ValueError):
            self.bad_messages["malformed"] += 1
            return
        if isinstance(m, ViewerPoseMessage):
            self._viewer_pose(m)
            return
        self.counts[m.action] += 1
        if m.action == "hello":
            self._offer(m.headset)
        elif m.action == "start":
            if m.targets is None:
                self.bad_messages["start_without_targets"] += 1
                return
            self._start(m.headset, np.asarray(m.targets, dtype=float))
        elif m.action == "take":
            self._take_now(m.headset)
        elif m.action == "cancel":
            if self.collecting is not None and self.collecting.headset == m.headset:
                self.collecting = None
                self._state(m.headset, "cancelled", "Registration cancelled.")
        elif m.action == "reset":
            self.active.pop(m.headset, None)
            self.drift.pop(m.headset, None)
            self._state(m.headset, "none", "The headset's space was reset: register again.")

    # --- registering ---------------------------------------------------------------------

    def _start(self, headset: str, targets: NDArray[np.float64]) -> None:
        if len(targets) < self.config.min_points:
            self.bad_messages["too_few_targets"] += 1
            self._state(
                headset, "refused", f"{len(targets)} targets: need {self.config.min_points}."
            )
            return
        try:  # the targets themselves must be able to fix a transform
            fit_rigid(targets, targets, self.config.min_spread_mm / 1000.0)
        except DegenerateRegistration as exc:
            self.bad_messages["degenerate_targets"] += 1
            self._state(headset, "refused", f"Targets unusable: {exc}.")
            return
        start_tip = self.tips[-1][1] if self.tips else None
        self.collecting = _Collecting(headset, targets, [], start_tip=start_tip)
        self.tips.clear()
        self._progress("")

    def _progress(self, refused: str) -> None:
        c = self.collecting
        assert c is not None
        c.refused = refused
        i = len(c.taken)
        self._state(
            c.headset,
            "collecting",
            f"Hold the probe's tip still on target {i + 1} of {len(c.targets)}.",
            index=i,
            count=len(c.targets),
            refused=refused,
        )

    def _recent_tips(self, since: float) -> NDArray[np.float64]:
        pts = [p for t, p in self.tips if t >= since]
        return np.array(pts) if pts else np.zeros((0, 3))

    def _dwell(self, t: float) -> None:
        """Take the tip when it has been still for ``dwell_s`` (with enough frames)."""
        cfg = self.config
        c = self.collecting
        assert c is not None
        if not c.armed:  # a probe lying still at start is not a touch of target 1
            moved = c.start_tip is None or np.linalg.norm(self.tips[-1][1] - c.start_tip) > 0.03
            c.armed = bool(moved)
            return
        if not self.tips or self.tips[0][0] > t - cfg.dwell_s:
            return  # not tracked for that long yet
        since = t - cfg.dwell_s
        window = [(tt, p) for tt, p in self.tips if tt >= since]
        if len(window) < 5 or window[0][0] - since > 0.1 or window[-1][0] < t:
            return  # tracked for less than the whole dwell (a gap), or not in this frame
        pts = np.array([p for _, p in window])
        spread = float(np.sqrt(np.mean(np.sum((pts - pts.mean(axis=0)) ** 2, axis=1))))
        if spread * 1000.0 > cfg.dwell_mm:
            return
        self._take(pts.mean(axis=0), dwell=True)

    def _take_now(self, headset: str) -> None:
        """The technician pressed: the tip of the last few frames, if recent."""
        c = self.collecting
        now = self.clock()
        if c is None and self.finished is not None and self.finished[0] == headset:
            if now - self.finished[1] < LATE_PRESS_S:  # pressed as the dwell took the last
                self.counts["press_after_done"] += 1  # target: the page had not heard yet
                return
        if c is None or c.headset != headset:
            self.bad_messages["take_not_collecting"] += 1
            return
        if not self.tips or now - self.tips[-1][0] > self.config.tip_max_age_s:
            self._progress("the probe's tip is not tracked: keep its markers in view")
            return
        self._take(self._recent_tips(self.tips[-1][0] - 0.2).mean(axis=0), dwell=False)

    def _take(self, tip: NDArray[np.float64], dwell: bool) -> None:
        c = self.collecting
        assert c is not None
        i = len(c.taken)
        if c.taken:
            # Rigid: the tip's distances to the taken touches match the targets' distances.
            got = np.linalg.norm(np.array(c.taken) - tip, axis=1)
            want = np.linalg.norm(c.targets[:i] - c.targets[i], axis=1)
            gap = float(np.max(np.abs(got - want))) * 1000.0
            if gap > self.config.distance_check_mm:
                if dwell and float(np.min(got)) < 0.03:
                    return  # still resting on the previous target: not a touch yet
                self.counts["touch_refused"] += 1
                self.tips.clear()  # the next dwell starts afresh
                self._progress(
                    f"not at target {i + 1}: {gap:.0f} mm from where it should be "
                    "relative to the targets already touched"
                )
                return
        c.taken.append(tip)
        self.tips.clear()  # a dwell on this target never counts for the next one
        self.counts["touches"] += 1
        if len(c.taken) < len(c.targets):
            self._progress("")
            return
        self._solve()

    def _solve(self) -> None:
        c = self.collecting
        assert c is not None
        self.collecting, self.finished = None, (c.headset, self.clock())
        try:
            fit = fit_rigid(c.targets, np.array(c.taken), self.config.min_spread_mm / 1000.0)
        except DegenerateRegistration as exc:
            self.counts["refused"] += 1
            self._state(c.headset, "refused", f"Not registered: {exc}.")
            return
        self.last_fit = fit
        why = refusal(fit, self.config)
        rms_mm = round(fit.rms_m * 1000.0, 2)
        if why is not None:
            self.counts["refused"] += 1
            self._state(c.headset, "refused", f"Not registered: {why}.", residual_mm=rms_mm)
            return
        self.counts["registered"] += 1
        old = self.store.get(c.headset) or {}
        entry = {
            "T_world_xr": _pose_fields(fit.T_world_xr),
            "residual_mm": rms_mm,
            "points": fit.n,
            "saved_at": time.strftime("%Y-%m-%d %H:%M", time.localtime()),
            "T_viewer_rig": old.get("T_viewer_rig"),
        }
        saved = self.store.put(c.headset, entry)
        self._use(c.headset, fit.T_world_xr)
        self.offset_pairs[c.headset] = []  # a fresh touch registration: (re)calibrate offset
        self._registered(c.headset, entry, reused=False, saved=saved)

    def _use(self, headset: str, T_world_xr: Pose) -> None:
        self.active[headset] = T_world_xr
        self.drift[headset] = deque(maxlen=self.config.watch_samples)

    def _offer(self, headset: str) -> None:
        """A page says hello: its registration in use, or its saved one, or none."""
        entry = self.store.get(headset)
        if entry is None:
            self._state(headset, "none", "This headset is not registered yet.")
            return
        if headset not in self.active:
            self._use(headset, _pose_from(entry["T_world_xr"]))
        self._registered(headset, entry, reused=True, saved=True)

    def _registered(self, headset: str, entry: dict, reused: bool, saved: bool) -> None:
        T = self.active[headset]
        when = f" (saved {entry['saved_at']})" if reused else ""
        self._state(
            headset,
            "registered",
            f"Registered{when}: residual {entry['residual_mm']:.1f} mm over "
            f"{entry['points']} targets.",
            residual_mm=entry["residual_mm"],
            T_world_xr=_pose_fields(T),
            T_xr_world=_pose_fields(T.inverse()),
            reused=reused,
            saved=saved,
            watch="waiting",
        )

    # --- watching ------------------------------------------------------------------------

    def _rig_at(self, t: float) -> Pose | None:
        best = None
        for tr, pose in reversed(self.rigs):
            if abs(tr - t) <= self.config.pair_within_s and (
                best is None or abs(tr - t) < abs(best[0] - t)
            ):
                best = (tr, pose)
            if tr < t - self.config.pair_within_s:
                break
        return None if best is None else best[1]

    def _viewer_pose(self, m: ViewerPoseMessage) -> None:
        T_world_xr = self.active.get(m.headset)
        if T_world_xr is None:
            self.counts["viewer_unregistered"] += 1
            return
        T_world_rig = self._rig_at(self.clock())
        if T_world_rig is None:
            self.counts["viewer_unpaired"] += 1
            return
        viewer = Pose(np.asarray(m.position), quat_normalize(m.quaternion))
        entry = self.store.get(m.headset) or {}
        pairs = self.offset_pairs.get(m.headset)
        if pairs is not None:  # calibrating the offset after a fresh touch registration
            pairs.append((viewer, T_world_rig))
            if len(pairs) < self.config.offset_samples:
                return
            del self.offset_pairs[m.headset]
            offset = viewer_rig_offset(T_world_xr, [p[0] for p in pairs], [p[1] for p in pairs])
            entry = {**entry, "T_viewer_rig": _pose_fields(offset)}
            self.store.put(m.headset, entry)
            self.counts["offset_calibrated"] += 1
        if entry.get("T_viewer_rig") is None:
            return  # reused before any offset was calibrated: nothing to compare with
        predicted = T_world_xr @ viewer @ _pose_from(entry["T_viewer_rig"])
        dp, da = predicted.distance_to(T_world_rig)
        window = self.drift[m.headset]
        window.append((dp, da))
        self.counts["viewer_compared"] += 1
        if len(window) < window.maxlen:
            return
        mm = 1000.0 * float(np.median([w[0] for w in window]))
        deg = math.degrees(float(np.median([w[1] for w in window])))
        drifted = mm > self.config.watch_mm or deg > self.config.watch_deg
        self._watch(m.headset, "drifted" if drifted else "ok", mm, deg)

    def _watch(self, headset: str, watch: str, mm: float, deg: float) -> None:
        last = self.states.get(headset, {})
        if last.get("state") != "registered":
            return
        if watch == "drifted" and last.get("watch") != "drifted":
            self.counts["drifted"] += 1
            log.warning("follower: headset %s drifted %.0f mm %.1f deg", headset, mm, deg)
        self._send({**last, "watch": watch, "drift_mm": round(mm, 1), "drift_deg": round(deg, 2)})

    def _state(self, headset: str, state: str, message: str, **extra: Any) -> None:
        self._send({"headset": headset, "state": state, "message": message, **extra})

    def _send(self, fields: dict[str, Any]) -> None:
        self.last = fields
        self.states[fields["headset"]] = fields
        self.states.move_to_end(fields["headset"])
        while len(self.states) > STATES_KEPT:
            self.states.popitem(last=False)
        self.publish("registration", fields)

    # --- figures -------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        """For the daemon's stats: counts, the last state, the last fit's residual (mm)."""
        return {
            "state": self.last.get("state"),
            "watch": self.last.get("watch"),
            "drift_mm": self.last.get("drift_mm"),
            "residual_mm": None if self.last_fit is None else round(self.last_fit.rms_m * 1e3, 2),
            "headsets_saved": len(self.store.entries),
            "load_error": self.store.load_error,
            "save_error": self.store.save_error,
            "counts": dict(self.counts),
            "bad_messages": dict(self.bad_messages),
        }

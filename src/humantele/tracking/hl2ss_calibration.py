"""The AHAT camera's calibration as hl2ss gives it (mode 2 of port 3804), and its file.

hl2ss (``download_calibration_rm_depth_ahat`` in ``viewer/hl2ss.py``; the app's
``Channel_RM_ZHT::Execute_Mode2`` and ``ResearchMode_GetIntrinsics``) sends float32s:
uv2x, uv2y (512 x 512 each: the unit-plane point (x, y) of every raw pixel, from research
mode's ``MapImagePointToCameraUnitPlane``), the extrinsics (4 x 4, row-vector, rig -> camera:
see :func:`~humantele.tracking.hl2ss_protocol.rig_camera_from_extrinsics`), scale (1000: depth
units per metre), alias (1055: the depth wrap, mm), mapx, mapy (512 x 512 each: the raw pixel
each undistorted pixel takes, for ``cv2.remap``) and K = (fx, fy, cx, cy) of the undistorted
pinhole image.

Camera axes: hl2ss takes x = uv2x increasing with the column and y = uv2y increasing with the
row, z = 1 forward (its LUT masks pixels where x or y fall; its K has fx, fy > 0), i.e. OpenCV's
x right, y down, z forward, the convention of :mod:`humantele.tracking.camera`. So no axis
flip is needed; :meth:`Hl2ssAhatCalibration.check_axes` verifies it on the device's own data
and refuses a calibration that disagrees.

The file the clinic saves once (``humantele devices hl2ss-calibration``): a JSON (K,
extrinsics as sent, scale, alias, where from, and ``T_rig_camera`` for reading) beside a
``.maps.npz`` with the four 512 x 512 tables.
"""

from __future__ import annotations

import json
import socket
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from humantele.geometry import Pose
from humantele.tracking.camera import CameraIntrinsics
from humantele.tracking.hl2ss_protocol import (
    AHAT_HEIGHT,
    AHAT_PIXELS,
    AHAT_PORT,
    AHAT_WIDTH,
    MODE_CALIBRATION,
    AhatConfiguration,
    hl2ss_matrix_from_pose,
    rig_camera_from_extrinsics,
)

FLOAT_COUNT = 4 * AHAT_PIXELS + 16 + 1 + 1 + 4  # hl2ss's _Mode2Layout_RM_DEPTH_AHAT
CALIBRATION_BYTES = 4 * FLOAT_COUNT
FILE_KIND = "hl2ss rm_depth_ahat calibration"
SHAPE = (AHAT_HEIGHT, AHAT_WIDTH)


@dataclass
class Hl2ssAhatCalibration:
    """hl2ss's AHAT calibration (arrays float32, as sent)."""

    uv2x: NDArray[np.float32]
    uv2y: NDArray[np.float32]
    extrinsics: NDArray[np.float32]
    scale: float
    alias: float
    mapx: NDArray[np.float32]
    mapy: NDArray[np.float32]
    k: NDArray[np.float32]

    # --- wire -----------------------------------------------------------------------------
    @classmethod
    def from_bytes(cls, data: bytes) -> Hl2ssAhatCalibration:
        if len(data) != CALIBRATION_BYTES:
            raise ValueError(f"AHAT calibration is {CALIBRATION_BYTES} bytes, got {len(data)}")
        f = np.frombuffer(data, "<f4")
        p = AHAT_PIXELS
        o = 2 * p + 18
        return cls(uv2x=f[:p].reshape(SHAPE).copy(), uv2y=f[p : 2 * p].reshape(SHAPE).copy(),
                   extrinsics=f[2 * p : 2 * p + 16].reshape(4, 4).copy(),
                   scale=float(f[2 * p + 16]), alias=float(f[2 * p + 17]),
                   mapx=f[o : o + p].reshape(SHAPE).copy(),
                   mapy=f[o + p : o + 2 * p].reshape(SHAPE).copy(),
                   k=f[o + 2 * p :].copy())  # fmt: skip

    def to_bytes(self) -> bytes:
        """The bytes the app sends (the replay server's calibration)."""
        parts = [self.uv2x, self.uv2y, self.extrinsics, [self.scale], [self.alias],
                 self.mapx, self.mapy, self.k]  # fmt: skip
        return b"".join(np.asarray(a, "<f4").ravel().tobytes() for a in parts)

    @classmethod
    def pinhole(
        cls, intrinsics: CameraIntrinsics, T_rig_camera: Pose, scale: float = 1000.0,
        alias: float = 1055.0,
    ) -> Hl2ssAhatCalibration:  # fmt: skip
        """A distortion-free calibration (identity maps) of a pinhole camera at
        ``T_rig_camera``: what the replay of simulated frames serves."""
        k = intrinsics
        uu, vv = np.meshgrid(np.arange(AHAT_WIDTH, dtype=np.float32),
                             np.arange(AHAT_HEIGHT, dtype=np.float32))  # fmt: skip
        return cls(uv2x=(uu - k.cx) / k.fx, uv2y=(vv - k.cy) / k.fy,
                   extrinsics=hl2ss_matrix_from_pose(T_rig_camera.inverse()),
                   scale=scale, alias=alias, mapx=uu, mapy=vv,
                   k=np.array([k.fx, k.fy, k.cx, k.cy], np.float32))  # fmt: skip

    # --- ours -----------------------------------------------------------------------------
    def intrinsics(self) -> CameraIntrinsics:
        """The undistorted (pinhole) image's intrinsics, px."""
        fx, fy, cx, cy = (float(v) for v in self.k)
        return CameraIntrinsics(width=AHAT_WIDTH, height=AHAT_HEIGHT, fx=fx, fy=fy, cx=cx, cy=cy)

    def T_rig_camera(self) -> Pose:
        """The AHAT camera (OpenCV axes) in the rig frame."""
        return rig_camera_from_extrinsics(self.extrinsics)

    def check_axes(self) -> None:
        """ValueError unless the unit-plane tables grow with column (x) and row (y) at the
        image centre and K is positive: hl2ss's camera axes are then OpenCV's."""
        c = AHAT_WIDTH // 2
        row = self.uv2x[c, c - 20 : c + 21]
        col = self.uv2y[c - 20 : c + 21, c]
        if not (np.all(np.diff(row) > 0) and np.all(np.diff(col) > 0)):
            raise ValueError("hl2ss AHAT calibration: unit-plane x/y do not grow with column/row "
                             "(camera axes are not x right, y down)")  # fmt: skip
        if not (np.all(np.isfinite(self.k)) and self.k[0] > 0 and self.k[1] > 0):
            raise ValueError(f"hl2ss AHAT calibration: bad intrinsics K {self.k.tolist()}")
        self.T_rig_camera()  # raises when the extrinsics are not rigid

    def undistort(
        self, depth_mm: NDArray[np.uint16], ab: NDArray[np.uint16], ab_shift_px: float = 0.0
    ) -> tuple[NDArray[np.uint16], NDArray[np.uint16]]:
        """The raw images remapped to the pinhole image of :meth:`intrinsics` (depth nearest,
        AB linear, as hl2ss's ``rm_depth_undistort``/``rm_ab_undistort``; outside: 0).
        ``ab_shift_px``: AB content lies this far right of its pixels in the raw image (hl2ss
        H.26x: 0.5, each even column's value repeated over two), taken back here."""
        d = cv2.remap(depth_mm, self.mapx, self.mapy, cv2.INTER_NEAREST,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=0)  # fmt: skip
        mapx = self.mapx + np.float32(ab_shift_px) if ab_shift_px else self.mapx
        a = cv2.remap(ab, mapx, self.mapy, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=0)  # fmt: skip
        return d, a

    def is_identity_map(self) -> bool:
        uu, vv = np.meshgrid(np.arange(AHAT_WIDTH), np.arange(AHAT_HEIGHT))
        return bool(np.array_equal(self.mapx, uu) and np.array_equal(self.mapy, vv))

    # --- file -----------------------------------------------------------------------------
    def save(self, path: str | Path, source: str = "") -> Path:
        """Write ``path`` (JSON) and ``<stem>.maps.npz`` beside it; returns the maps' path."""
        path = Path(path)
        maps = path.with_suffix(".maps.npz")
        np.savez_compressed(maps, uv2x=self.uv2x, uv2y=self.uv2y, mapx=self.mapx, mapy=self.mapy)
        T = self.T_rig_camera()
        doc = {
            "kind": FILE_KIND,
            "version": 1,
            "source": source,
            "saved_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "maps_file": maps.name,
            "k_fx_fy_cx_cy": [float(v) for v in self.k],
            "extrinsics_hl2ss": [[float(v) for v in r] for r in self.extrinsics],
            "extrinsics_convention": "as hl2ss sends it: row-vector, p_camera = p_rig @ E, "
            "translation in the last row",
            "scale": self.scale,
            "alias": self.alias,
            "T_rig_camera_for_reading": {"position_m": T.position.tolist(),
                                         "quaternion_xyzw": T.quaternion.tolist()},
        }  # fmt: skip
        path.write_text(json.dumps(doc, indent=1) + "\n")
        return maps

    @classmethod
    def load(cls, path: str | Path) -> Hl2ssAhatCalibration:
        """Read a file :meth:`save` wrote; ValueError (naming the file) when it is not one."""
        path = Path(path)
        try:
            doc = json.loads(path.read_text())
            if doc.get("kind") != FILE_KIND:
                raise ValueError(f"not an {FILE_KIND} file")
            with np.load(path.parent / doc["maps_file"]) as z:
                tables = {n: np.asarray(z[n], np.float32) for n in ("uv2x", "uv2y", "mapx", "mapy")}
            if any(t.shape != SHAPE for t in tables.values()):
                raise ValueError("tables are not 512 x 512")
            E = np.asarray(doc["extrinsics_hl2ss"], np.float32).reshape(4, 4)
            k = np.asarray(doc["k_fx_fy_cx_cy"], np.float32).reshape(4)
            cal = cls(extrinsics=E, scale=float(doc["scale"]), alias=float(doc["alias"]), k=k,
                      **tables)  # fmt: skip
            cal.check_axes()
        except (OSError, KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"hl2ss calibration file {path}: {exc}") from exc
        return cal


def download_ahat_calibration(
    host: str, port: int = AHAT_PORT, timeout_s: float = 10.0
) -> Hl2ssAhatCalibration:
    """The calibration from the app (mode 2), checked; OSError/ValueError on failure."""
    with socket.create_connection((host, port), timeout=timeout_s) as sock:
        sock.settimeout(timeout_s)
        sock.sendall(AhatConfiguration(mode=MODE_CALIBRATION).pack())
        buf = bytearray()
        while len(buf) < CALIBRATION_BYTES:
            chunk = sock.recv(min(1 << 20, CALIBRATION_BYTES - len(buf)))
            if not chunk:
                raise ConnectionError(f"closed after {len(buf)} of {CALIBRATION_BYTES} bytes")
            buf.extend(chunk)
    cal = Hl2ssAhatCalibration.from_bytes(bytes(buf))
    cal.check_axes()
    return cal

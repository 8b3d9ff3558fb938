"""A VP8 encoder on libvpx itself (through ctypes), so that a running encoder changes its bit
rate and its size without being reopened.

FFmpeg's libvpx wrapper (what PyAV and aiortc use) applies ``bit_rate`` only when it opens the
encoder (of the rate-control settings it re-applies only ``qmax`` per frame, libavcodec
``libvpxenc.c`` ``vpx_encode``), so every REMB move of more than 10 % used to reopen it: a
keyframe each time (27 US and 23 POV reopenings in a 15-minute loaded session). libvpx's own
API changes a running encoder with ``vpx_codec_enc_config_set``: the target bit rate at once,
no keyframe; a smaller size (never larger than the first one, ``vp8e_set_config``) with a
keyframe, as VP8 carries the size only in keyframes. The frame rate needs no change at all:
the rate control reads each frame's duration from its timestamps.

The library is the one PyAV ships (``av.libs/libvpx*``; else the system's ``libvpx``). Only
libvpx's public ABI is used (``vpx/vpx_encoder.h``): the fields of ``vpx_codec_enc_cfg_t`` are
written at their offsets, which :func:`load` checks against ``vpx_codec_enc_config_default``'s
known values before anything is encoded; the ABI version is the library's own (found by
``vpx_codec_enc_init_ver``, which refuses any other). If anything does not match, :func:`load`
returns None and the follower keeps FFmpeg's encoder (reopened on each rate change).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import glob
import logging
import os
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

# vpx/vpx_encoder.h, vpx/vp8cx.h, vpx/vpx_image.h (libvpx 1.12-1.16: the same values)
VPX_IMG_FMT_I420 = 0x102
VPX_EFLAG_FORCE_KF = 1
VPX_FRAME_IS_KEY = 1
VPX_CODEC_CX_FRAME_PKT = 0
VPX_DL_REALTIME = 1
VPX_CBR = 1
VPX_ERROR_RESILIENT_DEFAULT = 1
VP8E_SET_CPUUSED = 13
VP8E_SET_NOISE_SENSITIVITY = 15
VP8E_SET_STATIC_THRESHOLD = 17
VP8E_SET_TOKEN_PARTITIONS = 18
VP8E_GET_LAST_QUANTIZER_64 = 20
VP8E_SET_MAX_INTRA_BITRATE_PCT = 26

# vpx_codec_enc_cfg_t field offsets (bytes; x86-64 and aarch64 alike) and its size
CFG = {
    "g_threads": 4, "g_w": 12, "g_h": 16, "g_timebase_num": 28, "g_timebase_den": 32,
    "g_error_resilient": 36, "g_pass": 40, "g_lag_in_frames": 44, "rc_dropframe_thresh": 48,
    "rc_end_usage": 72, "rc_target_bitrate": 112, "rc_min_quantizer": 116,
    "rc_max_quantizer": 120, "rc_undershoot_pct": 124, "rc_overshoot_pct": 128,
    "rc_buf_sz": 132, "rc_buf_initial_sz": 136, "rc_buf_optimal_sz": 140, "kf_mode": 160,
    "kf_min_dist": 164, "kf_max_dist": 168,
}  # fmt: skip
CFG_BYTES = 4096  # vpx_codec_enc_cfg_t is 504 bytes in libvpx 1.12; room for later fields
CTX_BYTES = 512  # vpx_codec_ctx_t: 56 bytes
IMG_BYTES = 1024  # vpx_image_t: 136 bytes
# What vpx_codec_enc_config_default gives for VP8 (vp8_cx_iface.c): checks the offsets.
DEFAULTS = {"g_w": 320, "g_h": 240, "g_timebase_num": 1, "g_timebase_den": 30,
            "rc_target_bitrate": 256, "rc_min_quantizer": 4, "rc_max_quantizer": 63,
            "rc_undershoot_pct": 100, "rc_overshoot_pct": 100, "rc_buf_sz": 6000,
            "rc_buf_initial_sz": 4000, "rc_buf_optimal_sz": 5000, "kf_max_dist": 128}  # fmt: skip


class _CxFrame(ctypes.Structure):
    """``vpx_codec_cx_pkt_t`` up to the frame's flags."""

    _fields_ = [
        ("kind", ctypes.c_int),
        ("buf", ctypes.c_void_p),
        ("sz", ctypes.c_size_t),
        ("pts", ctypes.c_int64),
        ("duration", ctypes.c_ulong),
        ("flags", ctypes.c_uint32),
    ]


class LibVpx:
    """The loaded library, its VP8 encoder interface and ABI version."""

    def __init__(self, lib: ctypes.CDLL, abi: int) -> None:
        self.lib = lib
        self.abi = abi
        self.iface = lib.vpx_codec_vp8_cx()
        lib.vpx_codec_version_str.restype = ctypes.c_char_p
        self.version = lib.vpx_codec_version_str().decode()


def _library_paths() -> list[str]:
    paths = []
    try:
        import av

        here = os.path.dirname(av.__file__)
        paths += sorted(glob.glob(os.path.join(here, "..", "av.libs", "libvpx*.so*")))
    except Exception:  # noqa: BLE001 - PyAV without bundled libraries
        pass
    system = ctypes.util.find_library("vpx")
    if system:
        paths.append(system)
    return paths


def _declare(lib: ctypes.CDLL) -> None:
    vp, ci, cu = ctypes.c_void_p, ctypes.c_int, ctypes.c_uint
    lib.vpx_codec_vp8_cx.restype = vp
    lib.vpx_codec_vp8_cx.argtypes = []
    lib.vpx_codec_enc_config_default.argtypes = [vp, vp, cu]
    lib.vpx_codec_enc_config_default.restype = ci
    lib.vpx_codec_enc_init_ver.argtypes = [vp, vp, vp, ctypes.c_long, ci]
    lib.vpx_codec_enc_init_ver.restype = ci
    lib.vpx_codec_enc_config_set.argtypes = [vp, vp]
    lib.vpx_codec_enc_config_set.restype = ci
    lib.vpx_codec_encode.argtypes = [vp, vp, ctypes.c_int64, ctypes.c_ulong, ctypes.c_long,
                                     ctypes.c_ulong]  # fmt: skip
    lib.vpx_codec_encode.restype = ci
    lib.vpx_codec_get_cx_data.argtypes = [vp, ctypes.POINTER(vp)]
    lib.vpx_codec_get_cx_data.restype = ctypes.POINTER(_CxFrame)
    lib.vpx_codec_destroy.argtypes = [vp]
    lib.vpx_codec_destroy.restype = ci
    lib.vpx_img_wrap.argtypes = [vp, ci, cu, cu, cu, vp]
    lib.vpx_img_wrap.restype = vp
    lib.vpx_codec_error_detail.argtypes = [vp]
    lib.vpx_codec_error_detail.restype = ctypes.c_char_p
    lib.vpx_codec_control_.restype = ci  # variadic: (ctx, id, int)


_LOADED: list[LibVpx | None] = []


def load() -> LibVpx | None:
    """libvpx with its layout checked (once per process), or None (logged once)."""
    if _LOADED:
        return _LOADED[0]
    found = None
    for path in _library_paths():
        try:
            lib = ctypes.CDLL(path)
            _declare(lib)
            cfg = default_config(lib, lib.vpx_codec_vp8_cx())
            wrong = {k: get(cfg, k) for k, v in DEFAULTS.items() if get(cfg, k) != v}
            if wrong:
                log.warning("libvpx at %s: unexpected config layout %s", path, wrong)
                continue
            abi = _find_abi(lib, cfg)
            if abi is not None:
                found = LibVpx(lib, abi)
                break
        except (OSError, AttributeError) as exc:
            log.debug("libvpx at %s: %s", path, exc)
    if found is None:
        log.warning("libvpx not usable: VP8 bit-rate changes reopen the encoder (a keyframe)")
    _LOADED.append(found)
    return found


def default_config(lib: ctypes.CDLL, iface: int) -> ctypes.Array:
    cfg = ctypes.create_string_buffer(CFG_BYTES)
    if lib.vpx_codec_enc_config_default(iface, cfg, 0) != 0:
        raise OSError("vpx_codec_enc_config_default failed")
    return cfg


def get(cfg: ctypes.Array, name: str) -> int:
    return ctypes.c_uint.from_buffer(cfg, CFG[name]).value


def put(cfg: ctypes.Array, name: str, value: int) -> None:
    ctypes.c_uint.from_buffer(cfg, CFG[name]).value = int(value)


def _find_abi(lib: ctypes.CDLL, cfg: ctypes.Array) -> int | None:
    """The encoder ABI version the library was built with: init refuses any other
    (VPX_CODEC_ABI_MISMATCH) before it allocates anything."""
    iface = lib.vpx_codec_vp8_cx()
    for abi in range(20, 60):
        ctx = ctypes.create_string_buffer(CTX_BYTES)
        if lib.vpx_codec_enc_init_ver(ctx, iface, cfg, 0, abi) == 0:
            lib.vpx_codec_destroy(ctx)
            return abi
    return None


class LiveVp8:
    """One running libvpx VP8 encoder (real time, constant bit rate, one pass, no lag) whose
    bit rate (:meth:`set_bitrate`) and size (:meth:`set_size`) change without reopening it.

    ``options``: ``cpu_used``, ``noise_sensitivity``, ``static_thresh``, ``partitions``,
    ``max_intra_pct`` (a keyframe's size cap, % of a frame's average budget; 0: none),
    ``error_resilient`` (bool), ``qmin``, ``qmax``, ``undershoot_pct``, ``overshoot_pct``,
    ``buf_ms`` (the rate buffer, ms). Encodes I420 frames with 90 kHz timestamps."""

    def __init__(self, vpx: LibVpx, width: int, height: int, kbps: int, threads: int,
                 options: dict[str, Any]) -> None:  # fmt: skip
        self.vpx = vpx
        lib = vpx.lib
        cfg = default_config(lib, vpx.iface)
        put(cfg, "g_w", width)
        put(cfg, "g_h", height)
        put(cfg, "g_threads", threads)
        put(cfg, "g_timebase_num", 1)
        put(cfg, "g_timebase_den", 90_000)
        put(cfg, "g_lag_in_frames", 0)
        put(cfg, "g_error_resilient", VPX_ERROR_RESILIENT_DEFAULT if options.get(
            "error_resilient") else 0)  # fmt: skip
        put(cfg, "rc_dropframe_thresh", 0)
        put(cfg, "rc_end_usage", VPX_CBR)
        put(cfg, "rc_target_bitrate", kbps)
        put(cfg, "rc_min_quantizer", options.get("qmin", 2))
        put(cfg, "rc_max_quantizer", options.get("qmax", 56))
        put(cfg, "rc_undershoot_pct", options.get("undershoot_pct", 100))
        put(cfg, "rc_overshoot_pct", options.get("overshoot_pct", 15))
        buf = int(options.get("buf_ms", 1000))
        put(cfg, "rc_buf_sz", buf)
        put(cfg, "rc_buf_initial_sz", buf // 2)
        put(cfg, "rc_buf_optimal_sz", buf * 6 // 10)
        put(cfg, "kf_mode", 0)  # VPX_KF_DISABLED: keyframes only when asked or resized
        put(cfg, "kf_max_dist", 0x7FFFFFFF)
        self._cfg = cfg
        self._ctx = ctypes.create_string_buffer(CTX_BYTES)
        if lib.vpx_codec_enc_init_ver(self._ctx, vpx.iface, cfg, 0, vpx.abi) != 0:
            raise RuntimeError(f"libvpx VP8 init failed: {self._detail()}")
        self._open = True
        for ctrl, value in (
            (VP8E_SET_CPUUSED, options.get("cpu_used", -6)),
            (VP8E_SET_NOISE_SENSITIVITY, options.get("noise_sensitivity", 0)),
            (VP8E_SET_STATIC_THRESHOLD, options.get("static_thresh", 0)),
            (VP8E_SET_TOKEN_PARTITIONS, options.get("partitions", 0)),
            (VP8E_SET_MAX_INTRA_BITRATE_PCT, options.get("max_intra_pct", 0)),
        ):
            lib.vpx_codec_control_(self._ctx, ctypes.c_int(ctrl), ctypes.c_int(int(value)))
        self.initial = (width, height)
        self.width, self.height, self.kbps = width, height, kbps
        self._img = ctypes.create_string_buffer(IMG_BYTES)
        self._key_next = True

    def _detail(self) -> str:
        detail = self.vpx.lib.vpx_codec_error_detail(self._ctx)
        return detail.decode(errors="replace") if detail else "no detail"

    def _apply(self) -> None:
        if self.vpx.lib.vpx_codec_enc_config_set(self._ctx, self._cfg) != 0:
            raise RuntimeError(f"libvpx VP8 reconfiguration failed: {self._detail()}")

    def set_bitrate(self, kbps: int) -> None:
        """The target bit rate (kbit/s) from the next frame on; no keyframe."""
        kbps = max(1, int(kbps))
        if kbps != self.kbps:
            put(self._cfg, "rc_target_bitrate", kbps)
            self._apply()
            self.kbps = kbps

    def set_min_quantizer(self, q: int) -> None:
        """The rate control's best quantizer (0-63) from the next frame on; no keyframe."""
        q = max(0, min(63, int(q)))
        if q != get(self._cfg, "rc_min_quantizer"):
            put(self._cfg, "rc_min_quantizer", q)
            self._apply()

    def last_quantizer(self) -> int:
        """The quantizer (0-63) of the last frame encoded."""
        q = ctypes.c_int(0)
        self.vpx.lib.vpx_codec_control_(self._ctx, ctypes.c_int(VP8E_GET_LAST_QUANTIZER_64),
                                        ctypes.byref(q))  # fmt: skip
        return int(q.value)

    def fits(self, width: int, height: int) -> bool:
        """A frame of this size can be encoded without reopening (not larger than the first)."""
        return width <= self.initial[0] and height <= self.initial[1]

    def set_size(self, width: int, height: int) -> None:
        """Encode frames of this size from now on (at most the first size); the next frame is
        a keyframe (VP8 carries the size only in keyframes)."""
        if (width, height) != (self.width, self.height):
            put(self._cfg, "g_w", width)
            put(self._cfg, "g_h", height)
            self._apply()
            self.width, self.height = width, height
            self._key_next = True

    def encode(self, i420: np.ndarray, pts: int, duration: int, keyframe: bool = False
               ) -> tuple[bytes, bool]:  # fmt: skip
        """One frame: ``i420`` (H*3/2, W) uint8 at the current size, ``pts`` and ``duration``
        in 90 kHz ticks. Returns (the VP8 frame, whether it is a keyframe)."""
        lib = self.vpx.lib
        h, w = i420.shape[0] * 2 // 3, i420.shape[1]
        if (w, h) != (self.width, self.height) or not i420.flags.c_contiguous:
            raise ValueError(f"frame {w}x{h} for an encoder at {self.width}x{self.height}")
        lib.vpx_img_wrap(self._img, VPX_IMG_FMT_I420, w, h, 1, i420.ctypes.data)
        flags = VPX_EFLAG_FORCE_KF if (keyframe or self._key_next) else 0
        res = lib.vpx_codec_encode(self._ctx, self._img, int(pts), max(1, int(duration)),
                                   flags, VPX_DL_REALTIME)  # fmt: skip
        if res != 0:
            raise RuntimeError(f"libvpx VP8 encode failed: {self._detail()}")
        self._key_next = False
        chunks, key = [], False
        it = ctypes.c_void_p(None)
        while True:
            pkt = lib.vpx_codec_get_cx_data(self._ctx, ctypes.byref(it))
            if not pkt:
                break
            p = pkt.contents
            if p.kind == VPX_CODEC_CX_FRAME_PKT:
                chunks.append(ctypes.string_at(p.buf, p.sz))
                key = key or bool(p.flags & VPX_FRAME_IS_KEY)
        return b"".join(chunks), key

    def close(self) -> None:
        if self._open:
            self.vpx.lib.vpx_codec_destroy(self._ctx)
            self._open = False

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass

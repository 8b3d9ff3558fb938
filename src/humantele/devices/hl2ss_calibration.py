"""``humantele devices hl2ss-calibration``: save the HoloLens 2 AHAT camera's calibration once.

Downloads hl2ss's AHAT calibration (mode 2 of port 3804: intrinsics, undistortion maps and
the extrinsics of the camera in the rig) and writes it as a JSON file plus ``.maps.npz``
beside it, which the ``hl2ss`` tracker backend reads with ``calibration_file`` instead of
downloading it at every start:

    humantele devices hl2ss-calibration --host 192.168.1.7 --out hl2ss_ahat.json
"""

from __future__ import annotations

import argparse

from humantele.tracking.hl2ss_protocol import AHAT_PORT


def add_parser(sub: argparse._SubParsersAction) -> None:
    what = "download the HoloLens 2 AHAT calibration from hl2ss into a file"
    p = sub.add_parser("hl2ss-calibration", help=what, description=what)
    p.add_argument("--host", required=True, help="the headset's address")
    p.add_argument("--port", type=int, default=AHAT_PORT, help="hl2ss AHAT port (3804)")
    p.add_argument("--out", required=True, help="JSON file to write (maps go beside it)")
    p.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the data")


def run(args: argparse.Namespace) -> int:
    from humantele.tracking.hl2ss_calibration import download_ahat_calibration

    try:
        cal = download_ahat_calibration(args.host, args.port, args.timeout)
    except (OSError, ValueError) as exc:
        print(f"hl2ss-calibration: no calibration from {args.host}:{args.port} ({exc}); is the "
              "hl2ss app running on the headset, and research mode enabled?")  # fmt: skip
        return 1
    maps = cal.save(args.out, source=f"hl2ss {args.host}:{args.port}")
    T = cal.T_rig_camera()
    k = cal.intrinsics()
    print(f"saved {args.out} and {maps}: fx {k.fx:.2f} fy {k.fy:.2f} cx {k.cx:.2f} cy "
          f"{k.cy:.2f} px; AHAT camera at {[round(float(v), 4) for v in T.position]} m in the "
          "rig")  # fmt: skip
    return 0

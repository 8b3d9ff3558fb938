"""The prompted encoder reset for OpenHaptics devices calibrated that way
(HD_CALIBRATION_ENCODER_RESET; not the Touch X, which calibrates in its inkwell by itself):

    python -m humantele.haptics.devices.touchx_reset [--library libHD.so] [--device-name NAME]

As OpenHaptics' Calibration example: before the scheduler starts, the user is asked to hold the
arm at its reset pose, then ``hdUpdateCalibration(HD_CALIBRATION_ENCODER_RESET)``. The servo
never does this by itself (:mod:`humantele.haptics.devices.touchx`): an encoder reset zeroes
the encoders wherever the arm happens to be.
"""

from __future__ import annotations

import argparse
import ctypes
import sys
from collections.abc import Callable

from humantele.haptics.devices.base import DeviceError
from humantele.haptics.devices.touchx import TouchXConfig
from humantele.haptics.devices.touchx_hd import (
    CALIBRATION_NAMES,
    HD_CALIBRATION_ENCODER_RESET,
    HD_CALIBRATION_STYLE,
    HD_INVALID_HANDLE,
    HD_SUCCESS,
    STYLE_NAMES,
    describe_hd_error,
    gtdd_home_problem,
    load_hd_library,
)


def reset_encoders(config: TouchXConfig, confirm: Callable[[str], bool]) -> str:
    """Calibrate a device whose style is HD_CALIBRATION_ENCODER_RESET, as OpenHaptics'
    Calibration example: before the scheduler starts, ask the user (``confirm(prompt)``) to hold
    the arm at its reset pose, then ``hdUpdateCalibration(HD_CALIBRATION_ENCODER_RESET)``. Run
    it with the servo (and any other program on the device) stopped. Returns what was done;
    DeviceError when the device cannot, or the user declined."""
    lib = load_hd_library(config.library)
    name = config.device_name.encode() if config.device_name else None
    hhd = lib.hdInitDevice(name)
    err = lib.hdGetError()
    if hhd == HD_INVALID_HANDLE or err.errorCode != HD_SUCCESS:
        gtdd = gtdd_home_problem()
        raise DeviceError(
            f"touchx: cannot open the device: "
            f"{describe_hd_error(err.errorCode, err.internalErrorCode)}"
            + (f"; {gtdd}" if gtdd else "")
        )
    try:
        styles = ctypes.c_int(0)
        lib.hdGetIntegerv(HD_CALIBRATION_STYLE, ctypes.byref(styles))
        if not styles.value & HD_CALIBRATION_ENCODER_RESET:
            have = [n for s, n in STYLE_NAMES.items() if styles.value & s] or ["none"]
            raise DeviceError(
                f"touchx: this device has no encoder reset (its calibration: {', '.join(have)}); "
                "the servo calibrates it by itself (inkwell: put the stylus in the inkwell)"
            )
        if not confirm(
            "Hold the arm at its reset pose (for PHANTOM devices: all links orthogonal; see the "
            "device's manual) and keep it still. Reset the encoders now?"
        ):
            raise DeviceError("touchx: encoder reset cancelled; nothing changed")
        lib.hdUpdateCalibration(HD_CALIBRATION_ENCODER_RESET)
        err = lib.hdGetError()
        if err.errorCode != HD_SUCCESS:
            raise DeviceError(
                "touchx: encoder reset failed: "
                f"{describe_hd_error(err.errorCode, err.internalErrorCode)}"
            )
        status = lib.hdCheckCalibration()
        return f"encoders reset; calibration {CALIBRATION_NAMES.get(status, hex(status))}"
    finally:
        lib.hdDisableDevice(hhd)
        lib.hdGetError()


def main(argv: list[str] | None = None) -> int:
    """The command line: prompt, reset, print what was done (exit 1 with the reason if not)."""
    ap = argparse.ArgumentParser(prog="python -m humantele.haptics.devices.touchx_reset")
    ap.add_argument("--library", default="libHD.so", help="path or name of libHD.so")
    ap.add_argument("--device-name", default="", help="the name set in Touch_Setup")
    args = ap.parse_args(argv)

    def confirm(prompt: str) -> bool:
        return input(prompt + " [y/N] ").strip().lower() in ("y", "yes")

    try:
        print(reset_encoders(TouchXConfig(library=args.library, device_name=args.device_name),
                             confirm))  # fmt: skip
    except DeviceError as exc:
        print(exc, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

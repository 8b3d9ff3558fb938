"""What the servo tests share: a sim hand that presses and holds, and a condition wait."""

import time

from humantele.haptics.devices.sim import SimDeviceConfig, SimHandConfig
from humantele.haptics.servo_config import ServoConfig


def wait_for(pred, timeout=10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(0.01)
    raise AssertionError("condition not reached in time")


def pressing_config(**kw) -> ServoConfig:
    hand = SimHandConfig(path="hold", hold_target_m=(0.0, -0.05, 0.0), tremor_n=0.0)
    return ServoConfig(device=SimDeviceConfig(hand=hand, **kw), realtime_priority=0)

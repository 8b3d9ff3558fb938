"""What the servo tests share: a sim hand that presses and holds, and a condition wait."""

from humantele.haptics.devices.sim import SimDeviceConfig, SimHandConfig
from humantele.haptics.servo_config import ServoConfig


def pressing_config(**kw) -> ServoConfig:
    hand = SimHandConfig(path="hold", hold_target_m=(0.0, -0.05, 0.0), tremor_n=0.0)
    return ServoConfig(device=SimDeviceConfig(hand=hand, **kw), realtime_priority=0)

"""Doubles for the daemons' in-process tests (tests/expert, tests/follower): a link, the
servo process and a clock, each behaving like the real one where the daemon looks."""

from types import SimpleNamespace

import numpy as np

from humantele.geometry import Pose
from humantele.haptics.servo_layout import ServoSample


class LinkDouble:
    """Stands in for :class:`humantele.transport.PeerLink`: connected, keeps what is sent;
    every message is ``age_s`` old."""

    def __init__(self, age_s: float = 0.0):
        self.connected = True
        self.state = "connected"
        self.age_s = age_s
        self.poses, self.states, self.controls = [], [], []
        self.clock = SimpleNamespace(best=None)
        self.counters = SimpleNamespace(connections=1, sent={}, dropped={})

    def send_pose(self, msg):
        self.poses.append(msg)
        return True

    def send_state(self, msg):
        self.states.append(msg)
        return True

    def send_control(self, msg):
        self.controls.append(msg)
        return True

    def age_of(self, t):
        return self.age_s


class ServoDouble:
    """Stands in for the servo process: the stylus at ``p_device`` (device frame, rest
    orientation), mapped with the registration the daemon gave it like the servo does; a force
    that grows with the tick (0.1 N/s along y)."""

    def __init__(self):
        self.model = None
        self.models = []
        self.reg = (Pose.identity(), 1.0)
        self.p_device = np.zeros(3)
        self.buttons = 0
        self.t = 0.0
        self.alive = True
        self.pid = None
        self.late_ticks = 0
        self.down = ""  # the SupervisedServo's supervision: never down here
        self.cannot_run = ""
        self.restarts = 0
        self.stopped = False

    def check(self, t):
        pass

    def state(self, latest):
        return "stopped" if self.stopped else "running"

    def cpu_percent(self):
        return None

    async def stop(self):
        self.stopped = True

    def set_model(self, model):
        self.model = model
        self.models.append(model)

    def set_registration(self, T, scale):
        self.reg = (T, scale)

    def latest(self):
        T, s = self.reg
        self.t += 0.01
        stylus = Pose(self.p_device, (0.0, 0.0, 0.0, 1.0))
        patient = Pose(T.apply(s * self.p_device), T.quaternion)
        force = (0.0, 0.1 * self.t, 0.0)
        return ServoSample(
            t=self.t,
            T_device_stylus=stylus,
            T_patient_stylus=patient,
            velocity=(0.0, 0.0, 0.0),
            force=force,
            force_device=force,
            depth=0.001,
            buttons=self.buttons,
            fault_flags=0,
            tick=1,
            ramp=1.0,
        )

    def stats(self):
        st = SimpleNamespace(ticks=100, rate_hz=999.5, period_p99_us=1040.0,
                             late_ticks=self.late_ticks)  # fmt: skip
        st.as_dict = lambda: dict(st.__dict__)
        return st


class Clock:
    """A clock (s) the test sets: ``clock.t = 1.5``."""

    def __init__(self, t: float = 0.0):
        self.t = t

    def __call__(self):
        return self.t

import math

import numpy as np

from humantele.follower.sim_human import (
    SimHuman,
    SimHumanConfig,
    SimPatient,
    probe_down_quat,
    quat_slerp,
)
from humantele.geometry import Pose, quat_from_axis_angle, rotation_angle

Q0 = np.array([0.0, 0.0, 0.0, 1.0])


def track(config, f_hz=0.5, amp=0.05, duration=8.0, rate=100.0):
    human = SimHuman(config)
    ts, xs, ys = [], [], []
    for i in range(int(duration * rate)):
        t = i / rate
        x = amp * math.sin(2 * math.pi * f_hz * t)
        out = human.step(t, Pose([x, 1.0, 0.0], Q0))
        ts.append(t)
        xs.append(x)
        ys.append(out.position[0] if out is not None else 0.0)
    return np.array(ts), np.array(xs), np.array(ys)


def test_lag_is_that_of_a_novice():
    cfg = SimHumanConfig(offset_mm=(0, 0, 0), tremor_mm_rms=0.0)
    _, x, y = track(cfg)
    x, y = x[200:], y[200:]  # after the start
    lags = np.arange(0, 80)
    err = [np.mean((y[k:] - x[: len(x) - k]) ** 2) for k in lags]
    lag_s = lags[int(np.argmin(err))] / 100.0
    assert 0.28 <= lag_s <= 0.42  # 0.35 s: C&G 2024, Table 3 (docs/references.md)


def test_static_error_is_the_offset_plus_tremor():
    cfg = SimHumanConfig(offset_mm=(3, -2, 3.5), tremor_mm_rms=0.8, seed=3)
    human = SimHuman(cfg)
    target = Pose([0.1, 1.0, 0.2], probe_down_quat([0, 1, 0]))
    pos_err, ang_err = [], []
    for i in range(1000):
        out = human.step(i / 100.0, target)
        if i > 100:
            d = out.position - target.position
            pos_err.append(d)
            ang_err.append(rotation_angle(out.quaternion, target.quaternion))
    pos_err = np.array(pos_err)
    assert np.allclose(pos_err.mean(axis=0), [0.003, -0.002, 0.0035], atol=0.0006)
    tremor_rms = pos_err.std(axis=0)
    assert np.all((tremor_rms > 0.0004) & (tremor_rms < 0.0016))
    assert math.radians(3) < np.mean(ang_err) < math.radians(7)
    # The tremor is around 9 Hz, not white noise: most power between 5 and 15 Hz.
    spec = np.abs(np.fft.rfft(pos_err[:, 0] - pos_err[:, 0].mean())) ** 2
    f = np.fft.rfftfreq(len(pos_err), 0.01)
    band = (f > 5) & (f < 15)
    assert spec[band].sum() > 0.6 * spec.sum()


def test_no_target_no_pose_and_stale_target_holds():
    human = SimHuman()
    assert human.step(0.0, None) is None
    human.step(0.1, Pose([0, 1, 0], Q0))
    assert human.step(0.15, None) is None  # still within the reaction delay
    outs = [human.step(0.2 + i * 0.01, None) for i in range(100)]
    assert np.linalg.norm(outs[-1].position - [0.003, 0.998, 0.0035]) < 0.005


def test_patient_pushes_back_along_the_normal_and_person_limits_push():
    patient = SimPatient()
    lm = patient.landmarks()
    top = lm["xiphoid"]
    assert np.linalg.norm(patient.force(top + [0, 0.01, 0])) == 0.0
    f = patient.force(top - [0, 0.01, 0])
    assert f[1] > 0 and abs(np.linalg.norm(f) - 6.0) < 0.5  # 600 N/m x 10 mm
    human = SimHuman(SimHumanConfig(tremor_mm_rms=0, offset_mm=(0, 0, 0)), patient)
    deep = Pose(top - [0, 0.2, 0], probe_down_quat([0, 1, 0]))
    for i in range(300):
        out = human.step(i / 100.0, deep)
    assert np.linalg.norm(patient.force(out.position)) <= 30.0 + 1e-9
    assert np.linalg.norm(patient.force(lm["bed"] - [0, 0.002, 0])) > 5.0


def test_slerp_and_probe_orientation():
    q1 = quat_from_axis_angle([0, 0, 1], 1.0)
    assert rotation_angle(quat_slerp(Q0, q1, 0.25), quat_from_axis_angle([0, 0, 1], 0.25)) < 1e-9
    q = probe_down_quat([0, 1, 0])
    assert np.allclose(Pose([0, 0, 0], q).rotate([0, 0, 1]), [0, -1, 0])

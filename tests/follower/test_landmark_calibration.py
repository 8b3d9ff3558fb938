import json
import math

import numpy as np
import pytest

from humantele.config import ConfigError, validate_config
from humantele.follower.calibration import (
    Calibration,
    CalibrationConfig,
    Calibrator,
    build_calibration,
)
from humantele.follower.sim_human import CalibrationScript, SimHuman, SimPatient
from humantele.geometry import Pose, rotation_angle


def run_sim_calibration(seed=0, rate=100.0):
    patient = SimPatient()
    human = SimHuman(patient=patient)
    script = CalibrationScript(patient)
    cal = Calibrator()
    events = []
    t, t0 = 0.0, 0.0
    while t < script.duration_s + 1.0 and cal.step is not None:
        target = script.target(cal.step, t - t0)
        if target is None:  # this press is over: the next one (or the same again)
            t0 = t
            target = script.target(cal.step, 0.0)
        tip = human.step(t, target)
        if tip is not None:
            ev = cal.update(tip.position, float(np.linalg.norm(patient.force(tip.position))))
            if ev is not None:
                events.append(ev)
        t += 1.0 / rate
    return patient, cal, events


def test_sim_presses_give_four_landmarks_and_a_good_fit():
    patient, cal, events = run_sim_calibration()
    assert [e.kind for e in events] == ["taken", "taken", "taken", "done"]
    assert [e.landmark for e in events] == ["xiphoid", "left", "right", "bed"]
    assert cal.presses == 4 and cal.refusals == 0
    truth = patient.landmarks()
    for name, point in cal.taken.items():
        # The landmark is where the force crossed the threshold: within a press depth + offset.
        assert np.linalg.norm(point - truth[name]) < 0.02, name
    res = cal.result
    assert res is not None
    c = patient.config
    _, b, a = res.ellipsoid.semi_axes
    assert abs(a - c.half_width_m) < 0.015
    assert abs(b - c.half_height_m) < 0.01
    # Patient frame: y up, z from left to right; the sim patient is yawed about y.
    assert (
        abs(
            math.degrees(
                rotation_angle(res.T_world_patient.quaternion, patient.T_world_body.quaternion)
            )
        )
        < 3.0
    )
    assert np.linalg.norm(res.ellipsoid.center - patient.T_world_body.position) < 0.015
    # The model the expert gets is the same ellipsoid in the patient frame.
    top_world = res.T_world_patient.apply([0.0, b, 0.0])
    assert res.model_patient().penetration([0.0, b - 0.01, 0.0])[0] == pytest.approx(0.01)
    assert res.ellipsoid.penetration(top_world - [0, 0.01, 0])[0] == pytest.approx(0.01)


def test_one_press_gives_one_landmark_despite_chatter():
    cal = Calibrator(CalibrationConfig(force_on_n=5.0, force_off_n=2.0))
    tip = np.array([0.0, 1.0, 0.0])
    kinds = [cal.update(tip, f) for f in [0, 6, 4, 6, 3, 7, 2.5, 6, 1.0]]
    assert sum(k is not None for k in kinds) == 1
    assert list(cal.taken) == ["xiphoid"] and cal.presses == 1
    # After release below force_off_n, the next press gives the next landmark.
    ev = cal.update(tip + [0, -0.1, 0.15], 6.0)
    assert ev is not None and ev.landmark == "left" and ev.kind == "taken"


def test_landmark_waits_for_tracking_during_the_press():
    cal = Calibrator()
    assert cal.update(None, 8.0) is None  # crossed, but probe not tracked
    ev = cal.update([0.1, 1.0, 0.2], 8.0)
    assert ev is not None and ev.kind == "taken"
    assert cal.update([0.1, 1.0, 0.2], 9.0) is None  # same press
    assert cal.update([0.1, 1.0, 0.2], float("nan")) is None


def press(cal, point):
    cal.update(point, 0.0)
    ev = cal.update(point, 10.0)
    cal.update(point, 0.0)
    return ev


def test_implausible_landmarks_refused_with_actionable_message():
    cal = Calibrator()
    assert press(cal, [0.0, 1.0, 0.0]).kind == "taken"
    assert press(cal, [0.0, 0.9, -0.15]).kind == "taken"
    ev = press(cal, [0.02, 0.9, -0.16])  # on the left again
    assert ev.kind == "refused" and ev.message.startswith("press again on the right side")
    assert cal.step == "right" and cal.refusals == 1
    ev = press(cal, [0.0, 0.9, 0.03])  # too close to the xiphoid
    assert ev.kind == "refused" and "right side" in ev.message and "mm" in ev.message
    assert press(cal, [0.0, 0.9, 0.15]).kind == "taken"
    ev = press(cal, [0.0, 1.05, 0.3])  # "bed" above the xiphoid
    assert ev.kind == "refused" and ev.message.startswith("press again on the bed")
    ev = press(cal, [0.0, 0.78, 0.3])
    assert ev.kind == "done" and cal.step is None and cal.refusals == 3
    assert cal.result.ellipsoid.semi_axes[2] == pytest.approx(0.15)
    assert cal.result.ellipsoid.semi_axes[1] == pytest.approx(0.11)


def test_side_landmark_above_xiphoid_refused():
    cal = Calibrator()
    press(cal, [0.0, 1.0, 0.0])
    ev = press(cal, [0.0, 1.2, -0.15])
    assert ev.kind == "refused" and "left side" in ev.message and "above the xiphoid" in ev.message


def test_saved_and_reloaded(tmp_path):
    lm = {
        "xiphoid": [0.1, 1.0, 0.0],
        "left": [0.1, 0.9, -0.15],
        "right": [0.12, 0.9, 0.15],
        "bed": [0.0, 0.78, 0.3],
    }
    cal = build_calibration(lm, CalibrationConfig())
    path = cal.save(tmp_path / "state" / "calibration.json")
    back = Calibration.load(path)
    assert back is not None
    assert back.ellipsoid == cal.ellipsoid
    assert back.T_world_patient.distance_to(cal.T_world_patient)[0] < 1e-12
    # Landmarks map into the patient frame with the ellipsoid's top at the xiphoid.
    lp = back.landmarks_patient()
    b = back.ellipsoid.semi_axes[1]
    assert lp["xiphoid"][1] == pytest.approx(b)
    assert lp["bed"][1] == pytest.approx(-b)
    assert lp["left"][2] < 0 < lp["right"][2]


def test_corrupt_or_missing_calibration_is_none(tmp_path):
    assert Calibration.load(tmp_path / "none.json") is None
    f = tmp_path / "c.json"
    f.write_text("{not json")
    assert Calibration.load(f) is None
    f.write_text(json.dumps({"version": 1, "landmarks_world": {}}))
    assert Calibration.load(f) is None
    good = build_calibration(
        {
            "xiphoid": [0, 1, 0],
            "left": [0, 0.9, -0.15],
            "right": [0, 0.9, 0.15],
            "bed": [0, 0.78, 0.3],
        },
        CalibrationConfig(),
    ).to_dict()
    good["ellipsoid_world"]["semi_axes"][2] = -1.0
    f.write_text(json.dumps(good))
    assert Calibration.load(f) is None


def test_config_needs_hysteresis():
    with pytest.raises(ConfigError, match="force_off_n must be below force_on_n"):
        validate_config(CalibrationConfig, {"force_on_n": 3.0, "force_off_n": 3.0})
    assert Pose.identity() is not None


def test_fit_blames_a_landmark_and_asks_for_it_again():
    # The left landmark is a little below the bed: plausible alone, but the fit refuses it.
    cal = Calibrator()
    assert press(cal, [0.0, 1.0, 0.0]).kind == "taken"
    assert press(cal, [0.0, 0.8, -0.15]).kind == "taken"
    assert press(cal, [0.0, 0.9, 0.15]).kind == "taken"
    ev = press(cal, [0.0, 0.82, 0.3])
    assert ev.kind == "refused" and ev.message.startswith("press again on the left side")
    assert "above the bed" in ev.message
    assert cal.step == "left" and cal.result is None and "bed" in cal.taken
    ev = press(cal, [0.0, 0.9, -0.15])
    assert ev.kind == "done" and cal.result is not None

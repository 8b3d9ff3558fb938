"""analyze recovers the error injected into a simulated session (see recording.synthetic)."""

from __future__ import annotations

import numpy as np
import pytest

from humantele.analysis.sessions import analyze_scans, load_sessions
from humantele.recording.synthetic import SyntheticSession, write_synthetic

A_MM, THETA_DEG, F_HZ = 30.0, 15.0, 0.25
# The virtual probe at 200 Hz, not the servo's 1 kHz (a fifth of the samples to write): the
# analysis interpolates it at the tracker's 45 Hz frames, off a 0.25 Hz sine by at most
# A w^2 h^2 / 8 = 2e-4 mm and 1e-4 deg (h = 5 ms), a hundredth of the tightest tolerance here.
EXPERT_RATE_HZ = 200.0


def _analyze(tmp_path, name, **kw):
    cfg = SyntheticSession(
        **{
            "duration_s": 22.0,
            "trajectory": "sine",
            "amplitude_mm": A_MM,
            "rotation_amplitude_deg": THETA_DEG,
            "frequency_hz": F_HZ,
            "expert_rate_hz": EXPERT_RATE_HZ,
            **kw,
        }
    )
    path = tmp_path / f"{name}.mcap"
    truth = write_synthetic(path, cfg)
    (session,) = load_sessions([path])
    return analyze_scans(session), session, truth


def test_constant_offset_is_recovered_and_centering_removes_it(tmp_path):
    offset = np.array([10.0, -5.0, 3.0])
    results, session, _ = _analyze(
        tmp_path,
        "offset",
        offset_mm=tuple(offset),
        rotation_offset_deg=(0.0, 0.0, 4.0),
        dropout=0.2,
        clock_offset_s=2.5,
        clock_drift_ppm=80.0,
    )
    (r,) = results
    d = r.as_dict()
    assert d["position_rmse_mm"] == pytest.approx(np.linalg.norm(offset), abs=0.02)
    np.testing.assert_allclose(d["mean_position_error_mm"], offset, atol=0.02)
    assert d["centered_position_rmse_mm"] < 0.02
    assert d["orientation_rmse_deg"] == pytest.approx(4.0, abs=0.01)
    assert d["centered_orientation_rmse_deg"] < 0.01
    # the lost frames (pose left at zero) were skipped, not averaged in
    assert r.frames_tracked < 0.9 * r.frames_total
    assert session.warnings == []


def test_pure_lag_gives_the_analytic_rmse(tmp_path):
    lag = 0.3
    results, _, truth = _analyze(tmp_path, "lag", lag_s=lag, dropout=0.1)
    (r,) = results
    scan, start, stop = truth.scans[0]
    assert (stop - start) * F_HZ == pytest.approx(5.0)  # whole periods
    w = 2 * np.pi * F_HZ
    # e(t) = A (sin w(t - lag) - sin wt): RMS over whole periods is sqrt(2) A |sin(w lag / 2)|
    expected_mm = np.sqrt(2) * A_MM * abs(np.sin(w * lag / 2))
    expected_deg = np.sqrt(2) * THETA_DEG * abs(np.sin(w * lag / 2))
    d = r.as_dict()
    assert d["position_rmse_mm"] == pytest.approx(expected_mm, rel=0.02)
    assert d["orientation_rmse_deg"] == pytest.approx(expected_deg, rel=0.02)
    # zero-mean error: centering changes little
    assert d["centered_position_rmse_mm"] == pytest.approx(expected_mm, rel=0.03)


def test_lag_rmse_matches_a_numerical_integral_over_a_partial_period(tmp_path):
    lag = 0.5
    results, _, truth = _analyze(tmp_path, "lag2", lag_s=lag, duration_s=13.3)
    _, start, stop = truth.scans[0]
    t = np.linspace(start, stop, 200_001) - 1000.0  # the synthetic expert clock starts at 1000
    w = 2 * np.pi * F_HZ
    e = A_MM * (np.sin(w * (t - lag)) - np.sin(w * t))
    expected = np.sqrt(np.mean(e**2))
    expected_centered = np.std(e)
    d = results[0].as_dict()
    assert d["position_rmse_mm"] == pytest.approx(expected, rel=0.02)
    assert d["centered_position_rmse_mm"] == pytest.approx(expected_centered, rel=0.02)


def test_clock_offset_is_compensated_only_with_clock_sync(tmp_path):
    base = dict(offset_mm=(5.0, 0.0, 0.0))
    (ref,), _, _ = _analyze(tmp_path, "ref", **base)
    (synced,), _, _ = _analyze(tmp_path, "synced", clock_offset_s=0.4, **base)
    (blind,), session, _ = _analyze(
        tmp_path, "blind", clock_offset_s=0.4, record_clock_sync=False, **base
    )
    assert synced.as_dict()["position_rmse_mm"] == pytest.approx(
        ref.as_dict()["position_rmse_mm"], abs=0.05
    )
    assert blind.as_dict()["centered_position_rmse_mm"] > 10.0  # 0.4 s looks like lag
    assert any("clock-sync" in w for w in session.warnings)


def test_tremor_shows_in_the_centered_error(tmp_path):
    (r,), _, _ = _analyze(
        tmp_path, "tremor", duration_s=42.0, tremor_mm=2.0, tremor_deg=1.0, offset_mm=(8.0, 0, 0)
    )
    d = r.as_dict()
    assert d["centered_position_rmse_mm"] == pytest.approx(np.sqrt(3) * 2.0, rel=0.2)
    assert d["position_rmse_mm"] == pytest.approx(np.hypot(8.0, np.sqrt(3) * 2.0), rel=0.1)
    assert d["centered_orientation_rmse_deg"] == pytest.approx(np.sqrt(3) * 1.0, rel=0.2)


def test_centering_on_so3_removes_a_rotation_offset_under_oscillation(tmp_path):
    (lag_only,), _, _ = _analyze(tmp_path, "rl", lag_s=0.2)
    (both,), _, _ = _analyze(tmp_path, "rb", lag_s=0.2, rotation_offset_deg=(12.0, 0.0, 5.0))
    a, b = lag_only.as_dict(), both.as_dict()
    assert b["orientation_rmse_deg"] > 2 * a["orientation_rmse_deg"]
    assert b["centered_orientation_rmse_deg"] == pytest.approx(
        a["centered_orientation_rmse_deg"], rel=0.05
    )


def test_expert_and_follower_files_make_one_session(tmp_path):
    cfg = SyntheticSession(
        duration_s=20.0,
        n_scans=2,
        offset_mm=(6.0, 0, 0),
        clock_offset_s=1.5,
        expert_rate_hz=EXPERT_RATE_HZ,
    )
    write_synthetic(tmp_path / "e.mcap", cfg, follower_path=tmp_path / "f.mcap")
    write_synthetic(tmp_path / "one.mcap", cfg)
    (two,) = load_sessions([tmp_path / "e.mcap", tmp_path / "f.mcap"])
    (one,) = load_sessions([tmp_path / "one.mcap"])
    r2, r1 = analyze_scans(two), analyze_scans(one)
    assert [r.interval.scan for r in r2] == [1, 2]
    for a, b in zip(r1, r2, strict=True):
        assert a.as_dict()["position_rmse_mm"] == pytest.approx(b.as_dict()["position_rmse_mm"])
        assert a.as_dict()["follower_id"] == "F01"

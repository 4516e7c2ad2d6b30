"""Restore stage: the inverse model of CONVENTIONS, every term the calibration holds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.app.simulate import scenario_from_dict, simulate
from pipeline.core.errors import PipelineBuildError
from pipeline.core.geometry import quat_normalize, rotvec_to_quat, so3_exp
from pipeline.core.recording import AttitudeSeries, Frame, Recording, VectorSeries
from pipeline.core.stage import Pipeline
from pipeline.model.calibration import Calibration
from stages.context import Context
from stages.estimate import Judge
from stages.resample import Resample
from stages.restore import restore_samples

B_ENU = np.array([1300.0, 15000.0, -49000.0])
T0 = 1_767_225_600_000_000_000


def _attitudes(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 20.0
    rv = np.stack([0.6 * np.sin(0.7 * t + rng.uniform(0, 6)), 0.5 * np.sin(1.1 * t),
                   0.9 * t + rng.uniform(0, 6)], -1)
    return quat_normalize(rotvec_to_quat(rv))


def _recording(t_ns, mag_nT, att_t_ns, q) -> Recording:
    return Recording(
        path="mem.mcap", channels=(), mag=VectorSeries(t_ns, mag_nT), mag_topic="/mag",
        attitude=AttitudeSeries(att_t_ns, q), attitude_topic="/att",
    )


def _cal(R, D=None, o=None, tau=None, effects=None) -> Calibration:
    return Calibration(R_body_mag=R, sigma_rotvec_deg=[0.01] * 3, B_enu_nT=B_ENU,
                       estimator="truth", residual_rms_nT=0.0, n_samples=1, D=D, offset_nT=o,
                       time_offset_s=tau, effects=effects or {})


@settings(max_examples=25, deadline=None)
@given(
    rv=st.lists(st.floats(-0.2, 0.2), min_size=3, max_size=3),
    d=st.lists(st.floats(-0.05, 0.05), min_size=6, max_size=6),
    o=st.lists(st.floats(-800, 800), min_size=3, max_size=3),
    seed=st.integers(0, 1000),
)
def test_restore_inverts_the_forward_model(rv, d, o, seed):
    # Property: restoring what the forward model predicts gives back B_enu exactly,
    # whatever R, D (symmetric PD) and offset.
    R = so3_exp(np.array(rv))
    D = np.eye(3) + np.array([[d[0], d[3], d[4]], [d[3], d[1], d[5]], [d[4], d[5], d[2]]])
    cal = _cal(R, D, np.array(o))
    n = 80
    t = T0 + np.arange(n, dtype=np.int64) * 50_000_000
    q = _attitudes(n, seed)
    y = cal.predict(t, AttitudeSeries(t, q))
    series = restore_samples(_recording(t, y, t, q), cal).series
    assert series.frame is Frame.ENU
    assert len(series) == n
    np.testing.assert_allclose(series.values, np.broadcast_to(B_ENU, (n, 3)), atol=1e-6)


def test_attitude_gap_samples_are_left_out_and_counted():
    n = 200
    t = T0 + np.arange(n, dtype=np.int64) * 50_000_000
    q = _attitudes(n, 3)
    cal = _cal(np.eye(3))
    keep = (np.arange(n) < 60) | (np.arange(n) >= 100)  # a 2 s gap in the attitude
    rec = _recording(t, cal.predict(t, AttitudeSeries(t, q)), t[keep], q[keep])
    rs = restore_samples(rec, cal, max_gap_s=0.2)
    # the 40 samples with stamps 60..99 lie between attitude samples 59 and 100, 2.05 s apart
    assert rs.n_without_attitude == 40
    assert rs.n_used + rs.n_without_attitude + rs.n_without_attitude_at_stamp == n
    assert len(rs.series) == n - 40
    assert np.isnan(rs.enu_nT[~rs.valid]).all() and np.isnan(rs.residual_nT[~rs.valid]).all()
    np.testing.assert_allclose(rs.series.values, np.broadcast_to(B_ENU, (n - 40, 3)),
                               atol=1e-6)


def test_hard_iron_step_windows_are_removed():
    n = 200
    t = T0 + np.arange(n, dtype=np.int64) * 50_000_000
    q = _attitudes(n, 5)
    step = {"windows_s": [[2.0, 4.0]], "offset_nT": [300.0, -200.0, 100.0]}
    base = _cal(so3_exp([0.01, -0.02, 0.03]))
    y = base.predict(t, AttitudeSeries(t, q))
    t_rel = (t - t[0]) * 1e-9
    inside = (t_rel >= 2.0) & (t_rel < 4.0)  # half-open windows
    y[inside] += step["offset_nT"]
    rec = _recording(t, y, t, q)
    with_step = restore_samples(rec, base.replace(effects={"hard_iron_step": step}))
    without = restore_samples(rec, base)
    np.testing.assert_allclose(with_step.enu_nT, np.broadcast_to(B_ENU, (n, 3)), atol=1e-6)
    assert np.abs(without.enu_nT[inside] - B_ENU).max() > 100.0
    np.testing.assert_allclose(with_step.residual_nT, 0.0, atol=1e-6)


def _sim(effects: dict, seed: int = 4):
    d = {
        "name": "restore_test",
        "timing": {"duration_s": 20.0, "mag_rate_hz": 50.0, "attitude_rate_hz": 50.0},
        "motion": {"profile": "multiaxis", "yaw_rate_deg_s": 20.0, "pitch_amplitude_deg": 25.0,
                   "pitch_period_s": 7.0, "roll_amplitude_deg": 25.0, "roll_period_s": 11.0},
        "field": {"enu_nT": B_ENU.tolist()},
        "sensor": {"misalignment_rotvec_deg": [1.2, -1.0, 1.2]},
        "noise": {"mag_sigma_nT": 0.5, "heading_sigma_deg": 0.0, "pitch_roll_sigma_deg": 0.0},
        "effects": effects,
    }
    return simulate(scenario_from_dict(d), seed=seed)


def test_simulated_sensor_terms_restore_to_the_true_field():
    # Known answer: with the true offset, D, tau and eddy-current matrix, the restored field
    # equals the simulated field up to the magnetometer noise (0.5 nT) and SLERP error.
    E_s = [[0.004, 0.0, 0.0], [0.0, 0.003, 0.0], [0.0, 0.0, 0.002]]
    sim = _sim({
        "hard_iron": {"offset_nT": [250.0, -120.0, 80.0]},
        "soft_iron": {"D": [[1.02, 0.01, 0.0], [0.01, 0.98, 0.005], [0.0, 0.005, 1.01]]},
        "time_offset": {"time_offset_s": 0.03},
        "eddy_current": {"E_s": E_s},
    })
    tr = sim.truth
    cal = _cal(tr.R_body_mag, tr.D, tr.offset_nT, tr.time_offset_s,
               {"eddy_current": tr.effects["eddy_current"]})
    rs = restore_samples(sim.recording, cal)
    ok = rs.valid
    assert ok.mean() > 0.97
    err = rs.enu_nT[ok] - tr.B_enu_t_nT[ok]
    rms = float(np.sqrt(np.mean(err**2)))
    assert rms < 1.5, rms
    # leaving the eddy-current term out makes the restored field measurably worse
    rs_no = restore_samples(sim.recording, cal.replace(effects={}))
    rms_no = float(np.sqrt(np.mean((rs_no.enu_nT[ok] - tr.B_enu_t_nT[ok]) ** 2)))
    assert rms_no > 2 * rms
    # uncorrected time offset is visible too
    rs_tau = restore_samples(sim.recording, cal.replace(time_offset_s=0.0))
    assert np.sqrt(np.mean((rs_tau.enu_nT[ok] - tr.B_enu_t_nT[ok]) ** 2)) > 2 * rms


def test_stage_contract():
    with pytest.raises(PipelineBuildError, match="Judge"):
        Pipeline([Judge()], initial=("recording",))
    n = 20
    t = T0 + np.arange(n, dtype=np.int64) * 50_000_000
    q = _attitudes(n, 1)
    cal = _cal(np.eye(3))
    ctx = Context(recording=_recording(t, cal.predict(t, AttitudeSeries(t, q)), t, q),
                  calibration=cal)
    out = Resample().run(ctx)
    assert out is not ctx and ctx.aligned is None and out.aligned is not None

"""The one forward model (pipeline.model): Jacobians against finite differences, the exact
time offset, the simulator as an independent oracle, and one prediction for calibrate,
diagnose and restore."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.app.simulate import scenario_from_dict, simulate
from pipeline.core.geometry import (
    quat_conj,
    quat_mul,
    quat_normalize,
    quat_to_rotvec,
    rotvec_to_quat,
    so3_exp,
)
from pipeline.core.recording import AttitudeSeries
from pipeline.model.attitude import AttitudeInterpolator, interpolate_attitude
from pipeline.model.calibration import Calibration
from pipeline.model.effects.heading_drift import HeadingPart
from pipeline.model.forward import PARAM_NAMES, ForwardModel, evaluate, jacobian, perturbed
from stages.context import Context
from stages.restore import restore_samples

T0 = 1_767_225_600_000_000_000
B_ENU = np.array([1300.0, 15000.0, -49000.0])


def _fast_attitude(n: int, rate_hz: float, peak_rad_s: float, seed: int = 0) -> AttitudeSeries:
    """Attitude turning about a wandering axis at up to ``peak_rad_s``."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    ph = rng.uniform(0, 2 * np.pi, 3)
    rv = np.stack([0.8 * np.sin(1.3 * t + ph[0]), 0.6 * np.sin(0.9 * t + ph[1]),
                   peak_rad_s * t + 0.3 * np.sin(2.1 * t + ph[2])], -1)
    return AttitudeSeries(T0 + np.round(t * 1e9).astype(np.int64),
                          quat_normalize(rotvec_to_quat(rv)))


def _model(tau: float, eddy: bool) -> ForwardModel:
    R = so3_exp(np.array([0.02, -0.015, 0.03]))
    D = np.eye(3) + np.array([[0.02, 0.01, 0.0], [0.01, -0.015, 0.005], [0.0, 0.005, 0.01]])
    E = np.diag([0.004, -0.003, 0.002]) if eddy else None
    return ForwardModel(R_body_mag=R, B_enu_nT=B_ENU, D=D, offset_nT=np.array([40., -25., 15.]),
                        time_offset_s=tau, E_s=E)


# ----------------------------------------------------------------------------- attitude


def test_one_interpolator_gap_rule_and_resample_agree():
    from stages.resample import interpolate_attitude as resample_interp

    att = _fast_attitude(200, 50.0, 1.0)
    keep = (np.arange(200) < 80) | (np.arange(200) >= 100)
    att = AttitudeSeries(att.t_ns[keep], att.q_enu_body[keep])
    tq = T0 + np.arange(0, 4_000_000_000, 7_000_000, dtype=np.int64)
    q1, v1 = interpolate_attitude(att, tq, time_offset_s=0.013, max_gap_s=0.1)
    q2, v2 = resample_interp(att, tq, time_offset_s=0.013, max_gap_s=0.1)
    assert np.array_equal(v1, v2) and np.array_equal(q1[v1], q2[v2])
    # the 0.42 s gap (attitude samples 79..100) is not bridged; t - tau before the start is
    # not valid either
    t_sense = (tq - T0) * 1e-9 - 0.013
    assert not v1[(t_sense > 79 / 50 + 1e-9) & (t_sense < 100 / 50 - 1e-9)].any()
    assert not v1[t_sense < 0].any() and v1[(t_sense > 0) & (t_sense < 1.5)].all()


def test_interpolated_rate_is_the_exact_derivative():
    # omega_body: C(t + h) = C(t) Exp(omega h) inside a segment; checked at 5 rad/s
    att = _fast_attitude(300, 100.0, 5.0)
    it = AttitudeInterpolator.of(att)
    tq = T0 + np.arange(10_000_000, 2_900_000_000, 3_333_333, dtype=np.int64)
    h = 1e-6
    a = it.at(tq, 0.0)
    b = it.at(tq, -h)  # at t + h
    fd = quat_to_rotvec(quat_mul(quat_conj(a.q_enu_body), b.q_enu_body)) / h
    inside = np.abs(np.round((tq - T0) * 1e-7) - (tq - T0) * 1e-7) > 1e-3  # not on a knot
    # 1e-6 s step: the FD error is |omega|^2 h ~ 3e-5 rad/s, far below the 1e-4 tolerance
    np.testing.assert_allclose(fd[inside], a.omega_body_rad_s[inside], atol=1e-4)
    assert np.max(np.linalg.norm(a.omega_body_rad_s, axis=1)) > 4.0


# ----------------------------------------------------------------------------- Jacobian


@pytest.mark.parametrize("tau", [0.0123, -0.1, 0.1])
@pytest.mark.parametrize("eddy", [False, True])
def test_jacobian_matches_finite_differences(tau, eddy):
    # rotation rates up to 5 rad/s, lags up to +-100 ms
    att = _fast_attitude(400, 100.0, 5.0, seed=3)
    t = T0 + np.arange(150_000_000, 3_850_000_000, 20_000_000, dtype=np.int64) + 4_321_000
    m = _model(tau, eddy)
    it = AttitudeInterpolator.of(att)
    J = jacobian(m, t, it)
    ok = evaluate(m, t, it).valid
    assert ok.all()
    steps = {"rot": 1e-6, "B": 1e-2, "o": 1e-2, "D": 1e-6, "tau": 1e-7}
    for k, name in enumerate(PARAM_NAMES):
        h = steps["rot" if k < 3 else "B" if k < 6 else "o" if k < 9 else "D" if k < 15 else "tau"]
        dx = np.zeros(len(PARAM_NAMES))
        dx[k] = h
        yp = evaluate(perturbed(m, dx), t, it).y_nT
        ym = evaluate(perturbed(m, -dx), t, it).y_nT
        fd = (yp - ym) / (2 * h)
        scale = float(np.max(np.abs(J[:, :, k]))) or 1.0
        if name == "tau" and eddy:
            # the eddy regressor's tau-derivative is its second central difference (J5): a
            # model of the derivative, good to a few percent of the whole column
            err = np.abs(fd - J[:, :, k])
            assert np.percentile(err, 95) < 0.05 * scale, (name, err.max(), scale)
            continue
        # analytic: 1e-5 of the column's scale (nT/rad ~ 5e4, nT/s ~ 2.5e5 at 5 rad/s)
        # except samples whose +-h straddle an attitude knot
        err = np.max(np.abs(fd - J[:, :, k]), axis=1)
        bad = err > 1e-5 * scale + 1e-7
        assert bad.mean() < 0.01, (name, err.max(), scale)


def test_heading_drift_in_the_model_jacobian_and_restore():
    # (M1h): the attitude source's heading error turns the field about Up; (J2) carries
    # Rz(h); restoring takes the heading error out, leaving B_enu (noise-free)
    from pipeline.model.forward import restore

    att = _fast_attitude(400, 100.0, 2.0, seed=4)
    t = T0 + np.arange(150_000_000, 3_850_000_000, 20_000_000, dtype=np.int64)
    span = 3.7
    m = dataclasses.replace(_model(0.01, False),
                            parts=(HeadingPart(np.radians([0.5, -0.2]), span),))
    it = AttitudeInterpolator.of(att)
    ev = evaluate(m, t, it)
    h = m.heading_rad((t - t[0]) * 1e-9)
    assert ev.heading_rad is not None and np.degrees(np.ptp(h)) > 0.9
    J = jacobian(m, t, it)
    for k in (3, 4, 5):
        dx = np.zeros(len(PARAM_NAMES))
        dx[k] = 1e-2
        fd = (evaluate(perturbed(m, dx), t, it).y_nT
              - evaluate(perturbed(m, -dx), t, it).y_nT) / 2e-2
        np.testing.assert_allclose(fd, J[:, :, k], atol=1e-6)
    # without the heading term the prediction differs by |B_h| * h (hundreds of nT)
    no_h = evaluate(dataclasses.replace(m, parts=()), t, it).y_nT
    assert np.max(np.linalg.norm(ev.y_nT - no_h, axis=1)) > 100.0
    rs = restore(m, ev.y_nT, t, it)
    np.testing.assert_allclose(rs.enu_nT, np.broadcast_to(B_ENU, rs.enu_nT.shape), atol=1e-6)
    np.testing.assert_allclose(rs.residual_nT, 0.0, atol=1e-6)
    # a calibration carries it as the heading_drift effect's legendre_rad / span_s
    cal = Calibration(R_body_mag=m.R_body_mag, sigma_rotvec_deg=np.zeros(3), B_enu_nT=B_ENU,
                      estimator="test", residual_rms_nT=0.0, n_samples=len(t), D=m.D,
                      offset_nT=m.offset_nT, time_offset_s=m.time_offset_s,
                      effects={"heading_drift": {"rate_deg_per_h": 0.0, "peak_to_peak_deg": 0.0,
                                                 "legendre_rad": np.radians([0.5, -0.2]).tolist(),
                                                 "span_s": span}})
    np.testing.assert_allclose(cal.predict(t, att, t0_ns=int(t[0])), ev.y_nT, atol=1e-6)


def test_time_offset_jacobian_uses_rate_at_sensing_time():
    # At 5 rad/s a 100 ms lag is 0.5 rad of turn: the Jacobian must use omega(t - tau)
    att = _fast_attitude(400, 100.0, 5.0, seed=5)
    t = T0 + np.arange(200_000_000, 3_800_000_000, 50_000_000, dtype=np.int64) + 1_234_000
    m = _model(0.1, False)
    J = jacobian(m, t, att)[:, :, 15]
    J_wrong = jacobian(dataclasses.replace(m, time_offset_s=0.0), t, att)[:, :, 15]
    fd = (evaluate(perturbed(m, np.r_[np.zeros(15), 1e-7]), t, att).y_nT
          - evaluate(perturbed(m, np.r_[np.zeros(15), -1e-7]), t, att).y_nT) / 2e-7
    assert np.median(np.abs(fd - J)) < 1e-3 * np.median(np.abs(fd - J_wrong))


# ----------------------------------------------------------------------------- oracle


def _sim(tau: float, noise: bool, **over):
    d = {
        "name": "model_oracle",
        "timing": {"duration_s": 30.0, "mag_rate_hz": 50.0, "attitude_rate_hz": 200.0,
                   "attitude_phase_s": 0.0013},
        "motion": {"profile": "multiaxis", "yaw_rate_deg_s": 60.0, "pitch_amplitude_deg": 30.0,
                   "pitch_period_s": 5.0, "roll_amplitude_deg": 25.0, "roll_period_s": 7.0},
        "field": {"enu_nT": B_ENU.tolist()},
        "sensor": {"misalignment_rotvec_deg": [1.2, -1.0, 1.2]},
        "noise": {"mag_sigma_nT": 0.5 if noise else 0.0, "heading_sigma_deg": 0.0,
                  "pitch_roll_sigma_deg": 0.0},
        "effects": {
            "hard_iron": {"offset_nT": [250.0, -120.0, 80.0]},
            "soft_iron": {"D": [[1.02, 0.01, 0.0], [0.01, 0.98, 0.005], [0.0, 0.005, 1.01]]},
            "time_offset": {"time_offset_s": tau},
        },
    }
    d.update(over)
    return simulate(scenario_from_dict(d), seed=7)


def _truth_cal(tr) -> Calibration:
    return Calibration(R_body_mag=tr.R_body_mag, sigma_rotvec_deg=[0.01] * 3,
                       B_enu_nT=tr.B_enu_nT, estimator="truth", residual_rms_nT=0.0,
                       n_samples=1, D=tr.D, offset_nT=tr.offset_nT,
                       time_offset_s=tr.time_offset_s)


@pytest.mark.parametrize("tau", [0.06, -0.06])
def test_simulator_oracle_and_model_agree_without_noise(tau):
    # pipeline.app.simulate evaluates the continuous motion at t - tau (its own implementation);
    # the model re-interpolates the 200 Hz attitude samples at t - tau by SLERP. SLERP's
    # error at 200 Hz and these rates (<= 1.2 rad/s): s(1-s) dt^2/2 |alpha| ~ 1e-5 rad, i.e.
    # < 0.5 nT of a 51 uT field.
    sim = _sim(tau, noise=False)
    rec = sim.recording
    y = _truth_cal(sim.truth).predict(rec.mag.t_ns, rec.attitude)
    ok = np.isfinite(y).all(axis=1)
    assert ok.mean() > 0.99
    err = np.abs(y[ok] - rec.mag.values[ok])
    assert err.max() < 0.5, err.max()
    # a first-order (eddy-like) time offset would be off by tau^2/2 |d2y/dt2|: tens of nT
    y0 = _truth_cal(sim.truth).replace(time_offset_s=0.0).predict(rec.mag.t_ns, rec.attitude)
    assert np.nanmax(np.abs(y0 - rec.mag.values)) > 100 * err.max()


@pytest.mark.parametrize("tau", [0.06, -0.06])
def test_time_offset_recovered_from_simulated_recording(tau):
    from pipeline.core.vocabulary import EstimateTerm
    from stages.estimate import fit_calibration
    from stages.resample import Resample

    sim = _sim(tau, noise=True, effects={"hard_iron": {"offset_nT": [250.0, -120.0, 80.0]},
                                         "time_offset": {"time_offset_s": tau}})
    al = Resample().run(Context(recording=sim.recording)).aligned
    cal = fit_calibration(sim.recording, al, terms={EstimateTerm.OFFSET, EstimateTerm.TIME_OFFSET})
    # 0.5 nT noise, ~1500 samples turning at ~1 rad/s: sigma(tau) ~ 10 us; 0.2 ms is 20 sigma
    assert cal.time_offset_s == pytest.approx(tau, abs=2e-4)
    np.testing.assert_allclose(cal.offset_nT, [250.0, -120.0, 80.0], atol=2.0)  # nT
    assert cal.residual_rms_nT < 0.6  # the noise (0.5 nT) and nothing else


# ----------------------------------------------------------------------------- one prediction


def _diag_recording():
    d = {
        "name": "model_diag",
        "timing": {"duration_s": 40.0, "mag_rate_hz": 50.0, "attitude_rate_hz": 50.0,
                   "attitude_phase_s": 0.003},
        "motion": {"profile": "multiaxis", "yaw_rate_deg_s": 30.0, "pitch_amplitude_deg": 25.0,
                   "pitch_period_s": 7.0, "roll_amplitude_deg": 25.0, "roll_period_s": 11.0},
        "field": {"enu_nT": B_ENU.tolist()},
        "sensor": {"misalignment_rotvec_deg": [1.2, -1.0, 1.2]},
        "noise": {"mag_sigma_nT": 0.5, "heading_sigma_deg": 0.01, "pitch_roll_sigma_deg": 0.01},
        "effects": {"hard_iron": {"offset_nT": [60.0, -40.0, 25.0]},
                    "disturbance": {"windows_s": [[15.0, 24.0]], "peak_nT": 150.0,
                                    "direction_enu": [0.3, 0.2, 0.93]}},
    }
    return simulate(scenario_from_dict(d), seed=3)


def test_diagnose_prediction_is_the_calibration_prediction():
    # The diagnosis fit (stages.diagnose.model.evaluate) and Calibration.predict of the final
    # calibration it writes are the same function of time: every term, the disturbance
    # included, to round-off.
    from stages.diagnose.result import DiagnoseConfig
    from stages.diagnose.search import diagnose_data
    from stages.diagnose.stage import calibration_from, fit_data_from
    from stages.resample import Resample

    sim = _diag_recording()
    rec = sim.recording
    al = Resample().run(Context(recording=rec)).aligned
    data = fit_data_from(rec, al, max_samples=DiagnoseConfig().max_samples)
    diag, res = diagnose_data(data, None, DiagnoseConfig())
    assert {"hard_iron", "disturbance"} <= {f.effect for f in diag.findings}
    cal = calibration_from(res, data, diag.findings)
    from stages.diagnose.model import evaluate as effects_evaluate

    y_fit = effects_evaluate(res.state, data, jacobian=False).y_nT
    t_ns = int(rec.mag.t_ns[0]) + np.round(data.t_s * 1e9).astype(np.int64)
    y_cal = cal.predict(t_ns, rec.attitude, t0_ns=int(rec.mag.t_ns[0]),
                        max_gap_s=np.inf)
    np.testing.assert_allclose(y_cal, y_fit, atol=1e-6)  # nT
    # and therefore the same residual: the fit's and the restore's on the fitted samples
    r_fit = float(np.sqrt(np.mean((data.y_nT - y_fit) ** 2)))
    r_cal = float(np.sqrt(np.mean((data.y_nT - y_cal) ** 2)))
    assert r_cal == pytest.approx(r_fit, rel=1e-9)


def test_diagnose_baseline_equals_calibrate_residual():
    # Same recording, same model (R_body_mag and B_enu): calibrate's residual and the
    # diagnosis baseline agree within 0.1 % (one attitude interpolation, one prediction).
    from stages.diagnose.result import DiagnoseConfig
    from stages.diagnose.search import diagnose_data
    from stages.diagnose.stage import fit_data_from
    from stages.estimate import fit_calibration
    from stages.resample import Resample

    sim = _sim(0.0, noise=True, effects={})
    rec = sim.recording
    al = Resample().run(Context(recording=rec)).aligned
    cal = fit_calibration(rec, al)
    data = fit_data_from(rec, al, max_samples=DiagnoseConfig().max_samples)
    # no decimation; the diagnosis leaves out the 100 ms at each end of the attitude track
    assert len(al) - 12 <= len(data) < len(al)
    diag, _ = diagnose_data(data, None, DiagnoseConfig())
    # Calibration.restore over every sample gives calibrate's number ...
    t0 = int(rec.mag.t_ns[0])
    rs = cal.restore(al.mag_nT, al.t_ns, rec.attitude, t0_ns=t0)
    assert rs.valid.all()
    rms = float(np.sqrt(np.mean(rs.residual_nT**2)))
    assert rms == pytest.approx(cal.residual_rms_nT, rel=1e-3)
    # ... and over the diagnosis's samples the diagnosis baseline
    t_data = t0 + np.round(np.asarray(data.t_s) * 1e9).astype(np.int64)
    keep = np.isin(np.asarray(al.t_ns), t_data)
    assert keep.sum() == len(data)
    rms_same = float(np.sqrt(np.mean(rs.residual_nT[keep] ** 2)))
    assert diag.baseline["residual_rms_nT"] == pytest.approx(rms_same, rel=1e-3)


# ----------------------------------------------------------------------------- one number


def _line_with_passing_vehicle(tmp_path):
    from pipeline.app.simulate import write_simulated

    d = {
        "name": "line_vehicle",
        "timing": {"mag_rate_hz": 50.0, "attitude_rate_hz": 50.0, "attitude_phase_s": 0.003},
        "motion": {"profile": "survey_lines", "heading_deg": 135.0, "n_lines": 2,
                   "line_duration_s": 25.0, "turn_duration_s": 10.0, "turn_deg": 180.0,
                   "wobble_deg": 1.5, "wobble_period_s": 6.0},
        "field": {"enu_nT": B_ENU.tolist()},
        "sensor": {"misalignment_rotvec_deg": [1.2, -1.0, 1.2]},
        "noise": {"mag_sigma_nT": 0.5, "heading_sigma_deg": 0.05, "pitch_roll_sigma_deg": 0.01},
        "output": {"mag_type": "sensor_msgs/msg/MagneticField", "mag_topic": "/mag",
                   "attitude_type": "novatel_oem7_msgs/msg/INSPVA",
                   "attitude_topic": "/novatel/oem7/inspva"},
        # as the demo's line_04: a vehicle passes, its field a 60 nT bell, mostly vertical
        "effects": {"disturbance": {"windows_s": [[28.0, 40.0]], "peak_nT": 60.0,
                                    "direction_enu": [0.3, 0.2, 0.93]}},
    }
    sim = simulate(scenario_from_dict(d), seed=204)
    return write_simulated(sim, tmp_path / "line_vehicle.mcap")


def test_final_residual_is_one_number_everywhere(tmp_path):
    # The <mag>/residual channel read back from the corrected MCAP, the arrays the residual
    # figure is drawn from, the report and diagnosis.json give the final model's residual,
    # the diagnosed disturbance included: the same number (1e-6 relative).
    import json
    import re
    from pathlib import Path

    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from pipeline.io.mcap_read import read_recording
    from pipeline.run.runner import ProcessOptions, process_recording
    from stages.report import residual_figure_data
    from stages.restore import restore_samples, view_data

    path = _line_with_passing_vehicle(tmp_path)
    row = process_recording(path, tmp_path / "out",
                            options=ProcessOptions(write_rerun=False, write_report=True))
    out = Path(row["paths"]["calibration.json"]).parent
    diag = json.loads((out / "diagnosis.json").read_text())
    assert "disturbance" in diag["final"]["effects"]
    final = diag["final"]["residual_rms_nT"]

    # corrected MCAP, read with the real mcap reader (tesla on the wire, REP-145)
    rows = []
    with open(out / "line_vehicle.corrected.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _s, _c, _m, msg in reader.iter_decoded_messages(topics=["/mag/residual"]):
            v = msg.magnetic_field
            rows.append([v.x, v.y, v.z])
    r_mcap = np.asarray(rows) * 1e9
    r_mcap = r_mcap[np.isfinite(r_mcap).all(axis=1)]
    rms_mcap = float(np.sqrt(np.mean(r_mcap**2)))

    # the residual figure's arrays, from the calibration file read back
    cal = Calibration.load(out / "calibration.json")
    rs = restore_samples(read_recording(path), cal)
    t_fig, r_fig = residual_figure_data(view_data(rs, cal.R_body_mag))
    rms_fig = float(np.sqrt(np.mean(r_fig**2)))

    html = (out / "report.html").read_text()
    rms_report = float(re.search(r"<span id=residual_rms_nT>([^<]+)</span>", html).group(1))

    for name, v in (("mcap", rms_mcap), ("figure", rms_fig), ("report", rms_report),
                    ("calibration.json", cal.residual_rms_nT)):
        assert v == pytest.approx(final, rel=1e-6), (name, v, final)
    # and it is the attitude noise (0.05 deg of heading: ~8 nT), not the 60 nT vehicle: the
    # residual inside the vehicle's window is that of the rest of the line, and the model
    # without the disturbance leaves it there
    inside = (t_fig >= 28.0) & (t_fig < 40.0)
    rms_in = float(np.sqrt(np.mean(r_fig[inside] ** 2)))
    rms_out = float(np.sqrt(np.mean(r_fig[~inside] ** 2)))
    assert rms_in < 1.3 * rms_out, (rms_in, rms_out)
    no_dist = cal.replace(effects={k: v for k, v in cal.effects.items() if k != "disturbance"})
    r_no = restore_samples(read_recording(path), no_dist).residual_nT
    r_no = r_no[rs.valid][inside]
    assert float(np.sqrt(np.mean(r_no**2))) > 2.0 * rms_in

    # the sample counts add up
    m = json.loads((out / "metrics.json").read_text())
    assert (m["n_used"] + m["n_without_attitude"] + m["n_without_attitude_at_stamp"]
            == m["n_samples"] == len(rs.t_ns))
    assert f"{m['n_used']} of {m['n_samples']} samples used" in html


def test_diagnose_final_residual_is_the_restore_of_its_model():
    # Diagnose states the final model's residual over every sample as the restore of that
    # model gives it (the number every output shows); another model restores worse.
    from stages.diagnose.stage import Diagnose
    from stages.resample import Resample

    sim = _diag_recording()
    ctx = Diagnose().run(Resample().run(Context(recording=sim.recording)))
    rs = restore_samples(sim.recording, ctx.calibration)
    assert rs.residual_rms_nT == pytest.approx(ctx.diagnosis.final["residual_rms_nT"],
                                               rel=1e-12)
    other = restore_samples(sim.recording, ctx.calibration.replace(offset_nT=None))
    assert other.residual_rms_nT > rs.residual_rms_nT


# ----------------------------------------------------------------------------- one model


def test_wiring_reading_is_what_evaluate_predicts():
    """Wiring: the model against itself (physics: tests/test_model_independent.py)."""
    # forward.reading is (M2)-(M5) from the pieces: with the attitude and the field of an
    # ForwardEvaluation it gives the same prediction, and a constant field (3,) the same as (N, 3).
    from pipeline.model.forward import reading

    att = _fast_attitude(400, 50.0, 1.5)
    tq = att.t_ns[20:380:3] + 4_000_000
    model = _model(0.0123, eddy=False)
    ev = evaluate(model, tq, att)
    from pipeline.core.geometry import quat_to_matrix

    Ct = np.swapaxes(quat_to_matrix(ev.q_enu_body), -1, -2)
    rd = reading(Ct, ev.field_enu_nT, model.R_body_mag, model.D, (model.offset_nT,))
    np.testing.assert_allclose(rd.y_nT, ev.y_nT, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rd.b_body_nT, ev.b_body_nT, rtol=0, atol=1e-9)
    rc = reading(Ct, model.B_enu_nT, model.R_body_mag, model.D, (model.offset_nT,))
    np.testing.assert_allclose(rc.y_nT, rd.y_nT, rtol=0, atol=1e-9)


def test_wiring_ml_estimator_predicts_with_the_forward_model():
    """Wiring: the ML estimator against the forward model, which it calls (physics:
    tests/test_model_independent.py)."""
    # The ML estimator's prediction and Jacobian are the forward model's, (M2)-(M4) + o and
    # (J2)-(J5), for the same R, B, o, D and tau.
    from pipeline.core.vocabulary import EstimateTerm
    from stages.estimators.base import EstimationProblem
    from stages.estimators.ml import Model, State

    att = _fast_attitude(600, 50.0, 1.5, seed=2)
    t_ns = att.t_ns[30:570] + 7_000_000
    model = dataclasses.replace(_model(0.0123, eddy=False))
    p = EstimationProblem(t_ns=t_ns, mag_nT=np.zeros((len(t_ns), 3)),
                          q_enu_body=np.zeros((len(t_ns), 4)), attitude=att,
                          terms=frozenset({EstimateTerm.OFFSET, EstimateTerm.SOFT_IRON,
                                           EstimateTerm.TIME_OFFSET}))
    m = Model(p, estimate_B=True)
    s = State(model.R_body_mag, model.B_enu_nT, model.offset_nT, model.D, model.time_offset_s)
    np.testing.assert_allclose(m.predict(s), evaluate(model, t_ns, att).y_nT, rtol=0, atol=1e-8)
    J_ml = m.jacobian(s)
    J_fw = jacobian(model, t_ns, att)
    for ml_block, fw_cols in (("B", slice(3, 6)), ("offset", slice(6, 9)), ("tau", slice(15, 16))):
        np.testing.assert_allclose(J_ml[:, :, m.blocks[ml_block]], J_fw[:, :, fw_cols],
                                   rtol=1e-9, atol=1e-6)


def test_one_solver_core_for_every_fit():
    # levenberg_marquardt (the diagnosis) is minimise on the unweighted sum of squares; a
    # caller's step solver, stopping rule and damping schedule reach the same minimum.
    from pipeline.model.solve import Linearised, levenberg_marquardt, minimise

    rng = np.random.default_rng(1)
    b = rng.normal(size=(200, 3)) * 1000.0
    R_true = so3_exp(np.array([0.3, -0.2, 0.5]))
    y = b @ R_true + rng.normal(size=b.shape)

    def rj(R, with_j):
        from pipeline.model.forward import skew_rows

        m = b @ R
        return y - m, (skew_rows(m) if with_j else None)  # right perturbation: dm/dd = [m]x

    upd = lambda R, dx: R @ so3_exp(dx)  # noqa: E731
    sol = levenberg_marquardt(np.eye(3), rj, upd)

    def lin(R, with_normal):
        r, J = rj(R, with_normal)
        if not with_normal:
            return Linearised(float(np.sum(r * r)))
        Jf = J.reshape(-1, 3)
        return Linearised(float(np.sum(r * r)), Jf.T @ Jf, Jf.T @ r.reshape(-1))

    other = minimise(np.eye(3), lin, upd, lam0=1e-9, lam_up=10.0, lam_down=10.0,
                     lam_min=1e-12, rtol=0.0, relinearise_last=False,
                     solve_step=lambda H, g, lam, sc: np.linalg.lstsq(H + lam * np.diag(sc), g,
                                                                       rcond=None)[0],
                     converged=lambda a, b_, dx: bool(np.max(np.abs(dx)) < 1e-12))
    for R in (sol.state, other.state):  # 1 nT on 1000 nT, 200 samples: ~0.004 deg
        d = np.degrees(np.arccos(np.clip((np.trace(R.T @ R_true) - 1) / 2, -1, 1)))
        assert d < 0.05
    assert np.max(np.abs(sol.state - other.state)) < 1e-9

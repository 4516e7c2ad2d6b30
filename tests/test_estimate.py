"""Estimate stage: known answers from simulation, Jacobians, invariances, sigma sanity."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.core.errors import NotObservableError
from pipeline.core.geometry import quat_conj, quat_rotate, so3_exp, so3_log
from pipeline.core.recording import AlignedSeries
from pipeline.core.vocabulary import EstimateTerm, EstimatorKind
from stages.context import Context
from stages.estimate import Estimate, NoiseModel, fit_calibration
from stages.estimators import ml
from stages.estimators.base import EstimationProblem
from stages.estimators.synthetic import draw, small_rotation

R_SMALL = small_rotation([2.0, -3.0, 1.5])
R_BIG = np.array([[-1.0, 0, 0], [0, 0, 1], [0, 1, 0]]) @ small_rotation([3.0, 2.0, -4.0])
SCEN = Path(__file__).resolve().parents[1] / "pipeline" / "scenarios"
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def angle_between_deg(A, B):
    """Geodesic angle (deg), accurate near zero (arccos of the trace is not)."""
    return float(np.degrees(np.linalg.norm(so3_log(np.asarray(A) @ np.asarray(B).T))))


@pytest.fixture(scope="module")
def section41():
    from pipeline.app.simulate import load_scenario, simulate
    from stages.resample import Resample

    sim = simulate(load_scenario(SCEN / "li2020_section41.toml"))
    ctx = Resample().run(Context(recording=sim.recording))
    return sim, ctx


@pytest.mark.parametrize("est", [EstimatorKind.ML, EstimatorKind.LI2020])
def test_section41_noise_free_restores_field(section41, est):
    sim, ctx = section41
    al = ctx.aligned
    B = sim.truth.B_enu_nT
    # Without a reference: the restored field is constant (deviation from its mean).
    cal = fit_calibration(sim.recording, al, estimator=est)
    rest = cal.restore(al.mag_nT, al.t_ns, sim.recording.attitude).enu_nT
    assert np.abs(rest - rest.mean(0)).max() <= 1e-3
    # With the preset field as reference: deviation from the preset itself.
    cal = fit_calibration(sim.recording, al, estimator=est, reference_field_enu_nT=B)
    rest = cal.restore(al.mag_nT, al.t_ns, sim.recording.attitude).enu_nT
    assert np.abs(rest - B).max() <= 1e-3
    assert angle_between_deg(cal.R_body_mag, sim.truth.R_body_mag) < 1e-4
    assert cal.unobservable_axes_body == ()


def test_section41_rotation_axis_unobservable_without_reference(section41):
    sim, ctx = section41
    cal = fit_calibration(sim.recording, ctx.aligned)
    axis_body = quat_rotate(quat_conj(sim.truth.q_enu_body_true[0]), [0.0, 0.0, 1.0])
    assert len(cal.unobservable_axes_body) == 1
    assert abs(float(cal.unobservable_axes_body[0] @ axis_body)) > 1 - 1e-9
    assert np.isinf(cal.sigma_rotvec_deg).any()
    assert any("reference field" in w for w in cal.warnings)
    d = json.loads(cal.to_json())
    assert None in d["sigma_rotvec_deg"]


def test_large_mounting_converges_from_identity():
    s = draw(kind="multi", n=600, R_body_mag=R_BIG, noise=NoiseModel.li2020())
    # Converged to the right basin (not an axis permutation away); li2020's tangents and
    # normals carry the attitude noise, hence its wider tolerance.
    for est, tol in (
        (EstimatorKind.ML, 0.05),
        (EstimatorKind.LI2020, 0.2),
        (EstimatorKind.DPI, 0.1),
    ):
        cal = fit_calibration(None, s.aligned, estimator=est)
        assert angle_between_deg(cal.R_body_mag, R_BIG) < tol, est


def _state(terms):
    return ml.State(
        R_SMALL,
        np.array([10000.0, 30000.0, 20000.0]),
        np.array([50.0, -20, 10]),
        np.eye(3) + 0.01 * np.array([[1, 2, 0], [2, -1, 1], [0, 1, 0.5]]),
        0.004,
    )


@pytest.mark.parametrize("with_ref", [False, True])
def test_jacobian_matches_finite_differences(with_ref):
    s = draw(kind="multi", n=200, R_body_mag=R_SMALL, varying_rate=True)
    terms = frozenset({EstimateTerm.OFFSET, EstimateTerm.SOFT_IRON, EstimateTerm.TIME_OFFSET})
    p = EstimationProblem(
        s.aligned.t_ns,
        s.aligned.mag_nT,
        s.aligned.q_enu_body,
        attitude=s.attitude,
        terms=terms,
        reference_field_enu_nT=s.B_enu_nT if with_ref else None,
    )
    model = ml.Model(p, estimate_B=not with_ref)
    st0 = _state(terms)
    J = model.jacobian(st0)
    steps = np.full(model.n_params, 1e-6)
    steps[model.blocks["tau"]] = 1e-5
    if "B" in model.blocks:
        steps[model.blocks["B"]] = 1e-2
    if "offset" in model.blocks:
        steps[model.blocks["offset"]] = 1e-2
    for k in range(model.n_params):
        e = np.zeros(model.n_params)
        e[k] = steps[k]
        num = (model.predict(model.step(st0, e)) - model.predict(model.step(st0, -e))) / (
            2 * steps[k]
        )
        scale = np.abs(J[:, :, k]).max() + 1e-9
        assert np.abs(num - J[:, :, k]).max() <= 2e-3 * scale, k


def test_rotation_jacobian_is_left_perturbation_formula():
    # dy/dphi = D R.T [b]x for y = D R.T b with R = exp(phi^) R (CONVENTIONS model).
    rng = np.random.default_rng(3)
    b = rng.normal(size=3) * 3e4
    D = np.eye(3) + 0.02 * np.diag([1.0, -1.0, 0.5])
    phi = np.zeros(3)
    J = np.zeros((3, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-7
        yp = D @ (so3_exp(phi + e) @ R_SMALL).T @ b
        ym = D @ (so3_exp(phi - e) @ R_SMALL).T @ b
        J[:, k] = (yp - ym) / 2e-7
    from pipeline.core.geometry import skew

    np.testing.assert_allclose(J, D @ R_SMALL.T @ skew(b), rtol=1e-6, atol=1e-6)


def _fit_R(aligned, ref=None):
    return fit_calibration(None, aligned, reference_field_enu_nT=ref).R_body_mag


@settings(max_examples=6, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3))
def test_rotating_world_frame_gives_same_R(rv):
    s = draw(
        kind="multi", n=300, R_body_mag=R_SMALL, noise=NoiseModel(0.5), rng=np.random.default_rng(5)
    )
    from pipeline.core.geometry import matrix_to_quat, quat_mul

    G = so3_exp(np.array(rv))
    qG = matrix_to_quat(G)
    q2 = quat_mul(np.broadcast_to(qG, s.aligned.q_enu_body.shape), s.aligned.q_enu_body)
    al2 = AlignedSeries(s.aligned.t_ns, s.aligned.mag_nT, q2)
    R1 = _fit_R(s.aligned)
    R2 = _fit_R(al2)
    assert angle_between_deg(R1, R2) < 1e-6
    R1r = _fit_R(s.aligned, s.B_enu_nT)
    R2r = _fit_R(al2, G @ s.B_enu_nT)
    assert angle_between_deg(R1r, R2r) < 1e-6


@settings(max_examples=6, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3))
def test_relabelling_mag_axes_changes_R_to_R_Pt(rv):
    s = draw(
        kind="multi", n=300, R_body_mag=R_SMALL, noise=NoiseModel(0.5), rng=np.random.default_rng(6)
    )
    P = so3_exp(np.array(rv))
    al2 = AlignedSeries(s.aligned.t_ns, s.aligned.mag_nT @ P.T, s.aligned.q_enu_body)
    R1 = _fit_R(s.aligned)
    R2 = _fit_R(al2)
    assert angle_between_deg(R2, R1 @ P.T) < 1e-6


def test_reversing_time_changes_nothing():
    s = draw(
        kind="multi", n=400, R_body_mag=R_SMALL, noise=NoiseModel(0.5), rng=np.random.default_rng(7)
    )
    al = s.aligned
    rev = AlignedSeries(
        al.t_ns[-1] - al.t_ns[::-1] + al.t_ns[0], al.mag_nT[::-1], al.q_enu_body[::-1]
    )
    for est in (EstimatorKind.ML, EstimatorKind.DPI):
        c1 = fit_calibration(None, al, estimator=est)
        c2 = fit_calibration(None, rev, estimator=est)
        assert angle_between_deg(c1.R_body_mag, c2.R_body_mag) < 1e-6
        np.testing.assert_allclose(c1.sigma_rotvec_deg, c2.sigma_rotvec_deg, rtol=1e-5)


def test_sigma_matches_monte_carlo_spread():
    noise = NoiseModel.li2020()
    errs, sigs = [], []
    for k in range(30):
        s = draw(
            kind="multi", n=400, R_body_mag=R_SMALL, noise=noise, rng=np.random.default_rng(100 + k)
        )
        cal = fit_calibration(None, s.aligned, noise=noise)
        errs.append(np.degrees(so3_log(cal.R_body_mag @ R_SMALL.T)))
        sigs.append(cal.sigma_rotvec_deg)
    spread = np.sqrt(np.mean(np.square(errs), 0))
    sig = np.mean(sigs, 0)
    assert np.all(np.abs(sig / spread - 1) < 0.35), (sig, spread)


def _attitude_error_whitened(C_true, C_meas, noise):
    """Body-frame attitude errors whitened by the noise model's covariance, (N, 3)."""
    delta = so3_log(np.swapaxes(C_true, 1, 2) @ C_meas)
    L = np.linalg.cholesky(noise.attitude_cov_body(C_true))
    return np.linalg.solve(L, delta[:, :, None])[:, :, 0]


@pytest.mark.parametrize("source", ["simulate", "synthetic"])
def test_attitude_noise_model_matches_the_generators(source):
    # The estimator's weighting and the Cramer-Rao bound assume the attitude error model of
    # NoiseModel.attitude_cov_body; both generators must produce exactly that error. Small
    # heading and large pitch/roll noise with +-25-30 deg of roll make pitch about body x and
    # pitch about the Euler pitch axis differ by 10x along body z.
    import tomllib

    from pipeline.app.simulate import scenario_from_dict, simulate
    from pipeline.core.geometry import quat_to_matrix

    noise = NoiseModel(0.0, np.radians(0.005), np.radians(0.05), np.radians(0.05))
    if source == "simulate":
        d = tomllib.loads((SCEN / "multiaxis.toml").read_text())
        d["timing"].update(duration_s=30.0, attitude_phase_s=0.0)
        d["noise"] = {"mag_sigma_nT": 0.0, "heading_sigma_deg": 0.005, "pitch_roll_sigma_deg": 0.05}
        sim = simulate(scenario_from_dict(d), seed=4)
        assert np.array_equal(sim.recording.attitude.t_ns, sim.truth.mag_t_ns)
        q_true, q_meas = sim.truth.q_enu_body_true, sim.recording.attitude.q_enu_body
    else:
        s = draw(kind="multi", n=3000, noise=noise, rng=np.random.default_rng(4))
        q_true, q_meas = s.q_true, s.aligned.q_enu_body
    z = _attitude_error_whitened(quat_to_matrix(q_true), quat_to_matrix(q_meas), noise)
    cov = z.T @ z / len(z)
    # 3000 samples: each entry is known to ~0.026 (diagonal) / 0.018 (off-diagonal).
    np.testing.assert_allclose(cov, np.eye(3), atol=0.1)


def test_crb_is_marginal_over_the_field_and_equals_ml_sigma():
    from stages.estimators.ml import fisher_rotation_crb_deg

    noise = NoiseModel.li2020()
    s = draw(kind="multi", n=600, R_body_mag=R_SMALL, noise=noise, rng=np.random.default_rng(11))
    al = s.aligned

    def crb(**kw):
        p = EstimationProblem(al.t_ns, al.mag_nT, s.q_true, noise=noise, **kw)
        return fisher_rotation_crb_deg(p, R_SMALL, s.B_enu_nT)

    unknown, known = crb(), crb(reference_field_enu_nT=s.B_enu_nT)
    # Not knowing B costs information (most about the axis closest to the field direction).
    assert np.all(unknown >= known * (1 - 1e-9))
    assert np.max(unknown / known) > 1.05
    # ml's white-noise sigma is the same marginal bound, evaluated at its estimate; the reported
    # (block sandwich) sigma stays within 20 % of it on white noise (no over-inflation).
    cal = fit_calibration(None, al, noise=noise)
    np.testing.assert_allclose(cal.checks["sigma_rotvec_white_deg"], unknown, rtol=0.02)
    assert np.all(cal.sigma_rotvec_deg >= unknown * 0.98)
    assert np.all(cal.sigma_rotvec_deg <= unknown * 1.2)
    # A single-axis sweep leaves the rotation about the turning axis undetermined: inf there.
    s1 = draw(kind="single", n=300, R_body_mag=R_SMALL, noise=noise)
    p1 = EstimationProblem(s1.aligned.t_ns, s1.aligned.mag_nT, s1.q_true, noise=noise)
    b1 = fisher_rotation_crb_deg(p1, R_SMALL, s1.B_enu_nT)
    assert np.isinf(b1[2]) and np.all(np.isfinite(b1[:2]))


def test_li2020_cayley_jacobian_and_smoothed_tangents():
    from stages.estimators import li2020

    x = np.array([0.1, -0.2, 0.05])
    num = np.stack(
        [(li2020.cayley(x + 1e-6 * e) - li2020.cayley(x - 1e-6 * e)) / 2e-6 for e in np.eye(3)]
    )
    np.testing.assert_allclose(li2020.cayley_derivatives(x), num, atol=1e-8)
    noise = NoiseModel.li2020()
    rms = {}
    for tg in li2020.Tangents:
        est = li2020.Li2020Estimator(tangents=tg)
        # Noise-free: both ways of taking the derivatives are exact (same linear filter on the
        # readings and on the attitude).
        s = draw(kind="multi", n=800, R_body_mag=R_SMALL)
        p = EstimationProblem(s.aligned.t_ns, s.aligned.mag_nT, s.aligned.q_enu_body)
        assert angle_between_deg(est.fit(p).R_body_mag, R_SMALL) < 1e-8
        errs = []
        for k in range(3):
            s = draw(
                kind="multi", n=800, R_body_mag=R_SMALL, noise=noise, rng=np.random.default_rng(k)
            )
            p = EstimationProblem(s.aligned.t_ns, s.aligned.mag_nT, s.aligned.q_enu_body)
            errs.append(angle_between_deg(est.fit(p).R_body_mag, R_SMALL))
        rms[tg] = float(np.sqrt(np.mean(np.square(errs))))
    # Under the paper's INS noise the raw chords are several times worse than the fitted
    # derivatives.
    assert rms[li2020.Tangents.SMOOTHED] < 0.3 * rms[li2020.Tangents.FINITE_DIFFERENCE], rms


def test_li2020_sigma_accounts_for_correlated_tangent_residuals():
    # Tangents and normals of neighbouring samples share data: a plain s^2 H^-1 came out ~4x
    # too small. The sandwich must be of the right size (loose: a baseline's sigma, 20 runs).
    noise = NoiseModel.li2020()
    errs, sigs = [], []
    for k in range(20):
        s = draw(
            kind="multi", n=800, R_body_mag=R_SMALL, noise=noise, rng=np.random.default_rng(200 + k)
        )
        cal = fit_calibration(None, s.aligned, estimator=EstimatorKind.LI2020)
        errs.append(np.degrees(so3_log(cal.R_body_mag @ R_SMALL.T)))
        sigs.append(cal.sigma_rotvec_deg)
    ratio = np.mean(sigs, 0) / np.sqrt(np.mean(np.square(errs), 0))
    assert np.all((ratio > 0.4) & (ratio < 2.5)), ratio


def test_offset_soft_iron_time_offset_recovered():
    D = np.eye(3) + np.array([[0.02, 0.01, 0], [0.01, -0.01, 0.005], [0, 0.005, 0.01]])
    o = np.array([300.0, -200.0, 100.0])
    s = draw(
        kind="multi",
        n=3000,
        rate_hz=200.0,
        R_body_mag=R_SMALL,
        D=D,
        offset_nT=o,
        time_offset_s=0.013,
        varying_rate=True,
    )
    cal = fit_calibration(
        None,
        s.aligned,
        terms={EstimateTerm.OFFSET, EstimateTerm.SOFT_IRON, EstimateTerm.TIME_OFFSET},
        reference_field_enu_nT=s.B_enu_nT,
    )
    assert angle_between_deg(cal.R_body_mag, R_SMALL) < 2e-3
    assert np.abs(cal.offset_nT - o).max() < 1.0
    assert np.abs(cal.D - D).max() < 1e-4
    assert abs(cal.time_offset_s - 0.013) < 1e-4
    assert np.isfinite(cal.sigma_time_offset_s)


def test_time_offset_unobservable_at_constant_rate_single_axis():
    s = draw(kind="single", n=500, R_body_mag=R_SMALL)
    cal = fit_calibration(
        None, s.aligned, terms={EstimateTerm.TIME_OFFSET}, reference_field_enu_nT=s.B_enu_nT
    )
    assert cal.sigma_time_offset_s == np.inf
    assert any("vary the rotation rate" in w for w in cal.warnings)


def test_dpi_cannot_see_rotation_about_vertical_in_level_motion():
    s = draw(kind="single", n=400, R_body_mag=R_SMALL)
    cal = fit_calibration(
        None, s.aligned, estimator=EstimatorKind.DPI, reference_field_enu_nT=s.B_enu_nT
    )
    assert len(cal.unobservable_axes_body) == 1
    assert abs(cal.unobservable_axes_body[0][2]) > 1 - 1e-9


def test_ellipsoid_needs_3d_coverage_and_recovers_iron():
    s = draw(kind="single", n=300)
    with pytest.raises(NotObservableError):
        fit_calibration(None, s.aligned, estimator=EstimatorKind.ELLIPSOID)
    D = np.eye(3) + np.array([[0.03, 0.01, 0], [0.01, -0.02, 0.0], [0, 0.0, 0.01]])
    o = np.array([200.0, -100.0, 50.0])
    s = draw(kind="multi", n=800, R_body_mag=R_SMALL, D=D, offset_nT=o)
    cal = fit_calibration(
        None, s.aligned, estimator=EstimatorKind.ELLIPSOID, reference_field_enu_nT=s.B_enu_nT
    )
    assert np.abs(cal.offset_nT - o).max() < 1e-3
    assert np.abs(cal.D - D).max() < 1e-7


def test_robust_loss_resists_outliers():
    s = draw(
        kind="multi", n=600, R_body_mag=R_SMALL, noise=NoiseModel(1.0), rng=np.random.default_rng(9)
    )
    y = np.array(s.aligned.mag_nT)
    y[::37] += 3000.0
    al = AlignedSeries(s.aligned.t_ns, y, s.aligned.q_enu_body)
    plain = fit_calibration(None, al, reference_field_enu_nT=s.B_enu_nT)
    robust = fit_calibration(None, al, reference_field_enu_nT=s.B_enu_nT, robust=True)
    e_plain = angle_between_deg(plain.R_body_mag, R_SMALL)
    e_rob = angle_between_deg(robust.R_body_mag, R_SMALL)
    assert e_rob < 0.01 < e_plain


def test_stage_and_nominal_mounting():
    R_nom = np.array([[-1.0, 0, 0], [0, 0, 1], [0, 1, 0]])
    s = draw(kind="multi", n=300, R_body_mag=small_rotation([3.0, 2.0, -4.0]) @ R_nom)
    stage = Estimate(R_nominal_body_mag=tuple(map(tuple, R_nom)))
    ctx = Context(recording=None, aligned=s.aligned)
    out = stage.run(ctx)
    assert ctx.calibration is None
    np.testing.assert_allclose(out.calibration.rotvec_from_nominal_deg, [3.0, 2.0, -4.0], atol=0.05)


def test_calibrate_command_writes_json(tmp_path, section41):
    from pipeline.app.cli import main
    from pipeline.app.simulate import write_simulated

    sim, _ = section41
    rec = write_simulated(sim, tmp_path / "s41.mcap")
    out = tmp_path / "out"
    assert (
        main(["calibrate", str(rec), "--out", str(out), "--reference-field", "10000,30000,20000"])
        == 0
    )
    d = json.loads((out / "calibration.json").read_text())
    assert d["format"] == "magalign.calibration/1"
    assert d["unobservable_axes_body"] == []
    assert main(["calibrate", str(rec), "--out", str(out), "--estimate", "bogus"]) == 2


@pytest.mark.real
@pytest.mark.parametrize("name", ["lab_03", "lab_05"])
def test_real_lab_calibration_lowers_restored_std(name):
    path = REAL / f"{name}.mcap"
    if not path.exists():
        pytest.skip(f"real data folder {REAL.name} is absent (../shared/data/real)")
    from pipeline.io.mcap_read import read_recording
    from stages.resample import Resample

    rec = read_recording(path)
    al = Resample().run(Context(recording=rec)).aligned
    cal = fit_calibration(rec, al, terms={EstimateTerm.OFFSET, EstimateTerm.SOFT_IRON,
                                          EstimateTerm.TIME_OFFSET})
    rs = cal.restore(al.mag_nT, al.t_ns, rec.attitude, max_gap_s=0.1)
    al = al.select(rs.valid)
    before = quat_rotate(al.q_enu_body, al.mag_nT).std(0)
    after = rs.enu_nT[rs.valid].std(0)
    print(
        name,
        cal.rotvec_body_mag_deg,
        cal.sigma_rotvec_deg,
        cal.offset_nT,
        cal.time_offset_s,
        before,
        after,
    )
    assert np.all(after < before)

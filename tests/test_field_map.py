"""``field_map``: a smooth curl-free field beyond the linear gradient (Solin et al. 2018).

The basis (``pipeline/model/field_map.py``) against its own closed forms; the diagnosis'
Jacobian against finite differences (data from the diagnosis' own model, ``_diag_sim``);
then the physics against the independent generator (``tests/indep_gen.py``: distant point
dipoles, each minus the gradient of its closed-form potential, no magalign model code), read
and diagnosed through the command's own path.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from _diag_sim import lissajous_m, make_data
from indep_gen import (
    Spec,
    field_enu,
    mag_stamps_s,
    position_m,
    sensor_position_m,
    smooth_field_at,
    smooth_potential_at,
    truth,
    write,
)
from test_effects import G_TRUE, _gradient_value, _numeric_jacobian

from pipeline.app.commands.diagnose import diagnose_file
from pipeline.core.vocabulary import EffectKind
from pipeline.model.calibration import Calibration
from pipeline.model.effects.field_map import MapPart
from pipeline.model.field_map import (
    FieldMapBasis,
    axis_counts,
    domain_for,
    length_scale_for,
    mode_indices,
)
from stages.diagnose.fit import fit
from stages.diagnose.model import ModelState, Term, evaluate
from stages.restore import restore_samples

pytestmark = pytest.mark.filterwarnings("ignore::pipeline.core.errors.RecoveredDataWarning")


# ----------------------------------------------------------------------------- the basis


def test_each_basis_field_is_minus_the_gradient_of_its_potential_and_curl_free():
    b = FieldMapBasis.of([[-1.0, 1.5], [-2.0, 2.0], [0.0, 1.0]], (4, 5, 3))
    rng = np.random.default_rng(0)
    x = rng.uniform([-1.0, -2.0, 0.0], [1.5, 2.0, 1.0], (50, 3))
    w = rng.normal(size=b.n_basis) * 100.0  # nT
    g = b.field(x)
    h = 1e-6
    for d in range(3):
        e = np.zeros(3)
        e[d] = h
        num = -(b.potential(x + e) - b.potential(x - e)) / (2 * h)
        assert np.max(np.abs(num - g[:, d, :])) < 1e-8
    # a weight is a field in nT: no basis field exceeds 1 per unit weight
    assert np.max(np.linalg.norm(g, axis=1)) <= 1.0 + 1e-12
    # the field's gradient (the lever arm's Jacobian) against finite differences; symmetric
    D = b.field_gradient(x, w)

    def field(p):
        return np.einsum("ndk,k->nd", b.field(p), w)

    for d in range(3):
        e = np.zeros(3)
        e[d] = h
        num = (field(x + e) - field(x - e)) / (2 * h)
        assert np.max(np.abs(num - D[:, :, d])) < 1e-5 * np.max(np.abs(D))  # nT/m
    assert np.allclose(D, np.swapaxes(D, 1, 2), atol=1e-9)  # curl-free


def test_the_prior_gives_each_field_component_its_standard_deviation():
    """``var(w_j) = S(sqrt(lambda_j)) lambda_j / prod L_d``: well inside a large box, each
    component of ``-grad phi`` has the prior's standard deviation."""
    b = FieldMapBasis.of([[-5.0, 5.0]] * 3, (40, 40, 40))
    v = b.prior_variance(1.0, 30.0)  # l = 1 m, sigma_B = 30 nT
    g = b.field(np.array([[0.3, 0.1, -0.2]]))[0]
    assert np.allclose(np.sqrt(g**2 @ v), 30.0, rtol=1e-3)


def test_the_box_pads_the_path_and_a_flat_axis_gets_two_modes():
    p = np.array([[0.0, 0.0, 1.0], [6.0, 30.0, 1.0], [3.0, 10.0, 1.0]])
    dom = domain_for(p)
    assert np.allclose(dom, [[-7.5, 13.5], [-7.5, 37.5], [-6.5, 8.5]])
    ext = np.ptp(p, axis=0)
    assert axis_counts(dom, 8, ext) == (4, 8, 2)  # across: the same wavelength; flat: two
    assert axis_counts(dom, 2, ext) == (2, 2, 2)
    # with the box fixed, each complexity's modes are among the next one's
    for n in range(2, 8):
        small = {tuple(m) for m in mode_indices(axis_counts(dom, n, ext))}
        big = {tuple(m) for m in mode_indices(axis_counts(dom, n + 1, ext))}
        assert small <= big
    assert length_scale_for(dom, 6) == pytest.approx(45.0 / 12)


# ----------------------------------------------------------------------------- the model


def _map_term(p: np.ndarray, n: int, yaw_deg: float, noise_nT: float = 5.0) -> Term:
    dom = domain_for(p)
    return Term(EffectKind.FIELD_MAP, yaw_rad=np.radians(yaw_deg),
                domain_m=tuple((float(a), float(b)) for a, b in dom),
                n_axis=axis_counts(dom, n, np.ptp(p, axis=0)),
                length_scale_m=length_scale_for(dom, n), prior_nT=100.0, noise_nT=noise_nT)


def test_field_map_jacobian_matches_finite_differences_with_lever_arm_and_bearing():
    """Positions in a frame turned by 25 deg from ENU, the sensor 6 cm from the tracked point:
    the map's columns, the gradient's and the lever arm's (through the map's own gradient)."""
    fm = _map_term(lissajous_m(np.arange(0.0, 30.0, 0.01)), 3, 25.0)
    grad = Term(EffectKind.FIELD_GRADIENT, yaw_rad=np.radians(25.0))
    lever = Term(EffectKind.LEVER_ARM)
    w = np.random.default_rng(3).normal(size=fm.n_params()) * 100.0
    data, truth_state = make_data(
        (grad, fm, lever), (_gradient_value(G_TRUE), w, np.array([0.03, -0.02, 0.05])),
        duration_s=30.0, rate_hz=100.0, seed=5, noise_nT=0.0, positions=lissajous_m,
        position_frame="attitude_source_local")
    J = evaluate(truth_state, data).J
    eps = np.r_[[1e-6] * 3, [1e-2] * 3, [1e-2] * 5, [1e-2] * fm.n_params(), [1e-5] * 3]
    Jn = _numeric_jacobian(truth_state, data, eps)
    inner = (data.t_s > 0.2) & (data.t_s < data.t_s[-1] - 0.2)
    for k in range(6, truth_state.n_params()):
        a, b = J[inner, :, k], Jn[inner, :, k]
        assert np.max(np.abs(a - b)) / (np.max(np.abs(b)) + 1e-12) < 1e-4, k


def test_a_map_is_recovered_with_the_noise_off():
    """Readings from the model itself (a gradient and a map whose weights are drawn from the
    prior): the ridge fit from zero weights predicts them to a hundredth of a nT."""
    p = lissajous_m(np.arange(0.0, 40.0, 0.02))
    fm = _map_term(p, 3, 0.0, noise_nT=1e-3)
    rng = np.random.default_rng(7)
    w = rng.normal(size=fm.n_params()) * np.sqrt(fm.basis().prior_variance(
        fm.length_scale_m, 50.0))
    grad = Term(EffectKind.FIELD_GRADIENT)
    data, tr = make_data((grad, fm), (_gradient_value(G_TRUE), w), duration_s=40.0,
                         rate_hz=50.0, seed=9, noise_nT=0.0, positions=lissajous_m)
    start = ModelState(tr.R_body_mag, tr.B_enu_nT + 30.0, (grad, fm),
                       (_gradient_value(G_TRUE) * 0.5, np.zeros_like(w)))
    res = fit(start, data, max_iter=60)
    assert res.rms_nT < 0.01  # nT
    # the modelled field along the path is the true one (the split between the gradient
    # and the map's linear part is the prior's, the sum is the data's)
    f_true = evaluate(tr, data, jacobian=False).y_nT
    f_fit = evaluate(res.state, data, jacobian=False).y_nT
    assert np.max(np.abs(f_fit - f_true)) < 0.05  # nT


def test_a_map_candidate_is_charged_for_what_the_path_shows_of_it():
    """The score test's Occam factor of a map candidate (the Laplace evidence's, GP prior).

    Each weight costs the log of how much the data narrow its prior, not a count: the finer
    modes a finer map adds have a smaller prior (the squared-exponential spectrum falls) and
    cost less each than the coarse map's weights.
    """
    from stages.diagnose.statistics import score_from_J

    p = lissajous_m(np.arange(0.0, 40.0, 0.02))
    grad = Term(EffectKind.FIELD_GRADIENT)
    coarse, fine = _map_term(p, 2, 0.0, noise_nT=2.0), _map_term(p, 4, 0.0, noise_nT=2.0)
    rng = np.random.default_rng(3)
    w = rng.normal(size=fine.n_params()) * np.sqrt(fine.basis().prior_variance(
        fine.length_scale_m, 100.0))
    data, tr = make_data((grad, fine), (_gradient_value(G_TRUE), w), duration_s=40.0,
                         rate_hz=50.0, seed=5, noise_nT=2.0, positions=lissajous_m)
    cur = fit(ModelState(tr.R_body_mag, tr.B_enu_nT, (grad,), (_gradient_value(G_TRUE),)), data)
    costs = []
    for term in (coarse, fine):
        J = evaluate(cur.state.with_term(term), data).jac
        J = J.reshape(-1, J.shape[-1])
        st = score_from_J(cur, term, J, data, 2.0, prior=term.prior_precision())
        assert st.penalty > 0.0
        costs.append(st.penalty)
    added = fine.n_params() - coarse.n_params()
    assert costs[0] < costs[1]
    assert (costs[1] - costs[0]) / added < costs[0] / coarse.n_params()


# ----------------------------------------------------------------------------- generator

#: Two magnetised bodies 20-30 m from the survey and 12-15 m deep: over the 6 x 34 m the
#: sensor covers their field is smooth and, beyond its linear part, about 19 nT RMS.
SMOOTH = {"dipoles": [{"position_m": [30.0, 5.0, -15.0], "moment_Am2": [0.0, 2e4, -6e4]},
                      {"position_m": [-20.0, 40.0, -12.0], "moment_Am2": [1e4, 0.0, -3e4]}]}

#: A linear gradient alone (nT/m; symmetric, traceless): the null of the map.
LINEAR = {"field_gradient": {"G_nT_per_m": [[15.0, 4.0, -3.0], [4.0, -9.0, 5.0],
                                            [-3.0, 5.0, -6.0]]}}


def _survey(name: str, effects: dict, seed: int = 11) -> Spec:
    """A ground survey (lines 2 m apart, INSPVA attitude and positions at 20 Hz, 50 Hz
    magnetometer) with the calibration manoeuvre at its start (as the buried-dipole test)."""
    return Spec(name, seed=seed, duration_s=110.0, mag_rate_hz=50.0, att_rate_hz=20.0,
                att_type="novatel_oem7_msgs/msg/INSPVA", path="survey", position_type="inspva",
                survey_calibration_s=30.0, mag_noise_nT=1.0, att_noise_deg=0.002,
                effects=effects)


def test_the_generated_smooth_field_is_minus_the_gradient_of_its_potential():
    """Noise off, before anything is diagnosed: the generator's smooth field is curl-free and
    divergence-free, equals minus the gradient of the dipoles' closed-form potential, and is
    exactly what the generator adds to the field at the magnetometer."""
    spec = _survey("smooth", {"field_map": SMOOTH})
    t = mag_stamps_s(spec)[::25]
    x = sensor_position_m(spec, t)
    B = smooth_field_at(SMOOTH, x)
    h = 1e-3  # m
    K = np.zeros((len(x), 3, 3))
    for d in range(3):
        e = np.zeros(3)
        e[d] = h
        grad_phi = (smooth_potential_at(SMOOTH, x + e) - smooth_potential_at(SMOOTH, x - e))
        assert np.max(np.abs(-grad_phi / (2 * h) - B[:, d])) < 1e-6  # nT
        K[:, :, d] = (smooth_field_at(SMOOTH, x + e) - smooth_field_at(SMOOTH, x - e)) / (2 * h)
    assert np.max(np.abs(K - np.swapaxes(K, 1, 2))) < 1e-6  # nT/m: curl-free
    assert np.max(np.abs(np.trace(K, axis1=1, axis2=2))) < 1e-6  # divergence-free
    plain = dataclasses.replace(spec, effects={})
    assert np.allclose(field_enu(spec, t) - field_enu(plain, t), B, atol=1e-9)
    # far from linear over the survey: the size the diagnosis must find
    assert truth(spec)["effects"]["field_map"]["beyond_linear_rms_nT"] > 10.0


def _found(ctx, effect):
    return [f for f in ctx.diagnosis.findings if f.effect == effect]


def _effects(ctx):
    return [f.effect for f in ctx.diagnosis.findings]


def test_a_survey_through_a_smooth_field_names_the_map_and_restore_keeps_it(tmp_path):
    spec = _survey("smooth", {"field_map": SMOOTH})
    ctx = diagnose_file(write(spec, tmp_path / "smooth.mcap"))
    assert _effects(ctx) == ["field_gradient", "field_map"]
    (fm,) = _found(ctx, "field_map")
    p, ev = fm.params, fm.evidence
    assert set(p) == {"basis", "n_basis", "length_scale_m", "domain_m", "weights",
                      "position_frame", "position_origin", "peak_to_peak_nT"}
    assert p["position_frame"] == "enu" and len(p["weights"]) == p["n_basis"]
    assert p["position_origin"] == pytest.approx(truth(spec)["position_origin"], abs=1e-7)
    # the held-out error over the gradient alone: from the field's curvature to the noise
    # (1 nT per component, 1.7 nT of attitude noise)
    assert ev["heldout_rms_before_nT"] > 15.0
    assert ev["heldout_rms_after_nT"] < 2.5
    assert ev["delta_bic"] < -20.0
    assert "held-out" in fm.explanation and "surroundings" in fm.explanation
    # R within its sigma of the truth (each axis, 2 sigma)
    err = np.abs(np.asarray(ctx.calibration.rotvec_body_mag_deg)
                 - np.asarray(spec.rotvec_body_mag_deg))
    assert np.all(err < 2 * np.asarray(ctx.calibration.sigma_rotvec_deg)), err
    # the calibration's JSON carries the map; loaded again, its model is the same
    cal = Calibration.from_json(ctx.calibration.to_json())
    assert "field_map" in cal.effects
    assert any(isinstance(p, MapPart) for p in cal.forward_model().parts)
    # the modelled spatial field (gradient and map) is the generator's smooth field, up to a
    # constant (B_enu), along the path: positions from the first fix, as the file gives them
    tt = mag_stamps_s(spec)
    first = np.asarray(truth(spec)["first_position_enu_m"])
    F = cal.forward_model().external_field_nT(tt, position_m(spec, tt) - first)
    F_true = smooth_field_at(SMOOTH, position_m(spec, tt))
    d = F - F_true
    assert np.sqrt(np.mean((d - d.mean(axis=0)) ** 2)) < 2.0  # nT, of a 420 nT range
    # restore keeps it in the ENU field (it belongs to the surroundings): the restored field
    # is the background plus the smooth field, to the noise
    rs = restore_samples(ctx.recording, ctx.calibration)
    ok = rs.valid
    t_s = (np.asarray(rs.t_ns)[ok] - int(rs.t_ns[0])) * 1e-9
    expect = np.asarray(spec.B_enu_nT) + smooth_field_at(SMOOTH, position_m(spec, t_s))
    e = np.asarray(rs.enu_nT)[ok] - expect
    assert np.sqrt(np.mean((e - np.median(e, axis=0)) ** 2)) < 5.0  # nT
    assert np.sqrt(np.mean(np.asarray(rs.residual_nT)[ok] ** 2)) < 2.5  # nT


@pytest.mark.parametrize("case", ["linear", "uniform", "lissajous"])
def test_no_map_where_the_field_is_linear_or_uniform(tmp_path, case):
    """Nulls: a survey through a linear gradient, a survey through a uniform field, a
    hand-held path (positions in a frame of unknown bearing) through a linear gradient."""
    if case == "lissajous":
        spec = Spec("lin", seed=15, duration_s=60.0, mag_noise_nT=2.0, effects=LINEAR)
    else:
        spec = _survey(case, LINEAR if case == "linear" else {}, seed=12)
    ctx = diagnose_file(write(spec, tmp_path / f"{case}.mcap"))
    assert "field_map" not in _effects(ctx), _effects(ctx)
    if case != "uniform":
        assert "field_gradient" in _effects(ctx)


def test_a_buried_dipole_by_a_line_stays_a_local_source_beside_the_map(tmp_path):
    """A steel object 2 m below the second line (a compact source, 1/r^3) in a smooth field:
    the object is a ``local_source`` where it is, the rest the map."""
    src = {"position_m": [2.0, 15.0, -1.0], "moment_Am2": [0.0, 20.0, -60.0]}
    spec = _survey("both", {"field_map": SMOOTH, "local_source": src})
    ctx = diagnose_file(write(spec, tmp_path / "both.mcap"))
    assert sorted(_effects(ctx)) == ["field_gradient", "field_map", "local_source"]
    (s,) = _found(ctx, "local_source")
    tr = truth(spec)["effects"]["local_source"]
    assert np.linalg.norm(np.subtract(s.params["position_m"], tr["position_m"])) < 0.05  # m
    assert np.linalg.norm(np.subtract(s.params["moment_Am2"], tr["moment_Am2"])) < 2.0


def test_a_disturbance_stays_a_disturbance_beside_the_map(tmp_path):
    """A passing vehicle (60 nT for 6 s, the same everywhere) while the survey crosses a
    smooth field: named ``disturbance`` in its window, the smooth field the map."""
    dist = {"windows_s": [[70.0, 76.0]], "peak_nT": 60.0, "direction_enu": [0.6, 0.0, 0.8]}
    spec = _survey("dist", {"field_map": SMOOTH, "disturbance": dist})
    ctx = diagnose_file(write(spec, tmp_path / "dist.mcap"))
    assert sorted(_effects(ctx)) == ["disturbance", "field_gradient", "field_map"]
    (d,) = _found(ctx, "disturbance")
    (a, b), = d.params["windows_s"]
    assert a <= 70.0 + 1.0 and b >= 76.0 - 1.0
    assert d.params["peak_nT"] == pytest.approx(60.0, abs=10.0)


def test_the_calibration_json_round_trip_keeps_the_map():
    """The map's weights need their basis: the JSON carries the box, the modes per axis and
    the bearing, and a calibration loaded later predicts alike."""
    b = FieldMapBasis.of([[-1.0, 2.0], [-1.5, 1.5], [0.0, 2.0]], (3, 3, 2))
    w = np.linspace(-50.0, 50.0, b.n_basis)
    eff = {"field_map": {"basis": "laplace_dirichlet_box", "n_basis": b.n_basis,
                         "length_scale_m": 0.5, "domain_m": b.domain_m.tolist(),
                         "weights": w.tolist(), "position_frame": "attitude_source_local",
                         "position_origin": None, "peak_to_peak_nT": [1.0, 2.0, 3.0],
                         "n_per_axis": [3, 3, 2], "frame_yaw_deg": 30.0}}
    cal = Calibration(R_body_mag=np.eye(3), sigma_rotvec_deg=np.zeros(3),
                      B_enu_nT=np.array([0.0, 2e4, -4e4]), estimator="diagnose",
                      residual_rms_nT=1.0, n_samples=10, effects=eff)
    again = Calibration.from_json(json.dumps(json.loads(cal.to_json())))
    m0, m1 = cal.forward_model(), again.forward_model()
    p = np.random.default_rng(1).uniform([-1.0, -1.5, 0.0], [2.0, 1.5, 2.0], (20, 3))
    t = np.linspace(0.0, 1.0, 20)
    f0, f1 = m0.external_field_nT(t, p), m1.external_field_nT(t, p)
    assert np.abs(f0).max() > 1.0 and np.array_equal(f0, f1)
    # the field is the basis' turned by the bearing into ENU
    from pipeline.model.field_map import map_field_enu

    assert np.allclose(f0, map_field_enu(b, w, np.radians(30.0), p))
    # without the basis the map cannot be reproduced: said, not guessed
    del eff["field_map"]["n_per_axis"]
    assert "field_map" in cal.forward_model().unmodelled

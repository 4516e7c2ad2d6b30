"""``local_source``: the point dipole fixed in the surroundings (wiring of the diagnosis model).

These tests make their data with the diagnosis' own model (``_diag_sim``): they check the
Jacobian against finite differences and that a fit from a nearby start finds the source
with the noise off. Whether the physics is right is checked against the independent
generator (``tests/indep_gen.py``) in ``tests/test_local_source_indep.py``.
"""

import numpy as np
import pytest
from _diag_sim import lissajous_m, make_data
from test_effects import _numeric_jacobian

from pipeline.core.vocabulary import EffectKind
from pipeline.model.dipole_kernels import add_dipole_field, dipole_columns
from pipeline.model.forward import dipole_field, dipole_gradient, dipole_matrix
from stages.diagnose.fit import fit
from stages.diagnose.model import ModelState, Term, evaluate, term_params


def test_dipole_field_on_axis_and_equator():
    """B = 100 nT (3 (m.u) u - m) / r^3: 200 nT on the axis and -100 nT on the equator at 1 m."""
    m = np.array([0.0, 0.0, 1.0])
    on_axis = dipole_matrix(np.array([[0.0, 0.0, 1.0]]))[0] @ m
    equator = dipole_matrix(np.array([[1.0, 0.0, 0.0]]))[0] @ m
    assert np.allclose(on_axis, [0, 0, 200.0], atol=1e-9)
    assert np.allclose(equator, [0, 0, -100.0], atol=1e-9)
    # 1/r^3: twice as far, an eighth
    far = dipole_matrix(np.array([[0.0, 0.0, 2.0]]))[0] @ m
    assert np.allclose(far, on_axis / 8, atol=1e-9)


def test_dipole_field_is_the_matrix_times_the_moment():
    """``dipole_field`` (the field alone) and ``dipole_matrix`` (the moment's columns) agree,
    and each matrix is symmetric and traceless (``3 u u' - I``)."""
    rng = np.random.default_rng(2)
    r = rng.normal(size=(50, 3))
    m = np.array([0.3, -1.2, 0.7])
    P = dipole_matrix(r)
    np.testing.assert_allclose(dipole_field(r, m), P @ m, rtol=1e-12, atol=1e-9)
    np.testing.assert_array_equal(P, np.swapaxes(P, 1, 2))
    assert np.allclose(np.trace(P, axis1=1, axis2=2), 0.0, atol=1e-9)


def test_dipole_gradient_matches_finite_differences_and_is_curl_free():
    rng = np.random.default_rng(1)
    r = rng.normal(size=(20, 3))
    m = np.array([0.3, -1.2, 0.7])
    K = dipole_gradient(r, m)
    h = 1e-6
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        num = (dipole_matrix(r + e) @ m - dipole_matrix(r - e) @ m) / (2 * h)
        assert np.allclose(K[:, :, j], num, rtol=1e-6, atol=1e-6)
    assert np.allclose(K, np.swapaxes(K, 1, 2), atol=1e-9)  # curl-free
    assert np.allclose(np.trace(K, axis1=1, axis2=2), 0.0, atol=1e-6)  # divergence-free


@pytest.mark.parametrize("fit_yaw", [False, True])
def test_compiled_columns_are_the_gradient_and_matrix_formulas(fit_yaw):
    """The compiled loop of the source's columns (``dipole_columns``) writes
    ``w G [-K Rz(psi), P, K (e_z x r_p)]`` with ``K`` and ``P`` of ``dipole_gradient`` and
    ``dipole_matrix``, per sample's presence ``w``, into a view of a larger Jacobian; and the
    compiled field adds ``w P m`` in place. Samples from 2 cm to 30 m, where the field spans
    nine orders of magnitude."""
    rng = np.random.default_rng(7)
    n = 400
    r = rng.normal(size=(n, 3)) * np.geomspace(0.02, 30.0, n)[:, None]
    r_p = rng.normal(size=(n, 3))
    m = np.array([4.0, -1.5, 2.5])
    G = rng.normal(size=(n, 3, 3))
    w = rng.uniform(0.0, 1.0, n)
    psi = 0.7
    K, P = dipole_gradient(r, m), dipole_matrix(r)
    c, s = np.cos(psi), np.sin(psi)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    dB = np.concatenate([-(K @ Rz), P], axis=2)
    if fit_yaw:
        ez_r = np.stack([-r_p[:, 1], r_p[:, 0], np.zeros(n)], axis=1)
        dB = np.concatenate([dB, (K @ ez_r[:, :, None])], axis=2)
    want = w[:, None, None] * (G @ dB)
    J = np.full((n, 3, 10), np.nan)
    cols = slice(2, 2 + dB.shape[2])
    dipole_columns(r, m, psi, G, r_p if fit_yaw else None, w, J[:, :, cols])
    scale = np.max(np.abs(want), axis=(0, 1))
    assert np.all(np.abs(J[:, :, cols] - want) <= 1e-13 * scale)
    assert np.isnan(np.delete(J, np.r_[cols], axis=2)).all()  # nothing written beside
    B = np.full((n, 3), 5.0)
    add_dipole_field(r, m, B, w)
    np.testing.assert_allclose(B, 5.0 + w[:, None] * (P @ m), rtol=1e-12, atol=1e-12)


def _source_data(fit_yaw: bool, noise_nT: float = 0.0, psi_deg: float = 25.0):
    term = Term(EffectKind.LOCAL_SOURCE, fit_yaw=fit_yaw,
                yaw_rad=0.0 if fit_yaw else np.radians(psi_deg))
    # the source 0.15 m below where the path is at t = 7 s
    c = lissajous_m(np.array([7.0]))[0] + np.array([0.0, 0.0, -0.15])
    value = np.r_[c, 0.4, -0.2, 0.3]
    if fit_yaw:
        value = np.append(value, np.radians(psi_deg))
    frame = "attitude_source_local" if fit_yaw else "enu"
    data, truth = make_data((term,), (value,), duration_s=30.0, rate_hz=100.0, seed=5,
                            noise_nT=noise_nT,
                            positions=lissajous_m,
                            position_frame=frame)
    return term, value, data, truth


@pytest.mark.parametrize("fit_yaw", [False, True])
def test_source_jacobian_matches_finite_differences(fit_yaw):
    term, value, data, truth = _source_data(fit_yaw)
    J = evaluate(truth, data).J
    eps = np.r_[[1e-6] * 3, [1e-2] * 3, [1e-5] * 3, [1e-5] * 3, [1e-6] * (len(value) - 6)]
    Jn = _numeric_jacobian(truth, data, eps)
    inner = (data.t_s > 0.2) & (data.t_s < data.t_s[-1] - 0.2)
    blk = slice(6, 6 + term.n_params())
    a, b = J[inner, :, blk], Jn[inner, :, blk]
    for k in range(term.n_params()):
        scale = np.max(np.abs(b[:, :, k])) + 1e-12
        assert np.max(np.abs(a[:, :, k] - b[:, :, k])) / scale < 1e-4, k


@pytest.mark.parametrize("fit_yaw", [False, True])
def test_source_noise_off_is_recovered(fit_yaw):
    term, value, data, truth = _source_data(fit_yaw)
    start = value.copy()
    start[0:3] += [0.05, -0.04, 0.03]  # 7 cm off
    start[3:6] *= 0.7
    if fit_yaw:
        start[6] += np.radians(8.0)
    st = ModelState(truth.R_body_mag, truth.B_enu_nT, (term,), (start,))
    res = fit(st, data, max_iter=80)
    assert res.rms_nT < 1e-3  # nT
    got = res.state.values[0]
    assert np.max(np.abs(got[0:3] - value[0:3])) < 1e-5  # m
    assert np.max(np.abs(got[3:6] - value[3:6])) < 1e-5  # A m^2
    p = term_params(term, got, res.state, data)
    assert p["position_frame"] == ("attitude_source_local" if fit_yaw else "enu")
    d = np.linalg.norm(data.p_m - value[0:3], axis=1)  # the path against the true source
    assert abs(p["closest_approach_m"] - d.min()) < 1e-5
    assert p["closest_approach_m"] <= 0.15
    assert abs(p["closest_approach_s"] - data.t_s[np.argmin(d)]) < 0.02
    assert p["windows_s"] == [[0.0, pytest.approx(float(data.track.t_s[-1]))]]


@pytest.mark.parametrize("fit_yaw", [False, True])
def test_lever_arm_jacobian_with_a_source_and_a_gradient(fit_yaw):
    """The lever arm moves every spatial term: its columns and theirs against finite differences."""
    from test_effects import G_TRUE, _gradient_value

    term, value, data, truth = _source_data(fit_yaw)
    grad = Term(EffectKind.FIELD_GRADIENT, yaw_rad=np.radians(25.0))
    lever = Term(EffectKind.LEVER_ARM)
    st = ModelState(truth.R_body_mag, truth.B_enu_nT, (term, grad, lever),
                    (value, _gradient_value(G_TRUE), np.array([0.03, -0.02, 0.05])))
    J = evaluate(st, data).J
    eps = np.r_[[1e-6] * 3, [1e-2] * 3, [1e-5] * 3, [1e-5] * 3, [1e-6] * (len(value) - 6),
                [1e-2] * 5, [1e-5] * 3]
    Jn = _numeric_jacobian(st, data, eps)
    inner = (data.t_s > 0.2) & (data.t_s < data.t_s[-1] - 0.2)
    for k in range(6, st.n_params()):
        a, b = J[inner, :, k], Jn[inner, :, k]
        scale = np.max(np.abs(b)) + 1e-12
        assert np.max(np.abs(a - b)) / scale < 1e-4, k


def test_lever_arm_noise_off_is_recovered_near_a_source():
    term, value, data, truth = _source_data(False)
    lever = Term(EffectKind.LEVER_ARM)
    l_true = np.array([0.03, -0.02, 0.05])
    truth = ModelState(truth.R_body_mag, truth.B_enu_nT, (term, lever), (value, l_true))
    y = evaluate(truth, data, jacobian=False).y_nT
    import dataclasses

    data = dataclasses.replace(data, y_nT=y)
    start = ModelState(truth.R_body_mag, truth.B_enu_nT, (term, lever),
                       (value + np.r_[0.02, 0.01, -0.02, 0, 0, 0], np.zeros(3)))
    res = fit(start, data, max_iter=100)
    assert res.rms_nT < 1e-3
    assert np.max(np.abs(res.state.values[1] - l_true)) < 1e-5  # m

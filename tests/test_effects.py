"""The diagnosis' effect terms: Jacobians, fit, identifiability.

Tests named ``test_wiring_*`` are self-model tests: their data come from
``tests/_diag_sim.py``, which makes them with ``stages.diagnose.model.evaluate``, the model
the diagnosis fits. They check the wiring (search, fit, Jacobians, evidence, output),
not the physics: a sign or convention error shared by the model and the data passes
them. The physics of the terms is checked on ``tests/indep_gen.py``
recordings (``tests/test_model_independent.py``, ``tests/test_indep_corpus.py``).
"""

import numpy as np
import pytest
from _diag_sim import all_terms, lissajous_m, make_data

from pipeline.core.geometry import so3_exp
from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects import EFFECTS, Effect
from pipeline.model.forward import hat_basis
from pipeline.model.solve import normal_equations
from stages.diagnose.catalogue import motion_stats
from stages.diagnose.fit import fit, wahba_init
from stages.diagnose.model import FitData, ModelState, Term, evaluate, row_spans


def _numeric_jacobian(state: ModelState, data: FitData, eps: np.ndarray) -> np.ndarray:
    P = state.n_params()
    J = np.zeros((len(data), 3, P))
    for k in range(P):
        dx = np.zeros(P)
        dx[k] = eps[k]
        yp = evaluate(state.update(dx), data, jacobian=False).y_nT
        ym = evaluate(state.update(-dx), data, jacobian=False).y_nT
        J[:, :, k] = (yp - ym) / (2 * eps[k])
    return J


def _eps(state: ModelState) -> np.ndarray:
    eps = [1e-6] * 3 + [1e-2] * 3
    for t in state.terms:
        e = {
            EffectKind.TIME_OFFSET: 1e-4,
            EffectKind.SOFT_IRON: 1e-5,
            EffectKind.EDDY_CURRENT: 1e-6,
            EffectKind.AXIS_TILT: 1e-6,
        }.get(t.kind, 1e-2)
        eps += [e] * t.n_params()
    return np.array(eps)


@pytest.mark.parametrize("with_tilt_field", [False, True])
def test_wiring_jacobian_matches_finite_differences(with_tilt_field):
    terms, vals = all_terms()
    data, truth = make_data(terms, vals, duration_s=40.0, rate_hz=100.0, seed=3)
    if with_tilt_field:
        data = FitData(data.t_s, data.y_nT, data.track, B_known_enu_nT=truth.B_enu_nT)
        # non-zero tilt so the Jacobian is checked away from identity
        truth = ModelState(truth.R_body_mag, truth.B_enu_nT, truth.terms, truth.values,
                           so3_exp(np.radians([0.5, -0.3, 0.0])))
    J = evaluate(truth, data).J
    Jn = _numeric_jacobian(truth, data, _eps(truth))
    if with_tilt_field:
        Jn[:, :, 3:6] = 0.0  # B is held at the reference
    # the attitude track is held constant outside its span: compare away from the ends
    inner = (data.t_s > 0.2) & (data.t_s < data.t_s[-1] - 0.2)
    for (start, stop), name in _blocks(truth):
        a, b = J[inner, :, start:stop], Jn[inner, :, start:stop]
        scale = np.max(np.abs(b)) + 1e-12
        # slerp tracks are piecewise smooth: time-derivative terms agree to ~1 %
        tol = 2e-2 if name in ("time_offset",) else 1e-4
        assert np.max(np.abs(a - b)) / scale < tol, name


def _blocks(state):
    out = [((0, 3), "R"), ((3, 6), "B")]
    for t, i in zip(state.terms, state.offsets(), strict=True):
        out.append(((i, i + t.n_params()), t.kind.value))
    return out


def test_wiring_time_offset_is_isotropic_eddy_current():
    """Nesting: E_s = -tau I reproduces a small time offset to first order."""
    tau = 0.01
    d1, _ = make_data((Term(EffectKind.TIME_OFFSET),), (np.array([tau]),), noise_nT=0.0, seed=1)
    d2, _ = make_data((Term(EffectKind.EDDY_CURRENT),), ((-tau * np.eye(3)).ravel(),),
                      noise_nT=0.0, seed=1)
    d0, _ = make_data(noise_nT=0.0, seed=1)
    inner = (d0.t_s > 0.1) & (d0.t_s < d0.t_s[-1] - 0.1)
    effect = np.abs(d1.y_nT - d0.y_nT)[inner].max()
    assert effect > 50.0  # the effect itself is large
    assert np.abs(d1.y_nT - d2.y_nT)[inner].max() < 0.02 * effect


def test_wiring_fit_recovers_every_global_effect():
    terms = (Term(EffectKind.HARD_IRON), Term(EffectKind.SOFT_IRON), Term(EffectKind.TIME_OFFSET))
    vals = (np.array([800.0, -400.0, 250.0]), np.array([0.03, -0.02, 0.01, 0.005, -0.01]),
            np.array([0.015]))
    data, truth = make_data(terms, vals, noise_nT=5.0, seed=2)
    init = wahba_init(data)
    for t in terms:
        init = init.with_term(t)
    res = fit(init, data)
    assert res.rms_nT < 5.5
    assert np.degrees(np.linalg.norm(
        so3_exp(np.zeros(3)) - res.state.R_body_mag @ truth.R_body_mag.T)) < 0.05
    np.testing.assert_allclose(res.state.value(EffectKind.HARD_IRON), vals[0], atol=5.0)
    np.testing.assert_allclose(res.state.tau_s(), 0.015, atol=5e-4)
    np.testing.assert_allclose(res.state.D(), truth.D(), atol=1e-3)


def test_hat_basis_partition_of_unity():
    k = np.linspace(2.0, 6.0, 5)
    t = np.linspace(0.0, 8.0, 801)
    phi = hat_basis(t, k)
    inside = (t >= 2.0) & (t < 6.0)
    np.testing.assert_allclose(phi[inside].sum(axis=1), 1.0, atol=1e-12)
    assert np.all(phi[~inside] == 0.0)


def test_motion_stats_single_axis_and_tumble():
    d1, _ = make_data(single_axis=True, seed=0)
    d3, _ = make_data(seed=0)
    s1, s3 = motion_stats(d1), motion_stats(d3)
    assert s1.axis_spread < 0.01
    assert s3.axis_spread > 0.05
    assert abs(abs(s1.main_axis_body[2]) - 1.0) < 1e-3


def test_every_effect_has_words():
    assert set(EFFECTS) == set(EffectKind)
    for info in EFFECTS.values():
        assert len(info.physics) > 40 and info.frame in ("mag", "enu")


def test_field_drift_explanation_names_both_causes_and_the_gradient_limit():
    from stages.diagnose.catalogue import explanation

    # 20 nT over an hour: geomagnetic; 1700 nT over 3 minutes: the sensor moved through a
    # non-uniform field
    slow = explanation(EffectKind.FIELD_DRIFT, {"peak_to_peak_nT": [5.0, 20.0, 8.0]}, 3600.0)
    fast = explanation(EffectKind.FIELD_DRIFT, {"peak_to_peak_nT": [300.0, 1700.0, 900.0]}, 180.0)
    for text in (slow, fast):
        assert "diurnal" in text and "position" in text and "non-uniform" in text
        assert "gradient cannot be separated" in text
    assert "within the range of" in slow and "spatially varying" not in slow
    assert "spatially varying field" in fast and "566.7 nT/min" in fast
    assert explanation(EffectKind.HARD_IRON, {"offset_nT": [1.0, 0, 0]}, 60.0).startswith(
        EFFECTS[EffectKind.HARD_IRON].physics)


# ----------------------------------------------------------------------------- field gradient

# ENU gradient, symmetric and traceless, nT/m (a few uT/m, as indoors)
G_TRUE = np.array([[1200.0, -800.0, 1500.0], [-800.0, -3000.0, 600.0], [1500.0, 600.0, 1800.0]])


def _gradient_value(G: np.ndarray) -> np.ndarray:
    """Coefficients of G on the symmetric traceless basis."""
    from pipeline.model.effects.soft_iron import SOFT_BASIS

    A = SOFT_BASIS.reshape(5, 9).T
    v, *_ = np.linalg.lstsq(A, G.ravel(), rcond=None)
    assert np.allclose(A @ v, G.ravel())
    return v


@pytest.mark.parametrize("yaw_deg", [0.0, 35.0])
def test_wiring_gradient_jacobian_matches_finite_differences(yaw_deg):
    terms = (Term(EffectKind.HARD_IRON), Term(EffectKind.FIELD_DRIFT),
             Term(EffectKind.FIELD_GRADIENT, yaw_rad=np.radians(yaw_deg)),
             Term(EffectKind.EDDY_CURRENT))
    _, vals = all_terms()
    values = (vals[0], vals[4], _gradient_value(G_TRUE), vals[3])
    frame = "enu" if yaw_deg == 0 else "attitude_source_local"
    data, truth = make_data(terms, values, duration_s=30.0, rate_hz=100.0, seed=4,
                            positions=lissajous_m, position_frame=frame)
    J = evaluate(truth, data).J
    Jn = _numeric_jacobian(truth, data, _eps(truth))
    inner = (data.t_s > 0.2) & (data.t_s < data.t_s[-1] - 0.2)
    for (start, stop), name in _blocks(truth):
        a, b = J[inner, :, start:stop], Jn[inner, :, start:stop]
        scale = np.max(np.abs(b)) + 1e-12
        assert np.max(np.abs(a - b)) / scale < 1e-4, name


def test_wiring_gradient_noise_off_is_recovered_to_numerical_precision():
    """Noise off: a gradient along a path (positions in a frame yawed 35 deg) is recovered."""
    from stages.diagnose.model import term_params

    yaw = np.radians(35.0)
    term = Term(EffectKind.FIELD_GRADIENT, yaw_rad=yaw)
    data, truth = make_data((term,), (_gradient_value(G_TRUE),), noise_nT=0.0, seed=2,
                            positions=lissajous_m, position_frame="attitude_source_local")
    res = fit(ModelState(np.eye(3), np.zeros(3)).with_term(term), data)
    assert res.rms_nT < 1e-6
    M = np.asarray(term_params(term, res.state.values[0], res.state, data)["G_nT_per_m"])
    from stages.diagnose.model import rot_z

    assert np.max(np.abs(M - G_TRUE @ rot_z(yaw))) < 1e-6  # nT/m
    p = term_params(term, res.state.values[0], res.state, data)
    assert p["position_frame"] == "attitude_source_local"
    assert np.allclose(p["reference_position_m"], data.p_m.mean(axis=0), atol=1e-12)


def test_gradient_yaw_is_read_back_from_the_matrix():
    from pipeline.model.effects.field_gradient import yaw_of_gradient
    from stages.diagnose.model import rot_z

    for deg in (0.0, 35.0, 120.0, -70.0):
        got = np.degrees(yaw_of_gradient(G_TRUE @ rot_z(np.radians(deg))))
        assert abs((got - deg + 180.0) % 360.0 - 180.0) < 0.5


def test_wiring_gradient_identifiability_needs_positions_that_are_not_time():
    from stages.diagnose.catalogue import identifiability_reason

    st = None
    # no positions
    data, _ = make_data(seed=1, duration_s=30.0)
    st = motion_stats(data)
    why = identifiability_reason(EffectKind.FIELD_GRADIENT, st, data, 1.0)
    assert why is not None and "no positions" in why
    # a sensor that stays put (1 mm of jitter)
    data, _ = make_data(seed=1, duration_s=30.0, positions=lambda t: 1e-3 * np.sin(
        np.stack([t, 2 * t, 3 * t], -1)))
    why = identifiability_reason(EffectKind.FIELD_GRADIENT, st, data, 1.0)
    assert why is not None and "hardly moved" in why
    # a slow straight walk: position is a function of time, a drift mimics any gradient
    data, _ = make_data(seed=1, duration_s=30.0, positions=lambda t: np.stack(
        [0.05 * t, 0.02 * t, 0 * t], -1))
    why = identifiability_reason(EffectKind.FIELD_GRADIENT, st, data, 1.0)
    assert why is not None and "function of time" in why
    # a path that comes back to the same places
    data, _ = make_data(seed=1, duration_s=30.0, positions=lissajous_m)
    assert identifiability_reason(EffectKind.FIELD_GRADIENT, st, data, 1.0) is None


def test_field_drift_explanation_with_positions_says_what_the_gradient_test_found():
    from stages.diagnose.catalogue import explanation

    note = "with the positions, a spatial gradient was tested: not found"
    text = explanation(EffectKind.FIELD_DRIFT, {"peak_to_peak_nT": [300.0, 1700.0, 900.0]},
                       180.0, note=note)
    assert note in text and "cannot be separated" not in text


def test_every_model_term_writes_its_own_params_and_sigmas():
    # the registry, not a switch, answers for the outputs: every term of the forward model
    # (sample_hold is handled on the data) overrides both

    for kind, eff in EFFECTS.items():
        if kind is EffectKind.SAMPLE_HOLD:
            continue
        assert type(eff).params is not Effect.params, kind
        assert type(eff).sigma is not Effect.sigma, kind


def test_a_tilt_fitted_in_part_turns_the_frame_by_its_own_step():
    """A tilt held to one combination (the angle to a known field) turns ``T_enu`` by
    ``P A z``, and the term after it keeps its own step: the frame's turn reads the tilt's
    determined step, not the next term's parameters."""
    from pipeline.model.effects.axis_tilt import tilt_basis

    a = np.array([0.6, 0.8])  # the determined combination, unit length
    tilt = Term(EffectKind.AXIS_TILT).restricted(a[:, None])
    iron = Term(EffectKind.HARD_IRON)
    st = ModelState(np.eye(3), np.array([0.0, 20000.0, -40000.0]), (tilt, iron),
                    (tilt.null_value(), iron.null_value()))
    assert st.n_params() == 6 + 1 + 3
    dx = np.zeros(st.n_params())
    dx[6] = 1e-3  # rad along the combination
    dx[7:10] = [5.0, -3.0, 2.0]  # nT
    up = st.update(dx)
    np.testing.assert_allclose(up.T_enu, so3_exp(tilt_basis() @ (1e-3 * a)), atol=1e-15)
    np.testing.assert_allclose(up.values[1], [5.0, -3.0, 2.0])
    # and the frame goes with the term
    assert np.array_equal(up.with_terms(up.terms[1:], up.values[1:]).T_enu, np.eye(3))


def test_relations_between_effects_are_declared_consistently():
    """What each effect declares about the others holds together, and the search reads it.

    A contained effect is a whole term; a term described over its window is an event
    described by an event with a shortest window; only events merge, and each that does can
    start the merged term; every effect a term acts through or trades with is registered; the
    nested tables are the declarations, read from the registry.
    """
    from stages.diagnose.nested import ABSORBING, LOOKALIKES, NESTED, NESTED_SIMPLER, REQUIRES

    for kind, eff in EFFECTS.items():
        if eff.contains is not None:
            assert not EFFECTS[eff.contains].event, kind
            assert NESTED_SIMPLER[kind] is eff.contains
        if eff.in_window is not None:
            assert eff.event and EFFECTS[eff.in_window].event, kind
            assert EFFECTS[eff.in_window].min_window_s > 0, kind
        if eff.merges:
            assert eff.event, kind
            assert type(eff).merged_start is not Effect.merged_start, kind
        for other in eff.trades_with | eff.acts_through:
            assert other in EFFECTS and other is not kind
        assert LOOKALIKES.get(kind, frozenset()) == eff.trades_with
        assert REQUIRES.get(kind, frozenset()) == eff.acts_through
        assert (kind in ABSORBING) == eff.absorbing
        assert (kind in NESTED) == bool(eff.contains or eff.in_window or eff.merges
                                        or eff.shares_with)


def test_every_fitted_effect_is_offered_by_the_search():
    """Each effect with parameters reaches the search one way: every round, at an event, or
    by its own candidate (the map, tried after the others); an effect offered every round is
    no event and has a fixed count of parameters."""
    from stages.diagnose.candidates import AT_EVENT
    from stages.diagnose.search import GLOBAL_KINDS

    for kind, eff in EFFECTS.items():
        if eff.each_round:
            assert not eff.event and eff.n_fixed is not None, kind
        if kind is EffectKind.SAMPLE_HOLD:
            continue  # found from the repeats of the readings, not fitted
        assert eff.each_round or kind in AT_EVENT or eff.absorbing, kind
    assert GLOBAL_KINDS[0] is EffectKind.HARD_IRON  # CONVENTIONS' order, not the import's


def test_windowed_columns_vanish_outside_their_windows_and_the_normal_equations_agree():
    """``Effect.column_windows`` is what ``columns`` writes: zero at every other sample.

    A step with transitions, a disturbance and a source present in a window, beside every
    global effect; the normal equations summed over the windows alone equal the full product
    to rounding.
    """
    terms, vals = all_terms()
    step = Term(EffectKind.HARD_IRON_STEP, ((31.0, 37.0),), knot_step_s=0.1,
                ramps_s=((31.0, 31.6), (36.5, 37.0)), ramp_scale_s=0.1, prior_nT=1e4,
                noise_nT=10.0)
    source = Term(EffectKind.LOCAL_SOURCE, ((5.0, 12.0),))
    rng = np.random.default_rng(4)
    terms = (*terms, step, source)
    vals = (*vals, rng.normal(size=step.n_params()) * 100.0,
            np.array([0.3, -0.2, 0.1, 0.5, -0.4, 0.8]))
    data, truth = make_data(terms, vals, duration_s=40.0, rate_hz=100.0, seed=5,
                            positions=lambda t: lissajous_m(t) + np.array([1.0, 0.5, 0.2]))
    J = evaluate(truth, data).J
    spans = row_spans(truth, data.t_s)
    kinds = {truth.terms[k].kind for k, o in enumerate(truth.offsets())
             for i, _, _, _ in spans if o <= i < o + truth.terms[k].n_params()}
    assert kinds == {EffectKind.HARD_IRON_STEP, EffectKind.DISTURBANCE, EffectKind.LOCAL_SOURCE}
    for i, j, a, b in spans:
        assert 0 <= a < b <= len(data)
        outside = np.ones(len(data), dtype=bool)
        outside[a:b] = False
        assert np.all(J[outside, :, i:j] == 0.0), (i, j)
        assert np.any(J[a:b, :, i:j] != 0.0), (i, j)
    r = data.y_nT - evaluate(truth, data, jacobian=False).y_nT
    H0, g0 = normal_equations(J, r)
    H1, g1 = normal_equations(J, r, spans)
    np.testing.assert_allclose(H1, H0, rtol=1e-12, atol=1e-12 * np.abs(H0).max())
    np.testing.assert_allclose(g1, g0, rtol=1e-12, atol=1e-12 * np.abs(g0).max())
    np.testing.assert_array_equal(H1, H1.T)


def test_windowed_terms_on_stamps_out_of_order_equal_those_in_order():
    """A step's and a disturbance's field and columns, computed on their windows' samples
    alone (``window_rows``), do not depend on the stamps' order."""
    terms, vals = all_terms()
    data, truth = make_data(terms, vals, duration_s=40.0, rate_hz=50.0, seed=6)
    order = np.random.default_rng(6).permutation(len(data))
    shuffled = FitData(data.t_s[order], data.y_nT[order], data.track)
    a, b = evaluate(truth, data), evaluate(truth, shuffled)
    np.testing.assert_allclose(b.y_nT, a.y_nT[order], rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.J, a.J[order], rtol=0, atol=1e-9)

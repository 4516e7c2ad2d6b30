"""Streaming soft iron and time offset (issue 18): sums over every sample, one pass.

The model and the Jacobian are in :mod:`stages.estimators.streaming`'s docstring. Checked
here: the Jacobian against finite differences; the cost and normal equations from the sums
against the sample-by-sample definitions; the second-order expansion of the attitude against
the exact attitude at ``t - tau``; the same sums and fit for any split into blocks; agreement
with the in-memory ML estimator on the project's simulator and on the independent generator
(``tests/indep_gen.py``), noise-free and noisy; the covariance by fitting two halves.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import numpy as np
import pytest
import tomllib

from pipeline.core.geometry import quat_to_matrix, so3_exp, so3_log
from pipeline.core.recording import AttitudeSeries
from pipeline.core.vocabulary import EstimateTerm
from pipeline.model.attitude import interpolate_attitude
from stages.context import Context
from stages.estimators.base import EstimationProblem
from stages.estimators.ml import MLEstimator
from stages.estimators.streaming import (
    MAX_BLOCKS,
    NG,
    StreamAccumulator,
    StreamStats,
    _Design,
    _Full,
    fit_stats,
    full_cost,
    full_normal_equations,
)

sys.path.insert(0, str(Path(__file__).parent))
import indep_gen  # noqa: E402

SCENARIOS = Path(__file__).parents[1] / "pipeline" / "scenarios"
D_TRUE = np.array([[1.05, 0.02, -0.01], [0.02, 0.97, 0.015], [-0.01, 0.015, 0.98]])
D_TRUE = D_TRUE * 3.0 / np.trace(D_TRUE)  # trace 3: the normalisation when B is estimated
OFFSET = [40.0, -20.0, 10.0]
ALL = frozenset({EstimateTerm.OFFSET, EstimateTerm.SOFT_IRON, EstimateTerm.TIME_OFFSET})


def rot_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(so3_log(Ra @ Rb.T))))


# ----------------------------------------------------------------------------- data
@functools.cache
def simulated(gen: str, tau: float, soft: bool, noise: bool, seed: int = 3, duration_s=60.0):
    """Aligned samples and the raw attitude of a simulation: ``(t, y, q, attitude, D)``."""
    D = D_TRUE if soft else None
    if gen == "simulate":
        from pipeline.app.simulate import scenario_from_dict, simulate

        d = tomllib.loads((SCENARIOS / "multiaxis.toml").read_text())
        d["timing"]["duration_s"] = duration_s
        eff: dict = {}
        if tau:
            eff["time_offset"] = {"time_offset_s": tau}
        if soft:
            eff["soft_iron"] = {"D": D_TRUE.tolist()}
            eff["hard_iron"] = {"offset_nT": OFFSET}
        d["effects"] = eff
        if not noise:
            d["noise"] = {"mag_sigma_nT": 0.0, "heading_sigma_deg": 0.0,
                          "pitch_roll_sigma_deg": 0.0}
        rec = simulate(scenario_from_dict(d), seed=seed).recording
        assert rec.attitude is not None
        t_mag, y, att = rec.mag.t_ns, rec.mag.values, rec.attitude
    else:
        eff = {}
        if tau:
            eff["time_offset"] = {"time_offset_s": tau}
        if soft:
            eff["soft_iron"] = {"D": D_TRUE.tolist()}
            eff["hard_iron"] = {"offset_nT": OFFSET}
        spec = indep_gen.Spec("streaming", seed, duration_s=duration_s, effects=eff,
                              att_noise_deg=0.005 if noise else 0.0,
                              mag_noise_nT=1.0 if noise else 0.0)
        r = indep_gen.readings(spec)
        t_mag = indep_gen.T0_NS + np.round(r["t_mag_s"] * 1e9).astype(np.int64)
        t_att = indep_gen.T0_NS + np.round(r["t_att_s"] * 1e9).astype(np.int64)
        att = AttitudeSeries(t_att, r["att"].as_quat())
        y = r["mag_nT"]
    q, ok = interpolate_attitude(att, t_mag, max_gap_s=0.1)
    return t_mag[ok], y[ok], q[ok], att, D


def stream_fit(t, y, q, terms, cuts=None, **kw):
    acc = StreamAccumulator(**kw)
    edges = [0, *(cuts or []), len(t)]
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        acc.add(q[a:b], y[a:b], t[a:b])
    return fit_stats(acc.result(), estimate_offset=EstimateTerm.OFFSET in terms,
                     estimate_soft_iron=EstimateTerm.SOFT_IRON in terms,
                     estimate_time_offset=EstimateTerm.TIME_OFFSET in terms)


def ml_fit(t, y, q, att, terms):
    p = EstimationProblem(t_ns=t, mag_nT=y, q_enu_body=q, attitude=att, terms=frozenset(terms))
    return MLEstimator(checks=False).fit(p)


# ----------------------------------------------------------------------------- model
def _random_state(rng, B_free: bool) -> _Full:
    D = np.eye(3) + 0.05 * rng.standard_normal((3, 3))
    D = 0.5 * (D + D.T)
    if not B_free:
        D = D * 1.2
    return _Full(so3_exp(rng.normal(0, 0.5, 3)), rng.normal(0, 30_000, 3),
                 rng.normal(0, 50, 3), D, float(rng.normal(0, 0.02)))


@pytest.mark.parametrize("B_free", [True, False])
def test_jacobian_matches_finite_differences(B_free):
    """dm/dx of the model (module docstring) against central differences of m itself."""
    rng = np.random.default_rng(1)
    design = _Design(B_free, True, True, True)
    s = _random_state(rng, B_free)
    g = np.concatenate([np.ones((7, 1)), quat_to_matrix(rng.normal(size=(7, 4))).reshape(7, 9),
                        rng.normal(0, 0.5, (7, 9)), rng.normal(0, 0.3, (7, 9))], axis=1)
    _m, J = design.predict(g, s)
    assert J is not None and J.shape == (7, 3, design.n_params)
    # steps of about 1e-6 of each parameter's scale
    scale = np.ones(design.n_params)
    scale[design.blocks["rot"]] = 1e-6
    if "B" in design.blocks:
        scale[design.blocks["B"]] = 1e-2
    scale[design.blocks["offset"]] = 1e-4
    scale[design.blocks["D"]] = 1e-7
    scale[design.blocks["tau"]] = 1e-7
    for p in range(design.n_params):
        dx = np.zeros(design.n_params)
        dx[p] = scale[p]
        mp, _ = design.predict(g, design.step(s, dx), with_jacobian=False)
        mm, _ = design.predict(g, design.step(s, -dx), with_jacobian=False)
        fd = (mp - mm) / (2 * scale[p])
        np.testing.assert_allclose(J[:, :, p], fd, rtol=1e-6,
                                   atol=1e-6 * np.max(np.abs(fd)) + 1e-9, err_msg=str(p))


def _g_uniform(q: np.ndarray, k: int, dt_s: float) -> np.ndarray:
    """Independent expanded attitude on a uniform grid: central differences over +-k."""
    C = quat_to_matrix(q).reshape(-1, 9)
    h = k * dt_s
    c = C[k:-k]
    d1 = (C[2 * k:] - C[:-2 * k]) / (2 * h)
    d2 = (C[2 * k:] - 2 * c + C[:-2 * k]) / h**2
    return np.concatenate([np.ones((len(c), 1)), c, -d1, 0.5 * d2], axis=1)


def test_sums_give_the_sample_by_sample_cost_and_normal_equations():
    t, y, q, _att, _D = simulated("indep", 0.01, True, True)
    t, y, q = t[:3000], y[:3000], q[:3000]
    acc = StreamAccumulator(baseline_s=0.05)
    acc.add(q, y, t)
    st = acc.result()
    g = _g_uniform(q, 5, 0.01)  # 100 Hz, h = 50 ms
    yi = y[5:-5]
    assert st.n == 3000 and st.n_tau == len(g)
    np.testing.assert_allclose(st.Wg, g.T @ g, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(st.Yg, g.T @ yi, rtol=1e-9, atol=1e-3)
    design = _Design(True, True, True, True)
    s = _random_state(np.random.default_rng(2), True)
    m, J = design.predict(g, s)
    assert J is not None
    r = yi - m
    assert full_cost(st.Wg, st.Yg, st.yy, design, s) == pytest.approx(float((r**2).sum()),
                                                                        rel=1e-8)
    H, grad = full_normal_equations(st.Wg, st.Yg, design, s)
    np.testing.assert_allclose(H, np.einsum("nki,nkj->ij", J, J), rtol=1e-8,
                               atol=1e-8 * np.abs(H).max())
    Jr = np.einsum("nki,nk->i", J, r)
    np.testing.assert_allclose(grad, Jr, rtol=1e-6, atol=1e-6 * np.abs(Jr).max())


def test_expansion_truncation_error_is_as_stated():
    """|C(t - tau) - P(tau)| <= tau^3 |d3C/dt3| / 6 plus the stencil's h^2 / 6 |d3C/dt3| tau.

    A steady turn at omega = 0.7 rad/s about a tilted axis (|d3C/dt3| = omega^3), 100 Hz.
    """
    omega, h = 0.7, 0.05
    axis = np.array([0.3, -0.2, 0.93])
    axis /= np.linalg.norm(axis)
    ts = np.arange(0, 5.0, 0.01)

    def C(t_s):
        return np.stack([so3_exp(omega * x * axis) for x in np.atleast_1d(t_s)])

    from pipeline.core.geometry import matrix_to_quat

    q = matrix_to_quat(C(ts))
    g = _g_uniform(q, 5, 0.01)
    mid = ts[5:-5]
    for tau in (0.002, 0.01, 0.04, -0.04):
        P = (g[:, 1:10] + tau * g[:, 10:19] + tau**2 * g[:, 19:28]).reshape(-1, 3, 3)
        err = np.max(np.linalg.norm(P - C(mid - tau), axis=(1, 2)) / np.sqrt(3))
        bound = omega**3 * (abs(tau) ** 3 / 6 + abs(tau) * h**2 / 6 + tau**2 * h**2 / 12)
        assert err <= 1.05 * bound, (tau, err, bound)
    # the accumulator's three-point stencil gives the same expansion on this grid
    acc = StreamAccumulator(baseline_s=h)
    acc.add(q, np.zeros((len(q), 3)), (ts * 1e9).round().astype(np.int64))
    np.testing.assert_allclose(acc.result().Wg, g.T @ g, rtol=1e-9, atol=1e-9)


# ----------------------------------------------------------------------------- blocks
def _with_gap(t, y, q):
    """Drop 0.5 s in the middle: stencils must not cross the gap."""
    keep = (t < t[0] + 20_000_000_000) | (t >= t[0] + 20_500_000_000)
    return t[keep], y[keep], q[keep]


def test_block_splitting_gives_the_same_sums_and_fit():
    t, y, q, _att, _D = simulated("indep", 0.01, True, True)
    t, y, q = _with_gap(t, y, q)
    whole = stream_fit(t, y, q, ALL)
    rng = np.random.default_rng(5)
    for cuts in ([1, 2, 3, 4, 5, 6], sorted(rng.choice(len(t), 40, replace=False).tolist()),
                 list(range(7, len(t), 7))):
        parts = stream_fit(t, y, q, ALL, cuts=cuts)
        assert rot_deg(parts.R_body_mag, whole.R_body_mag) < 1e-9
        assert parts.time_offset_s == pytest.approx(whole.time_offset_s, abs=1e-12)
        np.testing.assert_allclose(parts.D, whole.D, atol=1e-11)
        np.testing.assert_allclose(parts.offset_nT, whole.offset_nT, atol=1e-7)
        # the sigmas scale with the cost, which the sums give to ~1e-9 of itself (it cancels
        # sum |y|^2 against terms of the same size)
        assert parts.sigma_time_offset_s == pytest.approx(whole.sigma_time_offset_s, rel=1e-7)
        np.testing.assert_allclose(parts.sigma_D, whole.sigma_D, rtol=1e-7)
    # the gap and the two ends are left out of the expanded sums (within h of them)
    acc = StreamAccumulator()
    acc.add(q, y, t)
    st = acc.result()
    assert st.n == len(t) and st.n_tau == len(t) - 4 * 5


def test_memory_does_not_grow_with_the_samples():
    """The carried samples stay within the stencil; the time blocks within MAX_BLOCKS."""
    acc = StreamAccumulator(baseline_s=0.05, block_s=0.1)
    rng = np.random.default_rng(0)
    n_blk = 500
    carried = []
    for b in range(40):
        t = (np.arange(b * n_blk, (b + 1) * n_blk) * 10_000_000).astype(np.int64)
        q = rng.normal(size=(n_blk, 4))
        acc.add(q, rng.normal(size=(n_blk, 3)), t)
        carried.append(len(acc._t))
    assert max(carried) <= 11  # the samples of 2 h at 100 Hz
    st = acc.result()
    assert st.block_Wg.shape[0] <= MAX_BLOCKS and st.block_Wg.shape[1:] == (NG, NG)
    np.testing.assert_allclose(st.block_Wg.sum(axis=0), st.Wg, rtol=1e-12)
    assert st.n == 40 * n_blk and st.n_tau == 40 * n_blk - 10


def test_decreasing_stamps_are_refused():
    from pipeline.core.errors import EstimationError

    acc = StreamAccumulator()
    q = np.tile([0.0, 0.0, 0.0, 1.0], (3, 1))
    acc.add(q, np.zeros((3, 3)), np.array([10, 20, 30]))
    with pytest.raises(EstimationError):
        acc.add(q, np.zeros((3, 3)), np.array([25, 40, 50]))


# ----------------------------------------------------------------------------- vs ML
GENERATORS = ["simulate", "indep"]


@pytest.mark.parametrize("gen", GENERATORS)
@pytest.mark.parametrize("noise", [False, True])
def test_offset_and_soft_iron_agree_with_ml(gen, noise):
    t, y, q, att, D = simulated(gen, 0.0, True, noise)
    terms = {EstimateTerm.OFFSET, EstimateTerm.SOFT_IRON}
    f = stream_fit(t, y, q, terms)
    c = ml_fit(t, y, q, att, terms)
    assert f.n_samples == len(t)  # every sample
    assert rot_deg(f.R_body_mag, c.R_body_mag) < 0.01
    np.testing.assert_allclose(f.D, c.D, atol=2e-5)  # 1 nT in 50,000 nT
    np.testing.assert_allclose(f.offset_nT, c.offset_nT, atol=0.5)
    if not noise:
        np.testing.assert_allclose(f.D, D, atol=1e-9)
        np.testing.assert_allclose(f.offset_nT, OFFSET, atol=1e-4)
    else:
        # the information-based sigmas agree with the in-memory ML's within a factor 1.5
        ratio = f.sigma_D / c.sigma_D
        assert np.all((ratio > 1 / 1.5) & (ratio < 1.5))
        assert np.all(np.abs(f.D - D) < 4 * f.sigma_D)


@pytest.mark.parametrize("gen", GENERATORS)
@pytest.mark.parametrize("noise", [False, True])
@pytest.mark.parametrize("tau_ms", [2.0, -2.0, 10.0, -10.0, 40.0, -40.0])
def test_time_offset_agrees_with_ml(gen, noise, tau_ms):
    tau = tau_ms * 1e-3
    t, y, q, att, _D = simulated(gen, tau, False, noise)
    f = stream_fit(t, y, q, {EstimateTerm.TIME_OFFSET})
    c = ml_fit(t, y, q, att, {EstimateTerm.TIME_OFFSET})
    assert f.time_offset_s is not None and c.time_offset_s is not None
    assert c.sigma_time_offset_s is not None and f.sigma_time_offset_s is not None
    assert abs(f.time_offset_s - c.time_offset_s) < max(c.sigma_time_offset_s, 0.2e-3)
    assert rot_deg(f.R_body_mag, c.R_body_mag) < 0.01
    if not noise:
        # truncation and stencil (module docstring): 3.5e-4 of tau here at most
        assert abs(f.time_offset_s - tau) < 5e-4 * abs(tau) + 1e-7
    else:
        assert abs(f.time_offset_s - tau) < 3 * f.sigma_time_offset_s + 1e-5


@pytest.mark.parametrize("gen", GENERATORS)
@pytest.mark.parametrize("noise", [False, True])
@pytest.mark.parametrize("tau_ms", [10.0, -40.0])
def test_all_terms_together_agree_with_ml(gen, noise, tau_ms):
    t, y, q, att, D = simulated(gen, tau_ms * 1e-3, True, noise)
    f = stream_fit(t, y, q, ALL)
    c = ml_fit(t, y, q, att, ALL)
    assert c.sigma_time_offset_s is not None and c.time_offset_s is not None
    assert f.time_offset_s is not None
    assert abs(f.time_offset_s - c.time_offset_s) < max(c.sigma_time_offset_s, 0.2e-3)
    assert rot_deg(f.R_body_mag, c.R_body_mag) < 0.01
    np.testing.assert_allclose(f.D, c.D, atol=2e-5)
    np.testing.assert_allclose(f.offset_nT, c.offset_nT, atol=0.5)
    if not noise:
        np.testing.assert_allclose(f.D, D, atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_covariance_by_splitting_in_halves(seed):
    """Two halves of a noisy recording differ in tau and D by less than 3 combined sigmas."""
    t, y, q, _att, _D = simulated("indep", 0.01, True, True, seed=seed)
    n = len(t) // 2
    a = stream_fit(t[:n], y[:n], q[:n], ALL)
    b = stream_fit(t[n:], y[n:], q[n:], ALL)
    assert a.time_offset_s is not None and b.time_offset_s is not None
    assert a.sigma_time_offset_s is not None and b.sigma_time_offset_s is not None
    assert a.D is not None and b.D is not None and a.sigma_D is not None
    assert b.sigma_D is not None
    z_tau = (a.time_offset_s - b.time_offset_s) / np.hypot(a.sigma_time_offset_s,
                                                           b.sigma_time_offset_s)
    z_D = (a.D - b.D) / np.hypot(a.sigma_D, b.sigma_D)
    assert abs(z_tau) < 3.0
    assert np.all(np.abs(z_D) < 3.0)


def test_single_axis_motion_reports_what_is_unobservable():
    """A turn about Up: the rotation about the vertical and part of D are reported."""
    from pipeline.model.attitude import interpolate_attitude as interp

    spec = indep_gen.Spec("single", 1, motion="single",
                          effects={"time_offset": {"time_offset_s": 0.01}})
    r = indep_gen.readings(spec)
    tm = indep_gen.T0_NS + np.round(r["t_mag_s"] * 1e9).astype(np.int64)
    ta = indep_gen.T0_NS + np.round(r["t_att_s"] * 1e9).astype(np.int64)
    q, ok = interp(AttitudeSeries(ta, r["att"].as_quat()), tm, max_gap_s=0.1)
    f = stream_fit(tm[ok], r["mag_nT"][ok], q[ok], ALL)
    cal = f.to_calibration()
    assert len(cal.unobservable_axes_body) >= 1
    assert np.any(np.isinf(cal.sigma_rotvec_deg))
    assert cal.sigma_D is not None and np.any(np.isinf(cal.sigma_D))
    assert any("soft-iron" in w for w in cal.warnings)
    f_tau = stream_fit(tm[ok], r["mag_nT"][ok], q[ok], {EstimateTerm.TIME_OFFSET})
    assert f_tau.time_offset_s == pytest.approx(0.01, abs=0.2e-3)
    assert len(f_tau.unobservable_axes_body) == 1
    assert abs(abs(f_tau.unobservable_axes_body[0][2]) - 1.0) < 1e-3


# ----------------------------------------------------------------------------- stage
def test_stage_estimates_the_terms_it_supports():
    from stages.estimate_sums import EstimateFromSums
    from stages.estimators.streaming import SampleSums

    assert EstimateFromSums.SUPPORTED_TERMS == ALL
    t, y, q, att, D = simulated("simulate", 0.01, True, False)
    q0, ok = interpolate_attitude(att, t, max_gap_s=0.1)
    acc = StreamAccumulator(max_gap_s=0.1)
    acc.add(q0[ok], y[ok], t[ok])
    ctx = EstimateFromSums(terms=ALL).run(Context(sums=SampleSums(terms=acc.result())))
    cal = ctx.need_calibration()
    assert cal.estimator == "ml-streaming"
    assert cal.time_offset_s == pytest.approx(0.01, abs=0.02e-3)
    assert cal.sigma_time_offset_s is not None
    assert cal.D is not None and cal.sigma_D is not None
    np.testing.assert_allclose(cal.D, D, atol=1e-6)
    np.testing.assert_allclose(cal.offset_nT, OFFSET, atol=0.05)


def test_rotation_only_sums_are_unchanged():
    """The rotation-only fit is the same on the expanded accumulator's sums and on the
    rotation sums alone."""
    t, y, q, _att, _D = simulated("indep", 0.0, False, True)
    acc = StreamAccumulator()
    acc.add(q, y, t)
    a = fit_stats(acc.result(), estimate_offset=True)
    b = fit_stats(StreamStats.of(q, y, t), estimate_offset=True)
    assert rot_deg(a.R_body_mag, b.R_body_mag) < 1e-9
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-9, atol=1e-30)


def test_from_file_in_chunks_equals_the_whole(tmp_path, monkeypatch):
    """The runner's first pass: chunked reading, aligning and accumulating give the same D,
    tau as the sums of the whole recording's aligned samples."""
    import pipeline.run.source as source
    from pipeline.app.simulate import scenario_from_dict, simulate, write_simulated
    from pipeline.io.mcap_read import read_recording
    from pipeline.run.runner import ProcessOptions, analyse_recording
    from stages.resample import Resample

    monkeypatch.setattr(source, "RANGE_MESSAGES", 1_000)

    d = tomllib.loads((SCENARIOS / "multiaxis.toml").read_text())
    d["timing"]["duration_s"] = 30.0
    d["effects"] = {"time_offset": {"time_offset_s": 0.01},
                    "soft_iron": {"D": D_TRUE.tolist()}, "hard_iron": {"offset_nT": OFFSET}}
    path = write_simulated(simulate(scenario_from_dict(d), seed=2), tmp_path / "r.mcap")
    cal = analyse_recording(path, ProcessOptions(
        terms=ALL, scale_samples=100, max_gap_s=0.1, diagnose=False)).need_calibration()
    assert cal.estimator == "ml-streaming"
    al = Resample(max_gap_s=0.1).run(Context(recording=read_recording(path))).need_aligned()
    whole = stream_fit(al.t_ns, al.mag_nT, al.q_enu_body, ALL)
    assert cal.time_offset_s is not None and whole.time_offset_s is not None
    assert cal.time_offset_s == pytest.approx(whole.time_offset_s, abs=1e-9)
    assert rot_deg(cal.R_body_mag, whole.R_body_mag) < 1e-7
    np.testing.assert_allclose(cal.D, whole.D, atol=1e-9)
    assert cal.time_offset_s == pytest.approx(0.01, abs=0.1e-3)


def test_known_field_carries_the_scale_of_soft_iron():
    """With a reference field D is not normalised: its scale is estimated, as in the ML."""
    t, y, q, att, D = simulated("simulate", 0.01, True, False)
    B = np.array([500.0, 20000.0, -45000.0])  # the scenario's field
    D_scaled = 1.1 * D
    y2 = (y - OFFSET) @ np.linalg.solve(D, D_scaled).T + OFFSET
    acc = StreamAccumulator()
    acc.add(q, y2, t)
    f = fit_stats(acc.result(), estimate_offset=True, estimate_soft_iron=True,
                  estimate_time_offset=True, reference_field_enu_nT=B)
    p = EstimationProblem(t_ns=t, mag_nT=y2, q_enu_body=q, attitude=att, terms=ALL,
                reference_field_enu_nT=B)
    c = MLEstimator(checks=False).fit(p)
    assert f.D is not None and f.time_offset_s is not None and c.time_offset_s is not None
    np.testing.assert_allclose(f.D, D_scaled, atol=1e-6)
    np.testing.assert_allclose(f.D, c.D, atol=1e-6)
    np.testing.assert_allclose(f.B_enu_nT, B)
    assert rot_deg(f.R_body_mag, c.R_body_mag) < 0.001
    assert abs(f.time_offset_s - c.time_offset_s) < 0.2e-3


def test_halves_sums_add_up_to_the_whole():
    """StreamStats of two halves added give the whole's fit (rotation to 1e-9 deg) and a
    block sandwich close to one accumulator's (blocks of other lengths, same stretches)."""
    t, y, q, _att, _D = simulated("indep", 0.0, False, True)
    cut = len(t) // 2
    parts = [StreamAccumulator(with_tau=False) for _ in range(2)]
    parts[0].add(q[:cut], y[:cut], t[:cut])
    parts[1].add(q[cut:], y[cut:], t[cut:])
    one = StreamAccumulator(with_tau=False)
    one.add(q, y, t)
    merged = parts[0].result() + parts[1].result()
    assert merged.n == one.result().n == len(t)
    a = fit_stats(merged, estimate_offset=True, block_sandwich=True)
    b = fit_stats(one.result(), estimate_offset=True, block_sandwich=True)
    assert rot_deg(a.R_body_mag, b.R_body_mag) < 1e-9
    np.testing.assert_allclose(a.sigma_rotvec_deg, b.sigma_rotvec_deg, rtol=0.3)
    # the sandwich is not below the information's sigmas (the two fits' own scalings of
    # the noise differ by a few 1e-4)
    c = fit_stats(one.result(), estimate_offset=True)
    assert np.all(b.sigma_rotvec_deg >= c.sigma_rotvec_deg * 0.99)

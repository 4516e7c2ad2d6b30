"""Streaming estimation: sufficient statistics, Gauss-Newton on them, chunked files."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.core.geometry import (
    li2020_euler_to_quat,
    quat_conj,
    quat_rotate,
    quat_to_matrix,
    rotvec_to_quat,
    skew,
    so3_exp,
    so3_log,
)
from stages.estimators.streaming import (
    StreamAccumulator,
    StreamStats,
    _State,
    cost,
    fit_stats,
    normal_equations,
)

ROTVEC_DEG = np.array([1.0, -2.0, 3.0])
B_ENU = np.array([10_000.0, 30_000.0, -20_000.0])
OFFSET = np.array([40.0, -20.0, 10.0])


def synthetic(n: int, *, noise_nT: float = 1.0, heading_only: bool = False, offset=None,
              seed: int = 0):
    """Aligned samples of a known model (CONVENTIONS forward model, D = I, tau = 0)."""
    rng = np.random.default_rng(seed)
    s = np.arange(n) / 50.0
    heading = 2 * np.pi * s / 40.0
    pitch = np.zeros(n) if heading_only else np.radians(25.0) * np.sin(2 * np.pi * s / 17.0)
    roll = np.zeros(n) if heading_only else np.radians(25.0) * np.sin(2 * np.pi * s / 23.0)
    q = li2020_euler_to_quat(heading, pitch, roll)
    R = so3_exp(np.radians(ROTVEC_DEG))
    b_body = quat_rotate(quat_conj(q), np.broadcast_to(B_ENU, (n, 3)))
    y = b_body @ R + noise_nT * rng.standard_normal((n, 3))  # R.T @ b per row
    if offset is not None:
        y = y + offset
    t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 20_000_000
    return q, y, t, R


def rot_err_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(so3_log(R_a @ R_b.T))))


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(1, 399), min_size=0, max_size=5, unique=True))
def test_chunked_sums_equal_whole(cuts):
    """Sums of any split of the samples equal the sums of all of them."""
    q, y, t, _ = synthetic(400, seed=3)
    edges = [0, *sorted(cuts), 400]
    acc = StreamAccumulator(with_tau=False)
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        acc.add(q[a:b], y[a:b], t[a:b])
    parts = acc.result()
    whole = StreamStats.of(q, y, t)
    assert parts.n == whole.n == 400
    for name in ("sum_y", "S", "M", "W"):
        np.testing.assert_allclose(getattr(parts, name), getattr(whole, name), rtol=1e-10,
                                   atol=1e-6)
    assert parts.sum_yy == pytest.approx(whole.sum_yy, rel=1e-12)


def test_cost_and_normal_equations_match_the_samples():
    """Cost, J^T J and J^T r from the sums equal their sample-by-sample definitions."""
    q, y, t, R = synthetic(300, seed=5, offset=OFFSET)
    stats = StreamStats.of(q, y, t)
    s = _State(R @ so3_exp([0.01, -0.02, 0.015]), B_ENU + [30.0, -10.0, 5.0], OFFSET - 3.0)
    C = quat_to_matrix(q)
    m = np.einsum("ab,nca,c->nb", s.R, C, s.B)  # R.T C.T B per sample
    r = y - s.o - m
    assert cost(stats, s.R, s.B, s.o) == pytest.approx(float((r**2).sum()), rel=1e-9)
    # J_i = d r_i / d [phi, B, o] = [-[m_i]x, -R.T C_i.T, -I]
    J = np.concatenate([
        -np.stack([skew(mi) for mi in m]),
        -np.einsum("ab,nca->nbc", s.R, C),
        -np.broadcast_to(np.eye(3), (len(y), 3, 3)),
    ], axis=2)
    H, g = normal_equations(stats, s)
    np.testing.assert_allclose(H, np.einsum("nki,nkj->ij", J, J), rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(g, np.einsum("nki,nk->i", J, r), rtol=1e-8, atol=1e-6)


def test_fit_recovers_rotation_field_and_offset():
    q, y, t, R = synthetic(20_000, noise_nT=1.0, offset=OFFSET)
    fit = fit_stats(StreamStats.of(q, y, t), estimate_offset=True)
    assert rot_err_deg(fit.R_body_mag, R) < 0.005
    np.testing.assert_allclose(fit.offset_nT, OFFSET, atol=0.5)
    np.testing.assert_allclose(fit.B_enu_nT, B_ENU, atol=0.5)
    assert fit.residual_rms_nT == pytest.approx(1.0, rel=0.05)  # 1 nT per axis
    # reported sigma matches the error scale: errors within 5 sigma on each axis
    err = np.degrees(so3_log(fit.R_body_mag @ R.T))
    assert np.all(np.abs(err) < 5 * fit.sigma_rotvec_deg + 1e-9)
    assert fit.unobservable_axes_body == ()
    cal = fit.to_calibration()
    assert cal.estimator == "ml-streaming" and cal.n_samples == 20_000


def test_fit_with_known_field_and_far_start():
    """A known field; the start is found among the 24 axis-aligned rotations."""
    q, y, t, R = synthetic(5_000, noise_nT=0.5)
    R_big = so3_exp(np.radians([0.0, 0.0, 170.0])) @ R
    y_big = np.einsum("ba,nb->na", R.T @ R_big, y)  # a sensor mounted ~180 deg about z
    fit = fit_stats(StreamStats.of(q, y_big, t), reference_field_enu_nT=B_ENU)
    assert rot_err_deg(fit.R_body_mag, R_big) < 0.01
    np.testing.assert_allclose(fit.B_enu_nT, B_ENU)


def test_heading_only_motion_leaves_the_vertical_axis_unobservable():
    q, y, t, R = synthetic(5_000, heading_only=True)
    fit = fit_stats(StreamStats.of(q, y, t))
    assert len(fit.unobservable_axes_body) == 1
    assert abs(abs(fit.unobservable_axes_body[0][2]) - 1.0) < 1e-6
    assert np.isinf(fit.sigma_rotvec_deg[2]) and np.all(np.isfinite(fit.sigma_rotvec_deg[:2]))
    # tilt about x and y is determined; of the equally good rotations the one nearest the
    # identity is reported (no rotation about the unobservable axis)
    rv = np.degrees(so3_log(fit.R_body_mag))
    assert abs(rv[2]) < 0.01
    assert abs(fit.R_body_mag[2] @ R[2] - 1.0) < 1e-6  # the body-z row (tilt) agrees


def test_too_few_samples_is_an_estimation_error():
    from pipeline.core.errors import EstimationError

    q, y, t, _ = synthetic(5)
    with pytest.raises(EstimationError):
        fit_stats(StreamStats.of(q, y, t))


def test_streaming_from_file_equals_in_memory(tmp_path, monkeypatch):
    """The runner's first pass: chunked reading + aligning + sums give the same answer as
    the whole recording."""
    import pipeline.run.plan as plan
    import pipeline.run.source as source
    from pipeline.io.mcap_read import read_recording
    from pipeline.io.mcap_write import write_recording
    from pipeline.run.runner import ProcessOptions, first_pass, make_plan, open_source
    from stages.context import Context
    from stages.estimate_sums import EstimateFromSums
    from stages.resample import Resample

    monkeypatch.setattr(source, "RANGE_MESSAGES", 2_000)
    monkeypatch.setattr(plan, "DECIMATED_SAMPLES", 10**9)  # every aligned sample kept

    n = 12_000
    q, y, t, R = synthetic(n, offset=OFFSET, seed=7)
    path = write_recording(tmp_path / "r.mcap", mag_t_ns=t, mag_nT=y,
                           attitude_t_ns=t - 3_000_000, q_enu_body=q, mag_log_delay_ns=200_000,
                           attitude_log_delay_ns=900_000, chunk_size=64 << 10)
    options = ProcessOptions(scale_samples=1_000, max_gap_s=0.1, terms=frozenset({"offset"}))
    src = open_source(path, options)
    assert type(src).__name__ == "FileSource"
    reduced = first_pass(src, make_plan(options, src.n_mag))
    t_stream = reduced.thin_aligned.t_ns
    ctx = Resample(max_gap_s=0.1).run(Context(recording=read_recording(path)))
    np.testing.assert_array_equal(t_stream, ctx.aligned.t_ns)
    whole = fit_stats(StreamStats.of(ctx.aligned.q_enu_body, ctx.aligned.mag_nT,
                                     ctx.aligned.t_ns),
                      estimate_offset=True)
    sums = Context(sums=reduced.sums)
    cal = EstimateFromSums(frozenset({"offset"})).run(sums).need_calibration()
    assert cal.n_samples == len(ctx.aligned)
    assert rot_err_deg(cal.R_body_mag, whole.R_body_mag) < 1e-7
    assert rot_err_deg(cal.R_body_mag, R) < 0.01
    np.testing.assert_allclose(cal.offset_nT, OFFSET, atol=1.0)


def test_agrees_with_the_in_memory_ml_estimator():
    """Same data, the ESTIMATE engineer's ML estimator and the streaming one agree."""
    from pipeline.core.recording import AlignedSeries
    from pipeline.core.vocabulary import EstimatorKind
    from stages.estimate import fit_calibration

    q, y, t, R = synthetic(4_000, noise_nT=0.5, seed=11)
    ml = fit_calibration(None, AlignedSeries(t, y, q), estimator=EstimatorKind.ML)
    fit = fit_stats(StreamStats.of(q, y, t))
    assert rot_err_deg(fit.R_body_mag, ml.R_body_mag) < 0.01
    assert rot_err_deg(fit.R_body_mag, R) < 0.01


def test_rotvec_to_quat_consistency():
    """The synthetic model's R is the rotation the geometry helpers build (guards the test)."""
    R = so3_exp(np.radians(ROTVEC_DEG))
    np.testing.assert_allclose(quat_to_matrix(rotvec_to_quat(np.radians(ROTVEC_DEG))), R,
                               atol=1e-12)

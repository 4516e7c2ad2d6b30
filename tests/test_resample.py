"""READER: THE attitude interpolator against scipy, gaps, time-offset sign, unsorted input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from pipeline.core.geometry import quat_mul, rotvec_to_quat
from pipeline.core.recording import AttitudeSeries, Recording, VectorSeries
from stages.context import Context
from stages.resample import Resample, auto_max_gap_s, interpolate_attitude

T0 = 1_700_000_000 * 1_000_000_000


def _att(n=50, rate_hz=20.0, seed=0):
    rng = np.random.default_rng(seed)
    t = T0 + np.round(np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    q = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.2, (n, 3)), axis=0)).as_quat()
    return AttitudeSeries(t, q)


def _same_rot(a, b, tol_rad):
    ang = (Rotation.from_quat(a) * Rotation.from_quat(b).inv()).magnitude()
    assert np.max(ang) < tol_rad


def test_interpolator_passes_through_samples_and_equals_slerp_at_constant_rate():
    att = _att()
    q, valid = interpolate_attitude(att, att.t_ns, max_gap_s=1.0)
    assert valid.all()
    _same_rot(q, att.q_enu_body, 1e-9)
    # a constant-rate rotation about one axis: the cubic is the SLERP (scipy's)
    t = T0 + np.arange(40, dtype=np.int64) * 40_000_000
    ang = 1.7 * (t - T0) * 1e-9
    axis = np.array([0.2, -0.6, 0.77]) / np.linalg.norm([0.2, -0.6, 0.77])
    qc = quat_mul(rotvec_to_quat(axis * ang[:, None]), rotvec_to_quat([0.1, 0.2, 0.3]))
    tq = np.sort(np.random.default_rng(1).integers(t[0], t[-1], 500))
    got, valid = interpolate_attitude(AttitudeSeries(t, qc), tq, max_gap_s=1.0)
    ref = Slerp((t - T0) * 1e-9, Rotation.from_quat(qc))((tq - T0) * 1e-9)
    assert valid.all()
    _same_rot(got, ref.as_quat(), 1e-9)


def _wobble(t_s):
    """A smooth multi-axis hand-held motion (25 deg swings at 1.2-1.5 Hz, up to ~5 rad/s)."""
    a = np.radians(25.0)
    rv = np.stack([a * np.sin(2 * np.pi * 1.2 * t_s), a * np.sin(2 * np.pi * 1.5 * t_s + 1.0),
                   a * np.sin(2 * np.pi * 1.3 * t_s + 2.0)], axis=1)
    return Rotation.from_rotvec(rv)


def test_cubic_beats_slerp_on_smooth_motion_and_its_rate_is_its_derivative():
    # attitude at 50 Hz; SLERP errs by alpha dt^2 / 8 (~0.1 deg here), the cubic by O(dt^3)
    from pipeline.model.attitude import AttitudeInterpolator

    t = T0 + np.arange(0, 10_000_000_000, 20_000_000, dtype=np.int64)
    truth = _wobble((t - T0) * 1e-9)
    att = AttitudeSeries(t, truth.as_quat())
    tq = np.sort(np.random.default_rng(3).integers(t[2], t[-3], 2000))
    ref = _wobble((tq - T0) * 1e-9)
    it = AttitudeInterpolator.of(att, max_gap_s=1.0)
    got = it.at(tq)
    err_cubic = (Rotation.from_quat(got.q_enu_body) * ref.inv()).magnitude()
    slerp = Slerp((t - T0) * 1e-9, truth)((tq - T0) * 1e-9)
    err_slerp = (slerp * ref.inv()).magnitude()
    assert np.degrees(err_slerp.max()) > 0.05
    assert np.degrees(err_cubic.max()) < 0.01
    assert err_cubic.max() < err_slerp.max() / 10
    # omega (A6) is the exact derivative of the interpolated attitude: q(t) ~ q(t0) Exp(w dt)
    h = 20_000  # 20 us
    qp, qm = it.at(tq + h).q_enu_body, it.at(tq - h).q_enu_body
    w_fd = (Rotation.from_quat(qm).inv() * Rotation.from_quat(qp)).as_rotvec() / (2 * h * 1e-9)
    # (lam < 1 blends in SLERP's tangents: the rate may jump at a knot, left out here)
    off_knot = np.abs(((tq - T0) % 20_000_000) - 10_000_000) < 10_000_000 - h
    np.testing.assert_allclose(got.omega_body_rad_s[off_knot], w_fd[off_knot],
                               atol=2e-3)  # rad/s, of up to ~5


def test_time_offset_sign():
    """tau > 0: the sample stamped t was sensed at t - tau, so it gets the attitude of t - tau."""
    att = _att()
    tau = 0.0123
    tq = att.t_ns[5:40] + 7_000_000
    q_tau, valid = interpolate_attitude(att, tq, time_offset_s=tau, max_gap_s=1.0)
    q_ref, _ = interpolate_attitude(att, tq - int(round(tau * 1e9)), max_gap_s=1.0)
    assert valid.all()
    _same_rot(q_tau, q_ref, 1e-9)
    q_neg, _ = interpolate_attitude(att, tq, time_offset_s=-tau, max_gap_s=1.0)
    assert (Rotation.from_quat(q_neg) * Rotation.from_quat(q_ref).inv()).magnitude().min() > 1e-4


def test_gap_and_span():
    att = _att(n=40)
    keep = np.ones(40, bool)
    keep[10:20] = False  # 0.55 s between samples 9 and 20
    a = AttitudeSeries(att.t_ns[keep], att.q_enu_body[keep])
    tq = np.array([att.t_ns[0] - 1, att.t_ns[5] + 10, att.t_ns[15], att.t_ns[9],
                   att.t_ns[20], att.t_ns[-1], att.t_ns[-1] + 1])
    q, valid = interpolate_attitude(a, tq, max_gap_s=0.1)
    np.testing.assert_array_equal(valid, [False, True, False, True, True, True, False])
    assert np.isnan(q[~valid]).all()
    _, valid2 = interpolate_attitude(a, tq, max_gap_s=1.0)
    assert valid2[2]


def test_unsorted_and_duplicated_attitude():
    att = _att(n=30)
    perm = np.random.default_rng(2).permutation(30)
    t = np.concatenate([att.t_ns[perm], att.t_ns[:3]])
    q = np.concatenate([att.q_enu_body[perm], -att.q_enu_body[:3]])
    tq = att.t_ns[0] + np.arange(0, 1_400_000_000, 13_000_000)
    q1, v1 = interpolate_attitude(AttitudeSeries(t, q), tq, max_gap_s=1.0)
    q2, v2 = interpolate_attitude(att, tq, max_gap_s=1.0)
    np.testing.assert_array_equal(v1, v2)
    _same_rot(q1[v1], q2[v2], 1e-12)


@settings(max_examples=40, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(-3.0, 3.0), st.floats(0.0, 3.0))
def test_constant_rate_rotation_is_exact(frac, w, rate):
    """A constant-rate rotation about a fixed axis is reproduced exactly by the interpolator."""
    axis = np.array([0.3, -0.5, w]) / np.linalg.norm([0.3, -0.5, w])
    t = T0 + np.arange(10, dtype=np.int64) * 100_000_000
    ang = rate * (t - T0) * 1e-9
    q0 = rotvec_to_quat([0.1, 0.2, 0.3])
    q = quat_mul(rotvec_to_quat(axis * ang[:, None]), q0)
    tq = np.array([T0 + int(round((3 + frac) * 1e8))])
    got, valid = interpolate_attitude(AttitudeSeries(t, q), tq, max_gap_s=0.2)
    exp = quat_mul(rotvec_to_quat(axis * rate * (tq - T0)[:, None] * 1e-9), q0)
    assert valid.all()
    _same_rot(got, exp, 1e-6)


def test_stage_contract_and_auto_gap():
    att = _att(n=100, rate_hz=200.0)
    assert auto_max_gap_s(att) == pytest.approx(0.05)  # 5 x 5 ms is below the 50 ms floor
    assert auto_max_gap_s(_att(n=10, rate_hz=10.0)) == pytest.approx(0.5)
    mag = VectorSeries(att.t_ns + 1_000_000, np.ones((100, 3)) * [1e4, 2e4, 3e4])
    rec = Recording("x.mcap", (), mag, "/mag", att, "/att")
    ctx = Context(recording=rec)
    out = Resample(time_offset_s=0.002).run(ctx)
    assert ctx.aligned is None and out.recording is rec
    assert Resample.requires == {"recording"} and Resample.provides == {"aligned"}
    al = out.aligned
    assert len(al) == 99 and al.time_offset_s == 0.002
    # attitude taken at t - tau = stamp - 1 ms: the first sample falls before the span
    np.testing.assert_array_equal(al.index, np.arange(1, 100))
    np.testing.assert_array_equal(al.mag_nT, mag.values[1:])


def test_cubic_weight_follows_motion_against_noise():
    # (A7): a fast motion sampled slowly gets the cubic; a slow motion with a noisy attitude
    # gets SLERP (the cubic's tangents would only add the neighbours' noise)
    from pipeline.model.attitude import AttitudeInterpolator, estimate_cubic_weight

    t = T0 + np.arange(0, 20_000_000_000, 20_000_000, dtype=np.int64)
    t_s = (t - T0) * 1e-9
    fast = _wobble(t_s).as_quat()
    assert estimate_cubic_weight(t, fast) > 0.95
    rng = np.random.default_rng(5)
    noise = Rotation.from_rotvec(rng.normal(0, np.radians(0.01), (len(t), 3)))
    slow = (noise * Rotation.from_rotvec(np.outer(np.sin(0.3 * t_s), [0, 0, 0.1]))).as_quat()
    assert estimate_cubic_weight(t, slow) < 0.05
    # the same samples give the same weight whatever the gap rule
    it1 = AttitudeInterpolator(t, fast, max_gap_s=0.05)
    it2 = AttitudeInterpolator(t, fast, max_gap_s=np.inf, clamp=True)
    assert it1.cubic_weight == it2.cubic_weight


def test_interpolation_error_is_measured_from_the_track_without_the_noise():
    # the curve through every 2nd and every 4th sample against the samples midway: the
    # attitude noise cancels in the difference, the interpolation error does not
    from pipeline.model.attitude import AttitudeInterpolator, interpolation_error_rad

    t = T0 + np.arange(0, 60_000_000_000, 80_000_000, dtype=np.int64)  # 12.5 Hz
    t_s = (t - T0) * 1e-9
    it = AttitudeInterpolator(t, _wobble(t_s).as_quat(), max_gap_s=1.0)
    # truth: the curve's own error midway between its samples
    mid = t[:-1] + 40_000_000
    got = it.at(mid[5:-5])
    true_err = (Rotation.from_quat(got.q_enu_body) * _wobble((mid[5:-5] - T0) * 1e-9).inv())
    rms_true = float(np.sqrt(np.mean(true_err.magnitude() ** 2)))
    est = interpolation_error_rad(it)
    assert rms_true / 3 < est < rms_true * 3, (est, rms_true)
    # a still attitude with 0.03 deg of white noise has none
    rng = np.random.default_rng(9)
    still = Rotation.from_rotvec(rng.normal(0, np.radians(0.03), (len(t), 3))).as_quat()
    assert interpolation_error_rad(AttitudeInterpolator(t, still, max_gap_s=1.0)) == 0.0


def test_right_jacobians_applied_equal_the_matrices():
    """(A5)/(A6) apply Jr and its inverse without forming them (Sola 2018, Eqs. 143-144)."""
    from pipeline.model.attitude import right_jacobian_apply, right_jacobian_inv_apply

    rng = np.random.default_rng(3)
    r = np.concatenate([rng.normal(size=(50, 3)), 1e-7 * rng.normal(size=(5, 3))])
    v = rng.normal(size=(55, 3))
    th = np.linalg.norm(r, axis=1)
    out, inv = [], []
    for ri, vi, t in zip(r, v, th, strict=True):
        K = np.array([[0, -ri[2], ri[1]], [ri[2], 0, -ri[0]], [-ri[1], ri[0], 0]])
        if t < 1e-6:
            Jr = np.eye(3) - 0.5 * K + K @ K / 6.0
        else:
            Jr = np.eye(3) - (1 - np.cos(t)) / t**2 * K + (t - np.sin(t)) / t**3 * K @ K
        out.append(Jr @ vi)
        inv.append(np.linalg.solve(Jr, vi))
    np.testing.assert_allclose(right_jacobian_apply(r, v), out, atol=1e-12)
    np.testing.assert_allclose(right_jacobian_inv_apply(r, v), inv, atol=1e-9)

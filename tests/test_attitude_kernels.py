"""The attitude's compiled pass (pipeline.model.attitude_kernels) is the numpy cubic.

The diagnosis of a recording with positions interpolates the attitude with the compiled
loop; every other command with numpy. Both must give one curve: the quaternions, ``C.T``,
the position in the segment, the validity (gaps, the span's ends) and the rate.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.core.geometry import quat_normalize, quat_to_matrix
from pipeline.model.attitude import AttitudeInterpolator


def _track(seed: int, m: int, gap: bool) -> AttitudeInterpolator:
    rng = np.random.default_rng(seed)
    dt_ns = rng.integers(8_000_000, 12_000_000, size=m - 1)
    if gap:
        dt_ns[m // 2] = 400_000_000  # 0.4 s: beyond the gap rule
    t_ns = np.concatenate([[0], np.cumsum(dt_ns)]).astype(np.int64)
    q = quat_normalize(np.cumsum(rng.normal(scale=0.05, size=(m, 4)), axis=0)
                       + [0.0, 0.0, 0.0, 1.0])
    return AttitudeInterpolator(t_ns, q)


def _queries(it: AttitudeInterpolator, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed + 1)
    tr = (it.t_ns - it.t_ns[0]) * 1e-9
    inside = rng.uniform(tr[0], tr[-1], size=200)
    # on the samples, both ends, and beyond them (held or not valid)
    return np.concatenate([inside, tr[:5], tr[-3:], [tr[0] - 0.05, tr[-1] + 0.05]])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), m=st.integers(3, 60), gap=st.booleans(),
       clamp=st.booleans())
def test_compiled_pass_is_the_numpy_cubic(seed: int, m: int, gap: bool, clamp: bool) -> None:
    it = _track(seed, m, gap and m > 4)
    tq = _queries(it, seed)
    ref = it.at_rel_s(tq, clamp=clamp)
    got = it.at_rel_s(tq, clamp=clamp, compiled=True)
    np.testing.assert_array_equal(got.valid, ref.valid)
    assert got.valid[-2:].all() == clamp  # beyond the ends: held when clamped, else none
    np.testing.assert_allclose(got.position, ref.position, rtol=0, atol=1e-14)
    np.testing.assert_allclose(got.q_enu_body, ref.q_enu_body, rtol=0, atol=1e-14)
    np.testing.assert_allclose(got.Ct, quat_to_matrix(ref.q_enu_body, transposed=True),
                               rtol=0, atol=1e-14)
    np.testing.assert_allclose(got.omega_body_rad_s, ref.omega_body_rad_s, rtol=1e-12,
                               atol=1e-12)


def test_compiled_pass_would_catch_a_wrong_sign() -> None:
    """The comparison above can fail: a rotation the other way round is far from the curve."""
    it = _track(3, 20, False)
    tq = _queries(it, 3)
    got = it.at_rel_s(tq, compiled=True)
    ok = got.valid
    wrong = got.q_enu_body[ok] * [-1.0, -1.0, -1.0, 1.0]
    assert np.max(np.abs(wrong - it.at_rel_s(tq).q_enu_body[ok])) > 1e-3
    assert np.isnan(got.Ct[~ok]).all() and ok[:200].all() and not ok[-2:].any()

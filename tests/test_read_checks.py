"""The reader's whole-recording checks where their shortcuts (issue 18) meet edge cases."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.errors import DataQualityError
from pipeline.io.mcap_checks import _check_mag, _check_quaternions
from pipeline.io.mcap_decode import DecodedColumns


def _dec(v: np.ndarray) -> DecodedColumns:
    n = len(v)
    t = np.arange(n, dtype=np.int64) * 5_000_000
    return DecodedColumns(t, v, t.copy(), "f")


@pytest.mark.parametrize("rail", [0.0, -0.0])
def test_rail_at_zero_keeps_its_sign(rail: float) -> None:
    rng = np.random.default_rng(3)
    v = np.array([20000.0, 5000.0, -40000.0]) + rng.standard_normal((400, 3))
    v[::4, 2] = rail  # the largest value of axis z: a rail at zero
    problems: list = []
    out = _check_mag("p", "/mag", _dec(v), problems)
    assert [p.code for p in problems] == ["saturated"]
    assert f"100 at {rail:.6g} nT on axis z" in problems[0].message
    assert len(out.t_ns) == 300


def test_saturated_constant_axis_named_twice() -> None:
    rng = np.random.default_rng(4)
    v = np.array([20000.0, 5000.0, -40000.0]) + rng.standard_normal((200, 3))
    v[:, 0] = 30000.0
    with pytest.raises(DataQualityError, match="200 at 30000 nT on axis x; 200 at 30000"):
        _check_mag("p", "/mag", _dec(v), [])


def test_quaternion_checks() -> None:
    rng = np.random.default_rng(5)
    q = rng.standard_normal((50, 4))
    q /= np.linalg.norm(q, axis=1)[:, None]
    problems: list = []
    out = _check_quaternions("/att", _dec(q.copy()), problems)
    assert problems == [] and out.values.shape == (50, 4)
    q[3] = 0.0
    q[7] *= 1 + 2e-6  # just beyond the tolerance
    out = _check_quaternions("/att", _dec(q.copy()), problems)
    assert [(p.code, p.count) for p in problems] == [("zero_quaternion", 1),
                                                    ("non_unit_quaternion", 1)]
    assert len(out.t_ns) == 49
    np.testing.assert_allclose(np.linalg.norm(out.values, axis=1), 1.0, rtol=0, atol=1e-15)

"""The framework: geometry, recording model, stage protocol, calibration value, config, atomic."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from pipeline.core import geometry as g
from pipeline.core.atomic import atomic_path, safe_join, write_text_atomic
from pipeline.core.config import TomlDoc
from pipeline.core.errors import ConfigError, InputError, OutputError, PipelineBuildError
from pipeline.core.recording import AttitudeSeries, VectorSeries
from pipeline.core.stage import Pipeline
from pipeline.model.calibration import Calibration
from stages.context import Context

quats = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda v: np.linalg.norm(v) > 0.1
).map(lambda v: g.quat_normalize(np.array(v)))
rotvecs = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3).map(np.array)


@given(quats, quats)
def test_quat_mul_is_matrix_product(p, q):
    np.testing.assert_allclose(
        g.quat_to_matrix(g.quat_mul(p, q)), g.quat_to_matrix(p) @ g.quat_to_matrix(q), atol=1e-12
    )


@given(quats)
def test_quat_matches_scipy(q):
    np.testing.assert_allclose(g.quat_to_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-12)
    v = np.array([0.3, -2.0, 5.0])
    np.testing.assert_allclose(g.quat_rotate(q, v), g.quat_to_matrix(q) @ v, atol=1e-12)


@given(rotvecs)
def test_exp_log_round_trip(phi):
    C = g.so3_exp(phi)
    np.testing.assert_allclose(C, Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(g.so3_exp(g.so3_log(C)), C, atol=1e-10)
    np.testing.assert_allclose(g.quat_to_matrix(g.rotvec_to_quat(phi)), C, atol=1e-12)


def test_slerp_matches_scipy():
    from scipy.spatial.transform import Slerp

    r = Rotation.from_rotvec([[0.1, 0.2, 0.3], [1.0, -0.5, 0.2]])
    s = np.linspace(0, 1, 11)
    ref = Slerp([0, 1], r)(s).as_quat()
    got = g.quat_slerp(np.repeat(r.as_quat()[:1], 11, 0), np.repeat(r.as_quat()[1:], 11, 0), s)
    np.testing.assert_allclose(np.abs(np.sum(got * ref, axis=1)), 1.0, atol=1e-12)


@given(st.floats(-3.1, 3.1), st.floats(-1.5, 1.5), st.floats(-3.1, 3.1))
def test_li2020_euler_round_trip(h, p, r):
    q = g.li2020_euler_to_quat(h, p, r)
    h2, p2, r2 = g.quat_to_li2020_euler(q)
    np.testing.assert_allclose(
        g.li2020_C_body_enu(h2, p2, r2), g.li2020_C_body_enu(h, p, r), atol=1e-9
    )


def test_li2020_heading_turns_body_counter_clockwise():
    # Heading 90 deg (Ez passive): the body x axis points north in ENU.
    q = g.li2020_euler_to_quat(np.pi / 2, 0.0, 0.0)
    np.testing.assert_allclose(g.quat_rotate(q, [1.0, 0, 0]), [0, 1.0, 0], atol=1e-12)


@pytest.mark.parametrize("az", [0.0, 45.0, 90.0, 200.0, 359.0])
def test_novatel_azimuth_is_clockwise_from_north(az):
    q = g.novatel_to_quat(0.0, 0.0, az)
    fwd = g.quat_rotate(q, [0.0, 1.0, 0.0])  # NovAtel y is forward
    np.testing.assert_allclose(fwd[:2], [np.sin(np.radians(az)), np.cos(np.radians(az))],
                               atol=1e-12)
    np.testing.assert_allclose(g.quat_to_novatel(q)[2], az, atol=1e-9)


# ---------------------------------------------------------------- recording and stages
def test_series_are_immutable_and_windows_half_open():
    s = VectorSeries(np.arange(5, dtype=np.int64) * 10, np.ones((5, 3)))
    with pytest.raises(ValueError):
        s.values[0, 0] = 2.0
    w = s.window(10, 30)
    assert w.t_ns.tolist() == [10, 20]
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.frame = "enu"  # type: ignore[misc]


@dataclass(frozen=True)
class _Make:
    requires: ClassVar[frozenset[str]] = frozenset({"source"})
    provides: ClassVar[frozenset[str]] = frozenset({"recording"})

    def run(self, ctx: Context) -> Context:
        return ctx.replace(source="made")


@dataclass(frozen=True)
class _NeedsCal:
    requires: ClassVar[frozenset[str]] = frozenset({"calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"diagnosis"})

    def run(self, ctx: Context) -> Context:
        return ctx.replace()


def test_pipeline_build_names_the_stage_that_does_not_fit():
    with pytest.raises(PipelineBuildError) as ei:
        Pipeline([_Make(), _NeedsCal()])
    assert ei.value.stage == "_NeedsCal"
    assert "calibration" in str(ei.value)
    Pipeline([_Make(), _NeedsCal()], initial=("source", "calibration"))


def test_pipeline_runs_without_mutating_input():
    ctx = Context(source="x")
    out = Pipeline([_Make()]).run(ctx)
    assert out.source == "made" and ctx.source == "x"


# ---------------------------------------------------------------- calibration value
def _cal(**kw):
    R = g.so3_exp(np.radians([1.0, -2.0, 0.5]))
    base = dict(
        R_body_mag=R,
        sigma_rotvec_deg=[0.01, 0.02, np.inf],
        B_enu_nT=[1000.0, 30000.0, -20000.0],
        estimator="ml",
        residual_rms_nT=1.5,
        n_samples=100,
        unobservable_axes_body=([0.0, 0.0, 1.0],),
        D=np.diag([1.01, 0.99, 1.0]),
        offset_nT=[10.0, -5.0, 3.0],
        time_offset_s=0.01,
    )
    base.update(kw)
    return Calibration(**base)


def test_calibration_json_round_trip():
    c = _cal()
    d = json.loads(c.to_json())
    assert d["format"] == "magalign.calibration/1"
    assert d["sigma_rotvec_deg"][2] is None
    np.testing.assert_allclose(d["rotvec_body_mag_deg"], [1.0, -2.0, 0.5], atol=1e-9)
    c2 = Calibration.from_json(c.to_json())
    np.testing.assert_allclose(c2.R_body_mag, c.R_body_mag)
    np.testing.assert_allclose(c2.D, c.D)
    assert c2.time_offset_s == c.time_offset_s
    assert np.isinf(c2.sigma_rotvec_deg[2])


def test_calibration_rejects_other_formats():
    with pytest.raises(InputError, match="format"):
        Calibration.from_dict({"format": "other/1"}, path="x.json")


def test_restore_inverts_predict():
    c = _cal()
    q = g.rotvec_to_quat(np.random.default_rng(0).normal(size=(50, 3)))
    t = np.arange(50, dtype=np.int64) * 10_000_000
    att = AttitudeSeries(t, q)
    y = c.predict(t, att)
    rs = c.restore(y, t, att)
    # tau = 10 ms, one attitude interval: the first sample was sensed before the attitude began
    assert rs.valid[1:].all() and not rs.valid[0] and np.isnan(y[0]).all()
    np.testing.assert_allclose(rs.enu_nT[1:], np.broadcast_to(c.B_enu_nT, (49, 3)), atol=1e-8)
    np.testing.assert_allclose(rs.residual_nT[1:], 0.0, atol=1e-8)


# ---------------------------------------------------------------- config and outputs
def test_config_errors_name_file_key_and_line(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text("[field]\nenu_nT = [1, 2]\n\n[noise]\nmag_nT = 'x'\n")
    doc = TomlDoc.load(p)
    with pytest.raises(ConfigError) as ei:
        doc.vector("field.enu_nT")
    msg = str(ei.value)
    assert "line 2" in msg and "field.enu_nT" in msg and "s.toml" in msg
    with pytest.raises(ConfigError, match="line 5"):
        doc.number("noise.mag_nT")
    with pytest.raises(ConfigError, match="line 1"):
        TomlDoc.parse("= broken", "b.toml")


def test_atomic_output_only_when_complete(tmp_path):
    dest = tmp_path / "out.json"
    with pytest.raises(RuntimeError), atomic_path(dest) as tmp:
        tmp.write_text("partial")
        raise RuntimeError("killed")
    assert not dest.exists() and list(tmp_path.iterdir()) == []
    write_text_atomic(dest, "{}")
    assert dest.read_text() == "{}"
    with pytest.raises(OutputError), atomic_path(dest, inputs=(dest,)):
        pass


def test_safe_join_stays_inside(tmp_path):
    p = safe_join(tmp_path, "../../etc", "/passwd")
    assert tmp_path.resolve() in p.parents


@given(st.integers(min_value=1, max_value=40), st.integers(min_value=1, max_value=9),
       st.integers(min_value=0, max_value=2**31))
def test_per_sample_products_equal_their_definitions(n, k, seed):
    """``rows_times`` is ``M_n @ v_n``, ``left_times`` ``A @ M_n``, ``right_times`` ``M_n @ A``
    and ``each_times_rows`` ``basis_k @ v_n``."""
    rng = np.random.default_rng(seed)
    M, v, basis = rng.normal(size=(n, 3, 3)), rng.normal(size=(n, 3)), rng.normal(size=(k, 3, 3))
    np.testing.assert_allclose(g.rows_times(M, v), np.matmul(M, v[:, :, None])[:, :, 0],
                               rtol=1e-12, atol=1e-12)
    A = basis[0]
    np.testing.assert_allclose(g.left_times(A, M), np.matmul(A, M), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g.right_times(M, A), np.matmul(M, A), rtol=1e-12, atol=1e-12)
    want = np.stack([v @ basis[j].T for j in range(k)], axis=2)
    got = g.each_times_rows(basis, v)
    assert got.shape == (n, 3, k)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)

"""Metrics stage: Li et al. 2020 Table 4 statistics, metrics.json and metrics.parquet."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.core.geometry import quat_normalize, quat_rotate, rotvec_to_quat, so3_exp
from pipeline.core.recording import (
    AttitudeSeries,
    Recording,
    Segment,
    SegmentKind,
    VectorSeries,
)
from pipeline.model.calibration import Calibration
from stages.metrics import component_stats, compute_metrics, heading_error_stats
from stages.restore import restore_samples

B_ENU = np.array([1300.0, 15000.0, -49000.0])
T0 = 1_767_225_600_000_000_000


def test_component_stats_known_answer():
    s = component_stats(np.array([0.0, 2.0, 4.0, 10.0]))
    assert s["fluctuation_range_nT"] == pytest.approx(10.0)
    assert s["absolute_deviation_nT"] == pytest.approx((4 + 2 + 0 + 6) / 4)  # mean is 4
    assert s["std_nT"] == pytest.approx(np.sqrt((16 + 4 + 0 + 36) / 4))


@settings(max_examples=30, deadline=None)
@given(
    v=st.lists(st.floats(-1e5, 1e5), min_size=2, max_size=50),
    c=st.floats(-1e5, 1e5),
    k=st.floats(0.01, 100.0),
)
def test_stats_are_shift_invariant_and_scale_linearly(v, c, k):
    a = np.array(v)
    s0 = component_stats(a)
    s1 = component_stats(k * a + c)
    for key in s0:
        assert s1[key] == pytest.approx(k * s0[key], rel=1e-6, abs=1e-6 * (1 + abs(c)))


def _case(n: int = 400, rv=(0.02, -0.015, 0.03), noise_nT: float = 0.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = T0 + np.arange(n, dtype=np.int64) * 50_000_000
    ts = np.arange(n) / 20.0
    q = quat_normalize(rotvec_to_quat(np.stack(
        [0.4 * np.sin(0.5 * ts), 0.3 * np.sin(0.8 * ts), 0.5 * ts], -1)))
    cal = Calibration(R_body_mag=so3_exp(np.array(rv)), sigma_rotvec_deg=[0.01] * 3,
                      B_enu_nT=B_ENU, estimator="truth", residual_rms_nT=0.0, n_samples=n)
    y = cal.predict(t, AttitudeSeries(t, q)) + noise_nT * rng.standard_normal((n, 3))
    rec = Recording(path="mem.mcap", channels=(), mag=VectorSeries(t, y), mag_topic="/mag",
                    attitude=AttitudeSeries(t, q), attitude_topic="/att")
    return rec, cal, q, y, t


def test_uncalibrated_is_attitude_only_and_calibrated_is_restored(tmp_path):
    rec, cal, q, y, t = _case(noise_nT=0.3)
    seg = (Segment(int(t[0]), int(t[200]), SegmentKind.ROTATION),
           Segment(int(t[200]), int(t[-1]) + 1, SegmentKind.LINE))
    m = compute_metrics(restore_samples(rec, cal), seg)
    j, p = m.write(tmp_path)
    raw_enu = quat_rotate(q, y)  # C_enu_body @ y: no R, no offset, no D
    for k, c in enumerate("xyz"):
        want = component_stats(raw_enu[:, k])
        got = m.whole.components[c]["uncalibrated"]
        assert got == pytest.approx(want)
        # calibrated: noise only (0.3 nT rms): std well below 1 nT, uncalibrated hundreds
        assert m.whole.components[c]["calibrated"]["std_nT"] < 0.5
        assert m.whole.components[c]["ratio_pct"]["std_nT"] < 1.0
    assert [s.n_samples for s in m.scopes] == [400, 200, 200]
    assert [s.kind for s in m.scopes] == ["all", "rotation", "line"]
    # files: json round trip and one parquet row per scope x component x calibrated
    d = json.loads((tmp_path / "metrics.json").read_text())
    assert d["format"] == "magalign.metrics/1" and len(d["scopes"]) == 3
    tab = pq.read_table(tmp_path / "metrics.parquet").to_pylist()
    assert len(tab) == 3 * 3 * 2
    row = next(r for r in tab if r["scope"] == "all" and r["component"] == "y" and r["calibrated"])
    comp = d["scopes"][0]["components"]["y"]
    assert row["fluctuation_range_nT"] == pytest.approx(comp["calibrated"]["fluctuation_range_nT"])
    assert row["ratio_pct"] == pytest.approx(comp["ratio_pct"]["fluctuation_range_nT"])
    assert (j, p) == (tmp_path / "metrics.json", tmp_path / "metrics.parquet")


def test_heading_error_for_turntable_data():
    rec, cal, q, y, t = _case(rv=(0.0, 0.0, np.radians(1.0)))
    m = compute_metrics(restore_samples(rec, cal), heading_reference_enu_nT=cal.B_enu_nT)
    he = m.heading_error
    # a 1 deg misalignment about body z shows as heading errors of up to ~1 deg before
    # calibration when the body z axis is near vertical, and none after
    assert he["calibrated"]["max_abs_deg"] < 1e-6
    assert 0.3 < he["uncalibrated"]["max_abs_deg"] < 2.0
    # heading atan2(east, north) of (1, 1) against a field pointing north: 45 deg
    assert heading_error_stats(np.array([np.arctan2(1.0, 1.0)]), np.arctan2(0.0, 1.0))[
        "mean_deg"] == pytest.approx(45.0)

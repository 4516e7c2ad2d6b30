"""Turntable attitude source and the axis-tilt fit (Tang 2016) on simulated tilted tables."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.errors import ChannelError
from pipeline.core.geometry import quat_conj, quat_mul
from pipeline.core.stage import Pipeline
from pipeline.model.tang import exact_eta, rotation_angle
from stages.context import Context
from stages.turntable import (
    TurntableAttitude,
    fit_axis_tilt,
    heading_error,
    heading_stats,
    tilt_quat,
    turntable_quat,
)

SCEN = Path(__file__).resolve().parents[1] / "pipeline" / "scenarios" / "turntable_tilt3.toml"


@pytest.fixture(scope="module")
def sim():
    from pipeline.app.simulate import load_scenario, simulate

    return simulate(load_scenario(SCEN), seed=4)


def _angle_deg(p, q):
    return np.degrees(rotation_angle(quat_mul(quat_conj(p), q)))


def test_stage_builds_the_nominal_attitude(sim):
    st = TurntableAttitude()
    assert st.requires == frozenset({"recording"}) and st.provides == frozenset({"recording"})
    ctx = Context(recording=sim.recording)
    out = st.run(ctx)
    assert ctx.recording.attitude is None and out.recording.attitude is not None
    att = out.recording.attitude
    np.testing.assert_array_equal(att.t_ns, sim.recording.turntable.t_ns)
    # a rotation about up by the table angle
    ang = sim.recording.turntable.angle_rad
    ref = np.stack([np.zeros_like(ang), np.zeros_like(ang), np.sin(ang / 2), np.cos(ang / 2)], -1)
    assert np.max(_angle_deg(att.q_enu_body, ref)) < 1e-9
    assert out.recording.attitude_topic == "/turntable"


def test_compensated_attitude_matches_the_simulators_truth(sim):
    tilt = sim.truth.effects["axis_tilt"]
    rec = TurntableAttitude(tilt_deg=tilt["tilt_deg"], azimuth_deg=tilt["azimuth_deg"]).apply(
        sim.recording
    )
    # attitude at the magnetometer stamps vs the truth there (the encoder noise is 0.01 deg)
    idx = np.searchsorted(rec.attitude.t_ns, sim.recording.mag.t_ns)
    ok = idx < len(rec.attitude)
    ok[ok] &= rec.attitude.t_ns[idx[ok]] == sim.recording.mag.t_ns[ok]
    err = _angle_deg(rec.attitude.q_enu_body[idx[ok]], sim.truth.q_enu_body_true[ok])
    assert ok.sum() > 1000 and np.max(err) < 0.06
    # and without the compensation it is 3 deg off
    nominal = TurntableAttitude().apply(sim.recording)
    err0 = _angle_deg(nominal.attitude.q_enu_body[idx[ok]], sim.truth.q_enu_body_true[ok])
    assert np.median(err0) == pytest.approx(3.0, abs=0.1)


def test_missing_turntable_channel_is_named(sim):
    rec = dataclasses.replace(sim.recording, turntable=None)
    with pytest.raises(ChannelError) as ei:
        TurntableAttitude().run(Context(recording=rec))
    assert ei.value.role == "attitude" and "turntable" in str(ei.value)


def test_pipeline_turntable_resample_segment(sim):
    from stages.resample import Resample
    from stages.segment import SegmentMotion

    p = Pipeline([TurntableAttitude(), Resample(), SegmentMotion()], initial=("recording",))
    out = p.run(Context(recording=sim.recording))
    assert len(out.segments) == 1 and out.segments[0].twist_deg > 1400


def test_heading_error_is_tangs_exact_azimuth_error():
    ang = np.radians(np.linspace(0.0, 720.0, 500))
    T = tilt_quat(5.0, 120.0)
    q_nom = turntable_quat(ang)
    q_true = quat_mul(T, q_nom)
    eta = heading_error(q_nom, q_true)
    np.testing.assert_allclose(eta, exact_eta(ang, np.radians(5.0)), atol=1e-12)
    st = heading_stats(eta)
    assert st.max_deg == pytest.approx(np.degrees(np.radians(5.0) ** 2 / 2), rel=0.01)
    assert st.min_deg == pytest.approx(-st.max_deg, rel=1e-3)
    # the true axis is where the tilt says: azimuth clockwise from north
    from pipeline.core.geometry import quat_rotate

    ax = quat_rotate(T, np.array([0.0, 0.0, 1.0]))
    t, az = np.radians(5.0), np.radians(120.0)
    np.testing.assert_allclose(ax, [np.sin(t) * np.sin(az), np.sin(t) * np.cos(az), np.cos(t)],
                               atol=1e-12)


def test_tilt_recovered_with_field_and_mounting_known(sim):
    tr = sim.truth
    res = fit_axis_tilt(sim.recording, reference_field_enu_nT=tr.B_enu_nT,
                        R_known_body_mag=tr.R_body_mag, q_true_enu_body=tr.q_enu_body_true)
    # Noise: 0.3 nT on ~48000 nT and a 0.01 deg encoder over 3600 samples put the 1-sigma of the
    # tilt near 1e-4 deg; 0.01 deg in tilt and 0.2 deg in azimuth (0.01 deg / sin(3 deg)) are
    # generous bounds that a wrong sign or azimuth convention would still miss by far.
    assert res.tilt_deg == pytest.approx(3.0, abs=0.01)
    assert res.azimuth_deg == pytest.approx(30.0, abs=0.2)
    assert np.isfinite(res.sigma_tilt_deg) and res.sigma_tilt_deg < 0.01
    assert abs(res.tilt_deg - 3.0) < 10 * res.sigma_tilt_deg + 1e-3
    assert res.unobservable_lean_dirs == ()
    # Tang's Table 2 statistics: the heading-error variance drops to the encoder noise
    hb, ha = res.heading_before, res.heading_after
    assert hb.var_deg2 == pytest.approx((np.radians(3.0) ** 2 / 2) ** 2 / 2 * np.degrees(1) ** 2,
                                        rel=0.1)
    assert ha.var_deg2 < 0.1 * hb.var_deg2
    assert ha.max_deg - ha.min_deg < hb.max_deg - hb.min_deg
    assert res.effect_params() == {"tilt_deg": res.tilt_deg, "azimuth_deg": res.azimuth_deg}


def test_field_known_only_the_lean_towards_the_field_is_observable(sim):
    tr = sim.truth
    res = fit_axis_tilt(sim.recording, reference_field_enu_nT=tr.B_enu_nT,
                        q_true_enu_body=tr.q_enu_body_true)
    assert len(res.unobservable_lean_dirs) == 1 and len(res.observable_lean_dirs) == 1
    B = np.asarray(tr.B_enu_nT)
    bh = B[:2] / np.linalg.norm(B[:2])  # (east, north) of the horizontal field
    d = res.observable_lean_dirs[0]
    assert abs(abs(float(d @ bh)) - 1.0) < 1e-3
    lean_true = 3.0 * np.array([np.sin(np.radians(30.0)), np.cos(np.radians(30.0))])
    # the unobserved lean (across the field) couples back at second order,
    # ~ t_perp^2 / 2 * |B_up| / |B_h| ~ 0.04 deg here
    assert float(res.lean_enu_deg @ d) == pytest.approx(float(lean_true @ d), abs=0.1)
    assert not np.isfinite(res.sigma_azimuth_deg)
    assert res.heading_after.var_deg2 < res.heading_before.var_deg2
    # what is determined exactly: the angle between the true axis and the field
    ax = np.array([np.sin(np.radians(3.0)) * np.sin(np.radians(30.0)),
                   np.sin(np.radians(3.0)) * np.cos(np.radians(30.0)), np.cos(np.radians(3.0))])
    truth = np.degrees(np.arccos(ax @ B / np.linalg.norm(B)))
    assert res.axis_field_angle_deg == pytest.approx(truth, abs=0.002)


def test_field_unknown_tilt_is_not_observable(sim):
    res = fit_axis_tilt(sim.recording, q_true_enu_body=sim.truth.q_enu_body_true)
    assert len(res.unobservable_lean_dirs) == 2
    assert not np.isfinite(res.sigma_tilt_deg)
    assert res.tilt_deg < 0.1  # stays at the prior: nothing was made up
    # yet the model fits: the tilt is absorbed by B_enu and R_body_mag
    assert res.residual_rms_nT < 5.0
    ax = np.array([np.sin(np.radians(3.0)) * np.sin(np.radians(30.0)),
                   np.sin(np.radians(3.0)) * np.cos(np.radians(30.0)), np.cos(np.radians(3.0))])
    B = np.asarray(sim.truth.B_enu_nT)
    truth = np.degrees(np.arccos(ax @ B / np.linalg.norm(B)))
    assert res.axis_field_angle_deg == pytest.approx(truth, abs=0.002)
    assert "reference field" in res.notes[0]


def test_in_memory_simulation_with_noise_and_uncertainty():
    from pipeline.app.reproduce_tang2016 import simulate_tilted_turntable

    s = simulate_tilted_turntable(3.0, 250.0, noise_nT=30.0, seed=2)
    res = fit_axis_tilt(s.recording, reference_field_enu_nT=s.B_enu_nT,
                        R_known_body_mag=s.R_body_mag, q_true_enu_body=s.q_true_enu_body)
    assert abs(res.tilt_deg - 3.0) < 5 * res.sigma_tilt_deg
    d_az = (res.azimuth_deg - 250.0 + 180.0) % 360.0 - 180.0
    assert abs(d_az) < 5 * res.sigma_azimuth_deg
    # 30 nT on ~48000 nT over 2400 samples x 3 axes: ~30 / 48000 / sqrt(2 * 2400) rad ~ 5e-4 deg
    expected = np.degrees(30.0 / np.linalg.norm(s.B_enu_nT) / np.sqrt(2 * 2400))
    assert expected / 3 < res.sigma_tilt_deg < expected * 3
    assert res.heading_after.var_deg2 < 0.1 * res.heading_before.var_deg2


# --------------------------------------------------------------------------- processing


def _processed_tilt3(tmp_path, reference: bool):
    import json

    from pipeline.app.simulate import load_scenario, simulate, write_simulated
    from pipeline.run.runner import ProcessOptions, process_recording

    scen = Path(__file__).resolve().parents[1] / "pipeline" / "scenarios" / "turntable_tilt3.toml"
    sim = simulate(load_scenario(scen), seed=1)
    rec = write_simulated(sim, tmp_path / "tt.mcap")
    opts = ProcessOptions(
        reference_field_enu_nT=tuple(sim.truth.B_enu_nT) if reference else None,
        diagnose=False,
        write_rerun=False,
        write_report=False,
    )
    process_recording(rec, tmp_path / "out", options=opts)
    cal = json.loads((tmp_path / "out" / "tt" / "calibration.json").read_text())
    return sim, cal


def test_process_recording_fits_and_compensates_axis_tilt(tmp_path):
    """turntable_tilt3 (3 deg towards 30 deg) end to end with a reference field."""
    from pipeline.model.tang import heading_error_stats

    sim, cal = _processed_tilt3(tmp_path, reference=True)
    tilt = cal["effects"]["axis_tilt"]
    assert set(tilt) == {"tilt_deg", "azimuth_deg"}
    true = sim.truth.effects["axis_tilt"]
    lean_true = true["tilt_deg"] * np.array(
        [np.sin(np.radians(true["azimuth_deg"])), np.cos(np.radians(true["azimuth_deg"]))]
    )
    lean_fit = tilt["tilt_deg"] * np.array(
        [np.sin(np.radians(tilt["azimuth_deg"])), np.cos(np.radians(tilt["azimuth_deg"]))]
    )
    # field known, mounting fitted: only the lean towards the horizontal field is observable
    bh = np.array(sim.truth.B_enu_nT[:2], dtype=float)
    bh = bh / np.linalg.norm(bh)
    assert float(lean_fit @ bh) == pytest.approx(float(lean_true @ bh), abs=0.1)
    assert any("partly identifiable" in w for w in cal["warnings"])
    # the compensated attitude has a smaller heading error (Tang's Table 2 variance)
    rec = sim.recording
    t0 = rec.turntable.t_ns[0]
    ang = np.interp(rec.mag.t_ns - t0, rec.turntable.t_ns - t0, rec.turntable.angle_rad)
    q_nom = turntable_quat(ang)
    q_comp = turntable_quat(ang, tilt=tilt_quat(tilt["tilt_deg"], tilt["azimuth_deg"]))
    q_true = sim.truth.q_enu_body_true
    before = heading_error_stats(heading_error(q_nom, q_true))
    after = heading_error_stats(heading_error(q_comp, q_true))
    assert after["var_deg2"] < 0.2 * before["var_deg2"]


def test_process_recording_says_why_tilt_is_not_identifiable(tmp_path):
    _, cal = _processed_tilt3(tmp_path, reference=False)
    assert "axis_tilt" not in cal["effects"]
    assert any("axis_tilt not identifiable" in w and "reference field" in w
               for w in cal["warnings"])

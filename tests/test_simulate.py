"""The simulator against hand-computed cases, effect by effect."""

from __future__ import annotations

import copy
import math
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.app.simulate import (
    Profile,
    Turntable,
    load_scenario,
    scenario_from_dict,
    simulate,
)
from pipeline.core.errors import ConfigError
from pipeline.core.geometry import quat_to_matrix, so3_exp, so3_log
from pipeline.model.igrf import igrf_enu_nT

START_NS = 1_767_225_600 * 1_000_000_000  # 2026-01-01T00:00:00Z
B = [1000.0, 20000.0, -40000.0]


def _turntable(**over) -> dict:
    """A small turntable scenario about ENU/body z; ``over`` merges into the tables."""
    d = {
        "name": "t",
        "timing": {"duration_s": 4.0, "mag_rate_hz": 50.0, "attitude_rate_hz": 50.0},
        "motion": {"profile": "turntable", "rate_deg_s": 90.0},
        "field": {"enu_nT": B},
    }
    for k, v in over.items():
        if k == "field" or (k == "motion" and v.get("profile", "turntable") != "turntable"):
            d[k] = v  # replaced whole: the keys of another profile or field source differ
        elif isinstance(v, dict) and isinstance(d.get(k), dict):
            d[k] = {**d[k], **v}
        else:
            d[k] = v
    return d


def _Rz(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# --- hand-computed physics -------------------------------------------------------------


def test_turntable_quarter_turn_by_hand():
    sim = simulate(scenario_from_dict(_turntable()))
    rec = sim.recording
    assert rec.mag.t_ns[0] == START_NS
    assert np.all(np.diff(rec.mag.t_ns) == 20_000_000)
    # t = 1 s: the body has turned +90 deg about up, so body x points north, body y west.
    i = 50
    assert rec.mag.t_ns[i] - START_NS == 1_000_000_000
    np.testing.assert_allclose(rec.mag.values[i], [B[1], -B[0], B[2]], atol=1e-9)
    # t = 2 s: half a turn.
    np.testing.assert_allclose(rec.mag.values[100], [-B[0], -B[1], B[2]], atol=1e-9)
    # The attitude channel carries the (noise-free) attitude: Rz(90 deg) at t = 1 s.
    np.testing.assert_allclose(quat_to_matrix(rec.attitude.q_enu_body[i]), _Rz(90), atol=1e-12)


def _E(h: float, p: float, r: float) -> np.ndarray:
    """Li 2020 Eqs. 4-7 written out: E = Ey(roll) Ex(pitch) Ez(heading), degrees."""
    a, g, b = (math.radians(x) for x in (h, p, r))
    Ez = np.array([[math.cos(a), math.sin(a), 0], [-math.sin(a), math.cos(a), 0], [0, 0, 1]])
    Ex = np.array([[1, 0, 0], [0, math.cos(g), math.sin(g)], [0, -math.sin(g), math.cos(g)]])
    Ey = np.array([[math.cos(b), 0, -math.sin(b)], [0, 1, 0], [math.sin(b), 0, math.cos(b)]])
    return Ey @ Ex @ Ez


def test_li2020_section41_by_hand():
    sc = load_scenario(resources.files("pipeline") / "scenarios" / "li2020_section41.toml")
    assert sc.profile is Profile.STATIC_SWEEP
    sim = simulate(sc)
    rec = sim.recording
    assert len(rec.mag) == 360 and len(rec.attitude) == 360
    np.testing.assert_array_equal(rec.mag.t_ns, START_NS + np.arange(360) * 1_000_000_000)
    Bf = np.array([10000.0, 30000.0, 20000.0])
    # R_body_mag = E(0, 5, -10).T, so y = R.T C_body_enu B = E(0, 5, -10) E(k, 0, -10) B.
    np.testing.assert_allclose(sim.truth.R_body_mag, _E(0, 5, -10).T, atol=1e-15)
    for k in (0, 1, 45, 90, 200, 359):
        want = _E(0, 5, -10) @ _E(k, 0, -10) @ Bf
        np.testing.assert_allclose(rec.mag.values[k], want, atol=1e-8)
        np.testing.assert_allclose(quat_to_matrix(rec.attitude.q_enu_body[k]), _E(k, 0, -10).T,
                                   atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(rec.mag.values, axis=1), np.linalg.norm(Bf),
                               rtol=1e-12)


def test_noisy_li2020_has_the_paper_sensor_figures():
    sc = load_scenario(resources.files("pipeline") / "scenarios" / "li2020_section41_noisy.toml")
    assert (sc.noise.mag_sigma_nT, sc.noise.heading_sigma_deg, sc.noise.pitch_roll_sigma_deg) == (
        0.1, 0.06, 0.015)
    sim = simulate(sc)
    r = sim.recording.mag.values - sim.truth.mag_clean_nT
    assert 0.08 < np.std(r) < 0.12


@settings(max_examples=15, deadline=None)
@given(rv=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
       b=st.lists(st.floats(-6e4, 6e4), min_size=3, max_size=3))
def test_rotations_preserve_the_field_magnitude(rv, b):
    # Without D, offset or noise the measurement is a rotation of B (CONVENTIONS model).
    if np.linalg.norm(b) < 1.0:
        b = [1.0, 0.0, 0.0]
    d = _turntable(field={"enu_nT": b}, sensor={"misalignment_rotvec_deg": rv},
                   motion={"profile": "multiaxis"}, timing={"duration_s": 2.0})
    sim = simulate(scenario_from_dict(d))
    np.testing.assert_allclose(np.linalg.norm(sim.recording.mag.values, axis=1),
                               np.linalg.norm(b), rtol=1e-12)
    # And it is exactly R.T C.T B per sample.
    C = quat_to_matrix(sim.truth.q_enu_body_true)
    want = np.einsum("ij,njk,k->ni", sim.truth.R_body_mag.T, np.swapaxes(C, 1, 2), np.array(b))
    np.testing.assert_allclose(sim.recording.mag.values, want, atol=1e-7)
    np.testing.assert_allclose(so3_log(sim.truth.R_body_mag), np.radians(rv), atol=1e-12)


# --- effects ---------------------------------------------------------------------------


def test_hard_and_soft_iron():
    base = simulate(scenario_from_dict(_turntable())).recording.mag.values
    o = [120.0, -80.0, 35.0]
    hi = simulate(scenario_from_dict(_turntable(effects={"hard_iron": {"offset_nT": o}})))
    np.testing.assert_allclose(hi.recording.mag.values - base, np.broadcast_to(o, base.shape),
                               atol=1e-9)
    assert hi.truth.effects == {"hard_iron": {"offset_nT": o}}
    np.testing.assert_array_equal(hi.truth.offset_nT, o)
    D = [[1.02, 0.01, 0.0], [0.01, 0.98, -0.02], [0.0, -0.02, 1.01]]
    si = simulate(scenario_from_dict(_turntable(effects={"soft_iron": {"D": D}})))
    np.testing.assert_allclose(si.recording.mag.values, base @ np.array(D).T, atol=1e-9)
    np.testing.assert_array_equal(si.truth.D, D)


def test_soft_iron_must_be_symmetric_positive_definite():
    with pytest.raises(ConfigError, match="symmetric"):
        scenario_from_dict(_turntable(effects={"soft_iron": {"D": [[1, 0.1, 0], [0, 1, 0],
                                                                    [0, 0, 1]]}}))
    with pytest.raises(ConfigError, match="positive definite"):
        scenario_from_dict(_turntable(effects={"soft_iron": {"D": [[1, 0, 0], [0, -1, 0],
                                                                    [0, 0, 1]]}}))


def test_time_offset_means_the_sample_saw_an_earlier_attitude():
    tau = 0.05
    late = simulate(scenario_from_dict(_turntable(effects={"time_offset": {"time_offset_s": tau}})))
    # At constant rate, sensing at t - tau is the same as starting 90 deg/s * tau earlier.
    early = simulate(scenario_from_dict(_turntable(motion={"initial_angle_deg": -90.0 * tau})))
    np.testing.assert_allclose(late.recording.mag.values, early.recording.mag.values, atol=1e-8)
    # The attitude channel is not shifted: it matches the untouched run.
    plain = simulate(scenario_from_dict(_turntable()))
    np.testing.assert_allclose(late.recording.attitude.q_enu_body,
                               plain.recording.attitude.q_enu_body, atol=1e-15)
    assert late.truth.time_offset_s == tau
    np.testing.assert_allclose(late.truth.q_enu_body_sensed, early.truth.q_enu_body_true,
                               atol=1e-12)


def test_eddy_current_adds_E_times_the_analytic_derivative():
    E = [[0.002, 0.0, 0.0], [0.0, 0.001, 0.0005], [0.0, 0.0, 0.003]]
    base = simulate(scenario_from_dict(_turntable()))
    eddy = simulate(scenario_from_dict(_turntable(effects={"eddy_current": {"E_s": E}})))
    t = (base.recording.mag.t_ns - START_NS) * 1e-9
    w = math.radians(90.0)
    th = w * t
    # y = Rz(th).T B: y_x = Be cos + Bn sin, y_y = -Be sin + Bn cos, y_z = Bu.
    dy = np.stack([w * (-B[0] * np.sin(th) + B[1] * np.cos(th)),
                   w * (-B[0] * np.cos(th) - B[1] * np.sin(th)), 0 * th], -1)
    np.testing.assert_allclose(eddy.recording.mag.values - base.recording.mag.values,
                               dy @ np.array(E).T, atol=1e-4)
    assert np.max(np.abs(dy @ np.array(E).T)) > 50.0  # the test sees a real effect


def test_field_drift_sinusoid_has_the_requested_range():
    ptp = [20.0, 5.0, 0.0]
    d = _turntable(motion={"rate_deg_s": 0.0}, timing={"duration_s": 20.0},
                   effects={"field_drift": {"peak_to_peak_nT": ptp}})
    sim = simulate(scenario_from_dict(d))
    # Identity attitude and mounting: the magnetometer reads B_enu(t) directly.
    v = sim.recording.mag.values
    np.testing.assert_allclose(v.max(0) - v.min(0), ptp, atol=0.01)
    np.testing.assert_allclose(sim.truth.B_enu_t_nT, v, atol=1e-9)
    assert sim.truth.effects["field_drift"] == {"peak_to_peak_nT": ptp}


def test_field_drift_random_walk_range_and_seed():
    ptp = [30.0, 10.0, 4.0]
    d = _turntable(motion={"rate_deg_s": 0.0}, timing={"duration_s": 60.0, "mag_rate_hz": 10.0},
                   effects={"field_drift": {"peak_to_peak_nT": ptp, "kind": "random_walk"}})
    a = simulate(scenario_from_dict(d), seed=1).recording.mag.values
    b = simulate(scenario_from_dict(d), seed=2).recording.mag.values
    for v in (a, b):
        np.testing.assert_allclose(v.max(0) - v.min(0), ptp, rtol=0.05)
    assert not np.allclose(a, b)


def test_disturbance_is_a_bell_inside_its_windows_only():
    d = _turntable(motion={"rate_deg_s": 0.0},
                   effects={"disturbance": {"windows_s": [[1.0, 2.0]], "peak_nT": 50.0,
                                            "direction_enu": [0.0, 3.0, 4.0]}})
    sim = simulate(scenario_from_dict(d))
    dv = sim.recording.mag.values - np.array(B)
    t = (sim.recording.mag.t_ns - START_NS) * 1e-9
    outside = (t < 1.0) | (t >= 2.0)
    np.testing.assert_allclose(dv[outside], 0.0, atol=1e-9)
    np.testing.assert_allclose(dv[np.argmin(np.abs(t - 1.5))], [0.0, 30.0, 40.0], atol=1e-9)
    assert np.all(np.linalg.norm(dv[~outside], axis=1) <= 50.0 + 1e-9)


def test_hard_iron_step_abrupt_and_smooth():
    o = [0.0, 0.0, 200.0]
    d = _turntable(effects={"hard_iron_step": {"windows_s": [[1.0, 2.0]], "offset_nT": o}})
    step = simulate(scenario_from_dict(d))
    base = simulate(scenario_from_dict(_turntable()))
    dv = step.recording.mag.values - base.recording.mag.values
    t = (step.recording.mag.t_ns - START_NS) * 1e-9
    inside = (t >= 1.0) & (t < 2.0)  # half-open
    np.testing.assert_allclose(dv[inside], np.broadcast_to(o, dv[inside].shape), atol=1e-9)
    np.testing.assert_allclose(dv[~inside], 0.0, atol=1e-9)
    d["effects"]["hard_iron_step"]["edge_s"] = 0.2
    smooth = simulate(scenario_from_dict(d)).recording.mag.values - base.recording.mag.values
    assert abs(smooth[np.argmin(np.abs(t - 1.0)), 2]) < 1e-9
    assert abs(smooth[np.argmin(np.abs(t - 1.1)), 2] - 100.0) < 1e-6
    assert abs(smooth[np.argmin(np.abs(t - 1.5)), 2] - 200.0) < 1e-9
    with pytest.raises(ConfigError, match="edge_s"):
        d["effects"]["hard_iron_step"]["edge_s"] = 0.6
        scenario_from_dict(d)


def test_axis_tilt_turntable_with_angle_channel():
    sc = load_scenario(resources.files("pipeline") / "scenarios" / "turntable_tilt3.toml")
    assert isinstance(sc.motion, Turntable)
    sim = simulate(sc, seed=5)
    rec = sim.recording
    assert rec.attitude is None and rec.attitude_topic is None
    assert len(rec.turntable) == len(rec.mag)
    # The true rotation axis (ENU) is the vertical tilted 3 deg towards bearing 30 deg.
    C = quat_to_matrix(sim.truth.q_enu_body_true)
    axis = so3_log(C[10] @ C[0].T)
    axis /= np.linalg.norm(axis)
    a = math.radians(30.0)
    want = [math.sin(math.radians(3)) * math.sin(a), math.sin(math.radians(3)) * math.cos(a),
            math.cos(math.radians(3))]
    np.testing.assert_allclose(axis, want, atol=1e-9)
    np.testing.assert_allclose(sim.truth.axis_tilt["axis_enu"], want, atol=1e-12)
    # ... while in the body frame it is still body z.
    ab = so3_log(C[0].T @ C[10])
    np.testing.assert_allclose(ab / np.linalg.norm(ab), [0, 0, 1], atol=1e-9)
    # The angle channel reports the table angle (unwrapped, rad) up to the encoder noise.
    ang = sc.motion.angle_rad((rec.turntable.t_ns - START_NS) * 1e-9)
    err = np.degrees(rec.turntable.angle_rad - ang)
    assert 0.005 < np.std(err) < 0.015
    assert sim.truth.effects["axis_tilt"] == {"tilt_deg": 3.0, "azimuth_deg": 30.0}


def test_axis_tilt_refused_outside_turntable():
    d = _turntable(motion={"profile": "multiaxis"},
                   effects={"axis_tilt": {"tilt_deg": 3.0, "azimuth_deg": 0.0}})
    with pytest.raises(ConfigError, match="turntable"):
        scenario_from_dict(d)


def test_varying_rate_turntable_matches_its_integral():
    m = Turntable(rate_deg_s=30.0, rate_modulation=0.5, modulation_period_s=4.0)
    t = np.linspace(0.0, 8.0, 8001)
    rate = np.degrees(np.gradient(m.angle_rad(t), t))
    np.testing.assert_allclose(rate[1:-1], 30.0 * (1 + 0.5 * np.sin(2 * np.pi * t[1:-1] / 4.0)),
                               atol=1e-3)


# --- noise, streams, seeds -------------------------------------------------------------


def test_noise_levels_and_seed():
    d = _turntable(motion={"profile": "multiaxis"}, timing={"duration_s": 40.0},
                   noise={"mag_sigma_nT": 2.0, "heading_sigma_deg": 0.5,
                          "pitch_roll_sigma_deg": 0.2})
    sc = scenario_from_dict(d)
    a = simulate(sc, seed=3)
    res = a.recording.mag.values - a.truth.mag_clean_nT
    assert 1.9 < np.std(res) < 2.1
    # Same stamps for both streams here, so the truth at the mag stamps is the true attitude.
    np.testing.assert_array_equal(a.recording.attitude.t_ns, a.recording.mag.t_ns)
    Ct = quat_to_matrix(a.truth.q_enu_body_true)
    Cm = quat_to_matrix(a.recording.attitude.q_enu_body)
    # Heading error: about ENU up (left); pitch/roll errors: about body x, y (right).
    dh = so3_log(Cm @ np.swapaxes(Ct, 1, 2))
    assert 0.45 < np.degrees(np.std(dh[:, 2])) < 0.55
    dpr = so3_log(np.swapaxes(Ct, 1, 2) @ Cm)
    assert 0.17 < np.degrees(np.std(dpr[:, 0])) < 0.23
    b = simulate(sc, seed=3)
    np.testing.assert_array_equal(a.recording.mag.values, b.recording.mag.values)
    c = simulate(sc, seed=4)
    assert not np.array_equal(a.recording.mag.values, c.recording.mag.values)


def test_stream_rates_and_phases():
    d = _turntable(timing={"duration_s": 2.0, "mag_rate_hz": 100.0, "attitude_rate_hz": 40.0,
                           "attitude_phase_s": 0.0075, "start": "2026-03-01T12:00:00Z"})
    rec = simulate(scenario_from_dict(d)).recording
    t0 = 1_772_366_400 * 1_000_000_000
    np.testing.assert_array_equal(rec.mag.t_ns, t0 + np.arange(200) * 10_000_000)
    np.testing.assert_array_equal(rec.attitude.t_ns, t0 + 7_500_000 + np.arange(80) * 25_000_000)
    info = {c.role.value: c for c in rec.channels}
    assert info["magnetometer"].rate_hz == pytest.approx(100.0)
    assert info["attitude"].rate_hz == pytest.approx(40.0)


def test_survey_lines_headings_and_turns():
    sc = load_scenario(resources.files("pipeline") / "scenarios" / "survey_lines.toml")
    m = sc.motion
    t = np.array([5.0, 25.0, 30.0 + 12.0 + 5.0, 2 * 42.0 + 5.0])
    h, p, r = m.euler_rad(t)
    np.testing.assert_allclose(np.degrees(h), [90.0, 90.0, 270.0, 90.0], atol=1e-9)
    assert np.all(np.abs(np.degrees(p)) <= 1.5 + 1e-12)
    assert sc.timing.duration_s == 3 * 30.0 + 2 * 12.0
    # Smooth: the heading rate is continuous (no jump at a turn's start or end).
    tt = np.linspace(25.0, 47.0, 22001)
    rate = np.diff(m.euler_rad(tt)[0]) / np.diff(tt)
    assert np.max(np.abs(np.diff(rate))) < 1e-3


def test_igrf_is_plausible():
    for lat, lon in ((60.0, 10.0), (48.0, 11.0), (-35.0, 149.0), (0.0, -60.0)):
        b = igrf_enu_nT(lat, lon, 100.0, "2026-01-01")
        assert 20_000 < np.linalg.norm(b) < 70_000
        assert b[1] > 0  # the horizontal field points roughly north everywhere here
    assert igrf_enu_nT(60.0, 10.0, 0.0, "2026-01-01")[2] < -40_000  # points down in the north
    assert igrf_enu_nT(-60.0, 140.0, 0.0, "2026-01-01")[2] > 40_000  # up in the south


def test_igrf_field_in_a_scenario():
    d = _turntable(field={"igrf": {"lat_deg": 60.0, "lon_deg": 10.0, "alt_m": 0.0,
                                   "date": "2026-01-01"}})
    sim = simulate(scenario_from_dict(d))
    np.testing.assert_allclose(sim.truth.B_enu_nT, igrf_enu_nT(60.0, 10.0, 0.0, "2026-01-01"))


# --- scenario files and their errors ---------------------------------------------------


SHIPPED = sorted(
    [p for p in (Path(__file__).resolve().parents[1] / "pipeline" / "scenarios").glob("*.toml")]
    + [p for p in (Path(__file__).resolve().parents[1] / "pipeline" / "demo").glob("*.toml")
       if p.name != "campaign.toml"]
)


def test_every_shipped_scenario_loads():
    names = {p.name for p in SHIPPED}
    for n in ("li2020_section41.toml", "li2020_section41_noisy.toml", "multiaxis.toml",
              "turntable_tilt3.toml", "survey_lines.toml", "calibration_rotation.toml",
              "line_01.toml", "line_02.toml", "line_03.toml", "line_04.toml"):
        assert n in names
    for p in SHIPPED:
        sc = load_scenario(p)
        assert sc.name == p.stem
        assert sc.description


def test_demo_shares_the_sensor_and_hides_one_effect():
    demo = Path(__file__).resolve().parents[1] / "pipeline" / "demo"
    cal = load_scenario(demo / "calibration_rotation.toml")
    assert 110 <= cal.timing.duration_s <= 130 and cal.timing.mag_rate_hz == 100.0
    assert np.degrees(np.linalg.norm(so3_log(np.array(cal.sensor.R_body_mag)))) == pytest.approx(
        2.0, abs=0.05)
    for n in ("line_01", "line_02", "line_03", "line_04"):
        sc = load_scenario(demo / f"{n}.toml")
        assert sc.sensor == cal.sensor and sc.field == cal.field and sc.noise == cal.noise
        assert 110 <= sc.timing.duration_s <= 130
        assert bool(sc.effects.params()) == (n == "line_04")


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "bad.toml"
    p.write_text(text)
    return p


GOOD = """name = "x"
[timing]
duration_s = 2.0
[motion]
profile = "turntable"
rate_deg_s = 10.0
[field]
enu_nT = [0.0, 20000.0, -40000.0]
"""


def test_toml_errors_name_file_key_and_line(tmp_path):
    load_scenario(_write(tmp_path, GOOD))
    cases = [
        (GOOD.replace("rate_deg_s = 10.0", "rate_deg_s = 10.0\nrate_dge_s = 3"),
         "motion.rate_dge_s", 7),
        (GOOD.replace('profile = "turntable"', 'profile = "spin"'), "motion.profile", 5),
        (GOOD.replace("duration_s = 2.0", 'duration_s = "long"'), "timing.duration_s", 3),
        (GOOD.replace("[0.0, 20000.0, -40000.0]", "[0.0, 1.0]"), "field.enu_nT", 8),
        (GOOD + "[effects.hard_iron]\noffset = [1, 2, 3]\n", "effects.hard_iron.offset", 10),
        (GOOD + "[effects.magic]\n", "effects.magic", 9),
        (GOOD + "[output]\nmag_type = \"sensor_msgs/msg/Foo\"\n", "output.mag_type", 10),
        (GOOD.replace("[timing]\nduration_s = 2.0\n", "[timing]\n"), "timing.duration_s", None),
    ]
    for text, key, line in cases:
        p = _write(tmp_path, text)
        with pytest.raises(ConfigError) as ei:
            load_scenario(p)
        e = ei.value
        assert e.key == key, (key, e.one_line())
        assert e.line == line, (key, e.one_line())
        assert str(p) in e.one_line() and key in e.one_line()


def test_toml_syntax_error_names_the_line(tmp_path):
    with pytest.raises(ConfigError) as ei:
        load_scenario(_write(tmp_path, GOOD.replace("[field]", "[field")))
    assert ei.value.line == 7


def test_profile_duration_conflict():
    d = copy.deepcopy(_turntable(motion={"profile": "static_sweep", "n_headings": 4}))
    with pytest.raises(ConfigError, match="set by the motion profile"):
        scenario_from_dict(d)
    del d["timing"]["duration_s"]
    d["timing"] = {}
    sim = simulate(scenario_from_dict(d))
    assert len(sim.recording.mag) == 4


def test_truth_is_frozen():
    sim = simulate(scenario_from_dict(_turntable(effects={"hard_iron": {"offset_nT": [1, 2, 3]}})))
    with pytest.raises(ValueError):
        sim.truth.R_body_mag[0, 0] = 2.0
    with pytest.raises(ValueError):
        sim.recording.mag.values[0, 0] = 2.0
    assert sim.truth.to_dict()["offset_nT"] == [1.0, 2.0, 3.0]


def test_small_rotation_helper_sanity():
    # so3_exp/so3_log round trip used above (guards the hand-made expectations).
    v = np.array([0.01, -0.02, 0.03])
    np.testing.assert_allclose(so3_log(so3_exp(v)), v, atol=1e-15)

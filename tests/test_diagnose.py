"""The diagnose stage: search, evidence, findings, output.

Tests named ``test_wiring_*`` are self-model tests: their data come from
``tests/_diag_sim.py``, which makes them with ``stages.diagnose.model.evaluate``, the model
the diagnosis fits. They check the wiring (search, fit, Jacobians, evidence, output),
not the physics: a sign or convention error shared by the model and the data passes
them. The physics of each effect is checked on recordings written without
magalign's model (``tests/indep_gen.py``): ``tests/test_indep_corpus.py``,
``tests/test_local_source_indep.py``, ``tests/test_model_independent.py``, and on the real
recordings in ``tests/test_diagnose_real.py``.
"""

import json

import numpy as np
import pytest
from _diag_sim import make_data

from pipeline.core.recording import AlignedSeries, AttitudeSeries, Recording, VectorSeries
from pipeline.core.stage import Pipeline
from pipeline.core.vocabulary import EffectKind as K
from stages.context import Context
from stages.diagnose.model import Term
from stages.diagnose.result import DiagnoseConfig
from stages.diagnose.search import diagnose_data
from stages.diagnose.stage import Diagnose

CFG = DiagnoseConfig()


def _check_heldout_drops(diag):
    for f in diag.findings:
        ev = f.evidence
        assert ev["heldout_rms_after_nT"] < ev["heldout_rms_before_nT"], f.effect
        assert ev["delta_bic"] < 0


def _bump(window, peak):
    """Disturbance values for a hat basis of step 1 s: a triangle-ish bump in ENU."""
    a, b = window
    n = int(np.ceil(b - a)) + 1
    shape = np.sin(np.linspace(0, np.pi, n)) ** 2
    return (shape[:, None] * np.array([0.6, 0.3, 0.74]) * peak).ravel()


def _near(a, b, tol):
    return abs(a - b) < tol


CASES = [
    ("hard_iron", (Term(K.HARD_IRON),), (np.array([40.0, -25.0, 15.0]),),
     lambda f, s: np.allclose(f.params["offset_nT"], [40, -25, 15],
                              atol=4 * np.max(s["offset_nT"]) + 0.5)),
    ("time_offset", (Term(K.TIME_OFFSET),), (np.array([0.004]),),
     lambda f, s: _near(f.params["time_offset_s"], 0.004, 4 * s["time_offset_s"] + 1e-5)),
    ("eddy_current", (Term(K.EDDY_CURRENT),), (np.diag([0.004, -0.003, 0.001]).ravel(),),
     lambda f, s: _near(np.asarray(f.params["E_s"])[0, 0], 0.004, 2e-4)),
    ("field_drift", (Term(K.FIELD_DRIFT),), (np.r_[30.0, -20.0, 10.0, np.zeros(9)],),
     lambda f, s: np.allclose(f.params["peak_to_peak_nT"], [60, 40, 20], atol=6.0)),
    ("hard_iron_step", (Term(K.HARD_IRON_STEP, ((30.0, 40.0),)),),
     (np.array([40.0, 30.0, -20.0]),),
     lambda f, s: _near(f.where["windows_s"][0][0], 30, 0.3)
     and _near(f.where["windows_s"][0][1], 40, 0.3)),
    ("disturbance", (Term(K.DISTURBANCE, ((20.0, 26.0),)),), (_bump((20.0, 26.0), 200.0),),
     lambda f, s: _near(f.where["windows_s"][0][0], 20, 1.0)
     and _near(f.where["windows_s"][0][1], 26, 1.0)),
]


@pytest.mark.parametrize("kind,terms,values,check", CASES, ids=[c[0] for c in CASES])
def test_wiring_each_effect_detected_and_located(kind, terms, values, check):
    data, _ = make_data(terms, values, seed=11)
    diag, _ = diagnose_data(data, cfg=CFG)
    assert [f.effect for f in diag.findings] == [kind]
    f = diag.findings[0]
    assert check(f, f.sigma), (f.params, f.sigma, f.where)
    _check_heldout_drops(diag)
    assert f.where["frame"] in ("mag", "enu") and f.where["axes"]


@pytest.mark.parametrize("seed", [21, 22, 23, 24])
def test_wiring_null_recordings_have_no_findings(seed):
    data, _ = make_data(seed=seed)
    diag, _ = diagnose_data(data, cfg=CFG)
    assert diag.findings == ()
    assert diag.final["heldout_rms_nT"] == diag.baseline["heldout_rms_nT"]


def test_wiring_single_axis_motion_reports_hard_iron_not_identifiable():
    data, _ = make_data(single_axis=True, seed=5)
    diag, _ = diagnose_data(data, cfg=CFG)
    assert "hard_iron" in dict(diag.not_identifiable)
    assert diag.findings == ()


def test_wiring_stage_output_format_and_figures():
    data, truth = make_data((Term(K.TIME_OFFSET),), (np.array([0.005]),), seed=3)
    t0 = 1_700_000_000_000_000_000
    t_ns = t0 + np.round(data.t_s * 1e9).astype(np.int64)
    ta_ns = t0 + np.round(data.track.t_s * 1e9).astype(np.int64)
    rec = Recording("mem", (), VectorSeries(t_ns, data.y_nT), "/mag",
                    AttitudeSeries(ta_ns, data.track.q_enu_body), "/att")
    aligned = AlignedSeries(t_ns, data.y_nT, data.track.at(data.t_s))
    ctx = Context(recording=rec, aligned=aligned, calibration=None)
    pipe = Pipeline([Diagnose()], initial=("recording", "aligned", "calibration"))
    out = pipe.run(ctx)
    d = out.diagnosis.to_dict()
    json.dumps(d, allow_nan=False)
    assert d["format"] == "magalign.diagnosis/1"
    assert set(d) >= {"baseline", "final", "findings", "not_identifiable"}
    f = d["findings"][0]
    assert set(f) == {"effect", "params", "sigma", "evidence", "where", "explanation"}
    assert set(f["evidence"]) == {"statistic", "delta_bic", "rms_before_nT", "rms_after_nT",
                                  "heldout_rms_before_nT", "heldout_rms_after_nT"}
    assert set(f["where"]) == {"windows_s", "axes", "frame"}
    cal = out.calibration
    assert abs(cal.time_offset_s - 0.005) < 3e-4
    assert cal.to_dict()["format"] == "magalign.calibration/1"
    from stages.report import finding_figures

    figs = finding_figures(out.diagnosis, t0)
    assert len(figs) == 1 and figs[0][1][:8] == b"\x89PNG\r\n\x1a\n"
    assert "time_offset" in out.diagnosis.table()


def test_wiring_evidence_chains_from_baseline_to_final_on_two_effects():
    # drift and a time offset together: the evidence of each finding is a build-up in the
    # final order, whatever rounds of selection (and backward steps) led there
    drift = np.r_[40.0, -30.0, 20.0, np.zeros(9)]
    data, _ = make_data((Term(K.FIELD_DRIFT), Term(K.TIME_OFFSET)),
                        (drift, np.array([0.004])), seed=7)
    diag, res = diagnose_data(data, cfg=CFG)
    assert sorted(f.effect for f in diag.findings) == ["field_drift", "time_offset"]
    assert [t.kind.value for t in res.state.terms] == [f.effect for f in diag.findings]
    ev = [f.evidence for f in diag.findings]
    for key in ("rms", "heldout_rms"):
        b = "residual_rms_nT" if key == "rms" else "heldout_rms_nT"
        assert ev[0][f"{key}_before_nT"] == diag.baseline[b]
        for e0, e1 in zip(ev[:-1], ev[1:], strict=True):
            assert abs(e0[f"{key}_after_nT"] - e1[f"{key}_before_nT"]) < 1e-9
        assert ev[-1][f"{key}_after_nT"] == diag.final[b]
    _check_heldout_drops(diag)
    # the final model leaves white noise of 5 nT
    assert 4.5 < diag.final["residual_rms_nT"] < 5.5


def test_wiring_chain_evidence_rebuilds_a_swapped_history():
    # a history where the later-added term ends up first (as a backward step that drops and
    # re-adds a term produces): the stale numbers must be re-measured in the final order
    import dataclasses

    from stages.diagnose.fit import fit
    from stages.diagnose.search import _chain_evidence
    from stages.diagnose.statistics import heldout_rms

    data, _ = make_data((Term(K.HARD_IRON), Term(K.TIME_OFFSET)),
                        (np.array([60.0, -40.0, 20.0]), np.array([0.004])), seed=9)
    diag, res = diagnose_data(data, cfg=CFG)
    assert len(diag.findings) == 2
    st = res.state
    swapped = dataclasses.replace(st, terms=st.terms[::-1], values=st.values[::-1])
    final = fit(swapped, data)
    base = fit(dataclasses.replace(st, terms=(), values=()), data)
    cv_b, cv_f = heldout_rms(base.state, data, CFG), heldout_rms(final.state, data, CFG)
    stale = list(diag.findings[::-1])
    chained = _chain_evidence(stale, final, base, cv_b, cv_f, data, CFG)
    assert [f.effect for f in chained] == [f.effect for f in stale]
    e0, e1 = chained[0].evidence, chained[1].evidence
    assert e0["rms_before_nT"] == base.rms_nT and e1["rms_after_nT"] == final.rms_nT
    assert e0["rms_after_nT"] == e1["rms_before_nT"]
    assert e0["heldout_rms_after_nT"] == e1["heldout_rms_before_nT"]
    assert e0["heldout_rms_before_nT"] == cv_b and e1["heldout_rms_after_nT"] == cv_f
    # the stale evidence of the (now first) finding was measured after the other one
    assert stale[0].evidence["rms_before_nT"] < e0["rms_before_nT"]
    # each step still helps, and the params/sigma are the final model's
    for f, g in zip(chained, stale, strict=True):
        assert f.evidence["rms_after_nT"] < f.evidence["rms_before_nT"]
        assert f.params == g.params


def test_tilted_turntable_axis_found_with_a_reference_field(tmp_path):
    """A turntable recording whose only attitude is the table angle, axis tilted 3 deg
    towards bearing 30 deg (concealed: nothing in the file says so). Without a reference field
    the tilt is declared not identifiable; with one, the analysis fits ``axis_tilt`` and
    reports the lean along the field's horizontal bearing that gives the true axis-to-field
    angle."""
    from importlib import resources

    from pipeline.app.commands.diagnose import diagnose_file
    from pipeline.app.simulate import load_scenario, simulate, write_simulated

    sc = load_scenario(resources.files("pipeline") / "scenarios" / "turntable_tilt3.toml")
    sim = simulate(sc, seed=5)
    path = tmp_path / "tilt.mcap"
    write_simulated(sim, path)
    B = np.asarray(sim.truth.B_enu_nT, float)

    blind = diagnose_file(path).diagnosis.to_dict()
    assert "axis_tilt" in {n["effect"] for n in blind["not_identifiable"]}
    assert "axis_tilt" not in [f["effect"] for f in blind["findings"]]

    # With the field known, the analysis every command shares fits the tilt with the
    # misalignment before the diagnosis (Tang 2016, stages.turntable.plan_turntable) and
    # compensates the attitude: the calibration carries it, the diagnosis finds nothing left.
    ctx = diagnose_file(path, reference_field_enu_nT=tuple(B))
    d = ctx.diagnosis
    assert [f.effect for f in d.findings] == []
    tilt = ctx.calibration.effects["axis_tilt"]
    # What the data fix is the angle between the true axis and the field; the equivalent
    # axis of least tilt leans along the field's horizontal bearing by the change of that angle.
    bearing = np.degrees(np.arctan2(B[0], B[1]))
    a = np.radians(30.0)
    axis = np.array([np.sin(np.radians(3)) * np.sin(a), np.sin(np.radians(3)) * np.cos(a),
                     np.cos(np.radians(3))])
    Bu = B / np.linalg.norm(B)
    lean = np.degrees(np.arccos(Bu[2]) - np.arccos(axis @ Bu))
    assert abs(tilt["tilt_deg"] - lean) < 0.005, (tilt, lean)
    assert abs(tilt["azimuth_deg"] - bearing) < 1.0, (tilt, bearing)
    assert any("lean" in w for w in ctx.calibration.warnings)


# ----------------------------------------------------------------------------- field gradient

G_ENU = np.array([[1200.0, -800.0, 1500.0], [-800.0, -3000.0, 600.0], [1500.0, 600.0, 1800.0]])


def _grad_value(G):
    from pipeline.model.effects.soft_iron import SOFT_BASIS

    v, *_ = np.linalg.lstsq(SOFT_BASIS.reshape(5, 9).T, G.ravel(), rcond=None)
    return v


@pytest.mark.parametrize("frame, yaw_deg", [("enu", 0.0), ("attitude_source_local", 35.0)])
def test_wiring_field_gradient_found_with_positions(frame, yaw_deg):
    """A gradient of a few uT/m along a path (0.3 m): found, G within 3 sigma or 10 %."""
    from _diag_sim import lissajous_m

    from stages.diagnose.model import rot_z

    yaw = np.radians(yaw_deg)
    term = Term(K.FIELD_GRADIENT, yaw_rad=yaw)
    data, _ = make_data((term,), (_grad_value(G_ENU),), noise_nT=20.0, seed=11,
                        positions=lissajous_m, position_frame=frame)
    diag, _ = diagnose_data(data, cfg=CFG)
    assert "field_gradient" in diag.effects, diag.table()
    _check_heldout_drops(diag)
    f = next(f for f in diag.findings if f.effect == "field_gradient")
    M = np.asarray(f.params["G_nT_per_m"])
    S = np.asarray(f.sigma["G_nT_per_m"])
    want = G_ENU @ rot_z(yaw)
    ok = (np.abs(M - want) <= 3 * S + 1.0) | (np.abs(M - want) <= 0.1 * np.abs(want).max())
    assert ok.all(), (M, want, S)
    assert f.params["position_frame"] == frame
    assert "uT/m" in f.explanation


def test_wiring_field_gradient_null_and_without_positions():
    """No gradient along a path: no finding; no positions: not identifiable, said so."""
    from _diag_sim import lissajous_m

    data, _ = make_data(noise_nT=20.0, seed=12, positions=lissajous_m,
                        position_frame="attitude_source_local")
    diag, _ = diagnose_data(data, cfg=CFG)
    assert "field_gradient" not in diag.effects, diag.table()
    data, _ = make_data((Term(K.FIELD_DRIFT),), (np.r_[300.0, 100, -200, np.zeros(9)],),
                        noise_nT=20.0, seed=13)
    diag, _ = diagnose_data(data, cfg=CFG)
    why = dict(diag.not_identifiable).get("field_gradient", "")
    assert "no positions" in why
    drift = next(f for f in diag.findings if f.effect == "field_drift")
    assert "cannot be separated" in drift.explanation


# ----------------------------------------------------------------------------- sample and hold


def _sim(effects, seconds=40.0, noise=2.0, trajectory=None, motion="multiaxis"):
    from pipeline.app.simulate import scenario_from_dict, simulate

    timing = {"mag_rate_hz": 100.0, "attitude_rate_hz": 100.0}
    if isinstance(motion, str):
        motion = {"profile": motion}
        timing["duration_s"] = seconds
    sc = {"name": "sh", "timing": timing,
          "motion": motion, "field": {"enu_nT": [1500.0, 21000.0, -43000.0]},
          "effects": effects,
          "noise": {"mag_sigma_nT": noise, "heading_sigma_deg": 0.0,
                    "pitch_roll_sigma_deg": 0.0},
          "output": {"attitude_type": "geometry_msgs/msg/PoseStamped"}}
    if trajectory is not None:
        sc["trajectory"] = trajectory
    return simulate(scenario_from_dict(sc))


def _run(sim):
    from stages.resample import Resample

    ctx = Resample().run(Context(source="x", recording=sim.recording))
    return Diagnose(config=DiagnoseConfig(max_samples=3000)).run(ctx).diagnosis


def test_sample_hold_found_with_its_native_rate():
    sim = _run(_sim({"sample_hold": {"native_rate_hz": 70.0}}))
    f = next((f for f in sim.findings if f.effect == "sample_hold"), None)
    assert f is not None, sim.table()
    assert abs(f.params["native_rate_hz"] - 70.0) < 0.7  # Hz, 1 %
    assert abs(f.params["repeated_fraction"] - 0.30) < 0.01
    ev = f.evidence
    assert ev["heldout_rms_after_nT"] < ev["heldout_rms_before_nT"]
    assert "native" in f.explanation


def test_sample_hold_never_fires_without_repeats():
    from pipeline.model.sample_hold import detect_sample_hold

    # noise-free and static: consecutive samples are identical, but nothing changes
    # noise-free dwells at 8 headings (100 Hz, 2 s each): every sample in a dwell repeats
    t_ns = np.arange(1600, dtype=np.int64) * 10_000_000
    ang = np.radians(45.0) * (np.arange(1600) // 200)
    mag = np.stack([20000 * np.cos(ang), 20000 * np.sin(ang), -43000 + 0 * ang], -1)
    assert np.mean(np.all(np.diff(mag, axis=0) == 0, axis=1)) > 0.99
    assert detect_sample_hold(t_ns, mag) is None
    # moving, noisy, no sample-and-hold
    diag = _run(_sim({}, seconds=30.0))
    assert "sample_hold" not in diag.effects, diag.table()


@pytest.mark.parametrize("G_nT_per_m, words", [
    (np.diag([2000.0, -1500.0, -500.0]), "2.55 uT/m in all"),  # steel indoors
    (np.diag([2.0, 0.0, -2.0]), "2.8 nT/m in all"),  # a regional gradient outdoors
])
def test_gradient_words_use_the_unit_its_size_needs(G_nT_per_m, words):
    """A survey's 2 nT/m gradient reads in nT/m; it read "0.00 uT/m" before."""
    from pipeline.model.effects.base import EFFECTS

    text = EFFECTS[K.FIELD_GRADIENT].remark({"G_nT_per_m": G_nT_per_m.tolist()}, 100.0)
    assert words in text, text
    assert "0.00 " not in text

"""The diagnosis on independently made recordings (issue 15 A; ``tests/indep_gen.py``).

Small versions only: the full corpus (>= 60 nulls, every effect at three sizes) is in
``bench/diagnose.py``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from indep_gen import ATTITUDE_TYPES, Spec, effect_specs, null_specs, sized, strength, write
from scipy.spatial.transform import Rotation

from pipeline.app.commands.diagnose import diagnose_file
from pipeline.io.mcap_read import read_recording
from stages.context import Context
from stages.estimate import fit_calibration
from stages.resample import Resample


def _calibrate(path):
    rec = read_recording(path)
    ctx = Resample().run(Context(source=str(path), recording=rec))
    return fit_calibration(rec, ctx.aligned)


def _angle_deg(R_est, spec):
    Rt = Rotation.from_rotvec(np.radians(spec.rotvec_body_mag_deg)).as_matrix()
    return float(np.degrees(Rotation.from_matrix(np.asarray(R_est) @ Rt.T).magnitude()))


@pytest.mark.parametrize("att_type", ATTITUDE_TYPES)
def test_noise_free_null_recovers_rotation(tmp_path, att_type):
    # the generator checked with noise off: same rates and phase, so no interpolation
    # either; R to far better than 0.01 deg and a residual at rounding level
    spec = Spec(name="clean", seed=5, duration_s=30.0, mag_rate_hz=50.0, att_rate_hz=50.0,
                att_type=att_type, mag_noise_nT=0.0, att_noise_deg=0.0)
    cal = _calibrate(write(spec, tmp_path / "clean.mcap"))
    assert _angle_deg(cal.R_body_mag, spec) < 0.01
    assert cal.residual_rms_nT < 1e-3  # of a 48 000 nT field
    assert np.allclose(cal.B_enu_nT, spec.B_enu_nT, atol=1e-3)


def test_noise_free_null_other_rate_and_phase(tmp_path):
    # attitude at half the rate, shifted by a third of its period, jittered: the residual is
    # the interpolation of the attitude only (well under a nanotesla)
    spec = Spec(name="clean2", seed=6, duration_s=30.0, mag_rate_hz=100.0, att_rate_hz=50.0,
                att_phase_s=0.0067, att_jitter_s=0.001, mag_noise_nT=0.0, att_noise_deg=0.0)
    cal = _calibrate(write(spec, tmp_path / "clean2.mcap"))
    assert _angle_deg(cal.R_body_mag, spec) < 0.01
    assert cal.residual_rms_nT < 1.0


def test_strength_scales_with_amplitude():
    # the size rule: twice the lag, twice the strength (the effect is linear to first order)
    base = Spec(name="s", seed=7, duration_s=30.0)
    s1 = strength(Spec(**{**base.__dict__, "effects": {"time_offset": {"time_offset_s": 0.002}}}),
                  "time_offset")
    s2 = strength(Spec(**{**base.__dict__, "effects": {"time_offset": {"time_offset_s": 0.004}}}),
                  "time_offset")
    assert s2 == pytest.approx(2 * s1, rel=0.02)
    assert strength(base, "time_offset") < 1e-6


def test_independent_nulls_have_no_findings(tmp_path):
    # one of each message type; attitude jitter up to 2 % of its period (larger jitter of a
    # slow attitude stream under fast swings is a known miss, reported by bench/diagnose.py)
    specs = null_specs(8, seed=151, duration_s=30.0, max_jitter_frac=0.02)[:4]
    assert sorted(s.att_type for s in specs) == sorted(ATTITUDE_TYPES)
    for s in specs:
        ctx = diagnose_file(write(s, tmp_path / f"{s.name}.mcap"))
        assert [f.effect for f in ctx.diagnosis.findings] == [], s


@pytest.mark.parametrize("case,reported", [("time_offset", "time_offset"),
                                           ("eddy_iso", "time_offset"),
                                           ("eddy_current", "eddy_current")])
def test_independent_rate_effects_named(tmp_path, case, reported):
    # mag 100 Hz, attitude 50 Hz (the rate mix of issue 15); 15x the detection threshold
    base = Spec(name=case, seed=17, duration_s=40.0, mag_rate_hz=100.0, att_rate_hz=50.0,
                att_phase_s=0.007)
    spec, rep, exp, st = sized(base, case, 15.0, np.random.default_rng(3))
    assert rep == reported and st == pytest.approx(15.0, rel=0.1)
    ctx = diagnose_file(write(spec, tmp_path / f"{case}.mcap"))
    found = {f.effect: f for f in ctx.diagnosis.findings}
    assert set(found) == {reported}
    f = found[reported]
    key = "time_offset_s" if reported == "time_offset" else "E_s"
    est, true, sig = (np.asarray(x, dtype=float) for x in (f.params[key], exp[key],
                                                           f.sigma[key]))
    assert np.all((np.abs(est - true) <= 3 * sig + 1e-12)
                  | (np.abs(est - true) <= 0.1 * np.max(np.abs(true))))


def test_slow_attitude_under_fast_motion_names_nothing_and_says_why(tmp_path):
    # null_005 of the bench's corpus (seed 2026): attitude at 12.5 Hz (0.25x the
    # magnetometer's) under multi-axis swings; the interpolation error (~15 nT RMS) projects
    # on a ~90 nT offset along mag z. Nothing is named; the diagnosis says the attitude is
    # too slow for the motion.
    import dataclasses

    spec = dataclasses.replace(null_specs(60, 2026)[5], duration_s=30.0)
    assert spec.att_rate_hz == 12.5 and not spec.effects
    ctx = diagnose_file(write(spec, tmp_path / "slow.mcap"))
    assert [f.effect for f in ctx.diagnosis.findings] == []
    why = dict(ctx.diagnosis.not_identifiable)
    assert "too slow for this motion" in why["hard_iron"]


def test_weak_long_hard_iron_step_is_found_by_the_moving_mean_scan(tmp_path):
    # the bench corpus' hard_iron_step at 6x its threshold (seed 2027): ~6 nT held for 8 s
    # under 1 nT and 0.005 deg of noise; the squared-norm scan opens no window, the moving
    # mean of the residual vector does
    from indep_gen import effect_specs

    spec, rep, exp, st = effect_specs(2027, targets=(6.0,), cases=("hard_iron_step",))[0]
    ctx = diagnose_file(write(spec, tmp_path / "step.mcap"))
    fs = ctx.diagnosis.findings
    assert {f.effect for f in fs} == {"hard_iron_step"}
    # it may come as back-to-back pieces of one offset: together they cover the step
    wins = sorted(w for f in fs for w in f.params["windows_s"])
    (ta, tb), = exp["windows_s"]
    assert abs(wins[0][0] - ta) < 0.5 and abs(wins[-1][1] - tb) < 0.5  # s
    assert all(b2 - a1 < 0.5 for (_, a1), (b2, _) in zip(wins[:-1], wins[1:], strict=True))
    true = np.asarray(exp["offset_nT"])
    for f in fs:
        est, sig = np.asarray(f.params["offset_nT"]), np.asarray(f.sigma["offset_nT"])
        err = np.abs(est - true)
        assert np.all((err <= 3 * sig) | (err <= 0.1 * np.abs(true).max()))


#: (case, seed) of every effect the generator makes; each 15x its detection threshold
PHYSICAL_CASES = [(c, 30 + i) for i, c in enumerate(
    ("hard_iron", "soft_iron", "field_drift", "field_gradient", "disturbance",
     "hard_iron_step", "heading_drift"))]


@pytest.mark.parametrize("case,seed", PHYSICAL_CASES)
def test_every_effect_is_named_and_measured_on_independent_recordings(tmp_path, case, seed):
    """The physics the self-model tests (``test_wiring_*``) only wire up, checked against
    recordings made outside the model: the effect is the one finding, and each of its
    parameters the generator states is recovered within 3 sigmas (or 10 % of its size);
    windows within 1 s."""
    base = Spec(name=case, seed=seed, duration_s=40.0, mag_rate_hz=100.0, att_rate_hz=50.0,
                att_phase_s=0.003)
    spec, rep, exp, st = sized(base, case, 15.0, np.random.default_rng(seed))
    assert rep == case
    ctx = diagnose_file(write(spec, tmp_path / f"{case}.mcap"))
    found = {f.effect: f for f in ctx.diagnosis.findings}
    assert case in found, (case, list(found))
    f = found[case]
    checked = 0
    for key, true in exp.items():
        if key == "windows_s":
            (ta, tb), = true
            got = sorted(w for g in ctx.diagnosis.findings if g.effect == case
                         for w in g.params["windows_s"])
            assert abs(got[0][0] - ta) < 1.0 and abs(got[-1][1] - tb) < 1.0, (got, true)
            checked += 1
            continue
        if key not in f.params or key not in (f.sigma or {}):
            continue
        est, tru = np.asarray(f.params[key], float), np.asarray(true, float)
        sig = np.asarray(f.sigma[key], float)
        ok = (np.abs(est - tru) <= 3 * sig + 1e-12) | (np.abs(est - tru)
                                                        <= 0.1 * np.max(np.abs(tru)))
        assert np.all(ok), (key, est, tru, sig)
        checked += 1
    assert checked >= 1, (case, exp, f.params)


def test_a_drift_beside_a_magnet_is_named_when_it_is_there(tmp_path):
    """A real drift and a step in the middle of one recording: both named, both measured.

    A drift beside a transient must earn its margin with the transient held where it was
    without the drift (nested.earns_beside_lookalikes): on a lab excerpt the pair had
    traded a 3000 nT magnet's offset for a drift the recording does not have. A drift that
    is there keeps its margin under that check.
    """
    drift, _, exp_drift, _ = effect_specs(31, targets=(15.0,), cases=("field_drift",))[0]
    step, _, exp_step, _ = effect_specs(33, targets=(15.0,), cases=("hard_iron_step",))[0]
    spec = dataclasses.replace(drift, effects={**drift.effects, **step.effects})
    diag = diagnose_file(write(spec, tmp_path / "both.mcap")).diagnosis
    fs = {f.effect: f for f in diag.findings}
    assert set(fs) == {"field_drift", "hard_iron_step"}, sorted(fs)
    (ta, tb), = exp_step["windows_s"]
    (fa, fb), = fs["hard_iron_step"].params["windows_s"]
    assert abs(fa - ta) < 0.5 and abs(fb - tb) < 0.5  # s
    f_step = fs["hard_iron_step"]
    true, est = np.asarray(exp_step["offset_nT"]), np.asarray(f_step.params["offset_nT"])
    sig = np.asarray(f_step.sigma["offset_nT"])
    assert np.all(np.abs(est - true) <= 0.1 * np.abs(true).max() + 3 * sig)  # nT
    ptp = np.asarray(fs["field_drift"].params["peak_to_peak_nT"])
    assert np.allclose(ptp, exp_drift["peak_to_peak_nT"], rtol=0.1, atol=5.0)  # nT

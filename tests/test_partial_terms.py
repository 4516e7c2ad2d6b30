"""A term the motion determines only in part: fitted where the recording determines it,
held and named where it does not.

A ground survey (tests/indep_gen.py, ``path="survey"``): a calibration manoeuvre at four
headings with roll +-10 deg and pitch +-5 deg, then lines walked north and south. The sensor
carries a hard-iron offset of (180, -90, 60) nT. The heading turns determine the offset's
horizontal components. Its vertical component reads almost as the vertical field: the other
terms mimic 99.7 % of it (efficiency 0.003). Yet at 1 nT of noise the tilts leave it a
sigma of under 1 nT, a five-hundredth of its prior (500 nT): the recording determines it,
and the diagnosis fits the whole offset.

A combination is held only where the data know it less well than the prior does. With a
prior tighter than the data's sigma (an offset known beforehand to 0.3 nT, which the test
sets), the same survey holds the vertical component at zero with the prior's sigma, says
so and names nothing else for what the held part leaves in the residual.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from indep_gen import Spec, readings, write
from scipy.spatial.transform import Rotation

from pipeline.app.commands.diagnose import diagnose_file
from pipeline.app.exports import export_text
from pipeline.core.verdict import plain_words
from pipeline.core.vocabulary import EffectKind
from pipeline.model.calibration import Calibration
from pipeline.model.effects import IRON_PRIOR
from pipeline.model.effects.base import CONFOUND_RATIO
from stages.diagnose.fit import fit
from stages.diagnose.model import (
    AttitudeTrack,
    FitData,
    ModelState,
    Term,
    evaluate,
)
from stages.diagnose.partial import (
    _decimated,
    _efficiencies,
    _info_per_unit,
    partial_candidate,
    tilt_to_determine_deg,
)
from stages.diagnose.statistics import robust_sigma

OFFSET = [180.0, -90.0, 60.0]  # nT, mag frame

#: a prior on the offset tighter than what the survey's tilts teach about its vertical part
#: (0.6-0.8 nT): an offset known to 0.3 nT before the survey
TIGHT_PRIOR_NT = 0.3
HELD_OFFSET = [180.0, -90.0, 0.0]  # nT: the offset of the survey diagnosed with it

#: terms that could take up what the held vertical offset leaves in the residual
ABSORBERS = {"field_drift", "hard_iron_step", "disturbance"}


def survey(name: str, noise_nT: float = 1.0, att_rate_hz: float = 20.0, **effects) -> Spec:
    """A 90 s ground survey: 30 s of calibration turns and tilts, then lines 2 m apart."""
    return Spec(name, seed=21, duration_s=90.0, mag_rate_hz=50.0, att_rate_hz=att_rate_hz,
                path="survey", survey_calibration_s=30.0, mag_noise_nT=noise_nT,
                att_noise_deg=0.002 if noise_nT else 0.0, effects=effects)


def fit_data(spec: Spec, every: int = 1) -> FitData:
    """The generator's readings as the diagnosis fits them (stamps in s from the first sample)."""
    r = readings(spec)
    track = AttitudeTrack(r["t_att_s"], r["att"].as_quat())  # scalar-last, as the model's
    keep = (np.arange(len(r["t_mag_s"])) % every == 0) & (r["t_mag_s"] > 0.2) & (
        r["t_mag_s"] < spec.duration_s - 0.2)
    return FitData(r["t_mag_s"][keep], r["mag_nT"][keep], track)


def truth_state(spec: Spec, term: Term) -> ModelState:
    R = Rotation.from_rotvec(np.radians(spec.rotvec_body_mag_deg)).as_matrix()
    return ModelState(R, np.asarray(spec.B_enu_nT, float), (term,),
                      (np.asarray(spec.effects["hard_iron"]["offset_nT"], float),))


def test_the_generator_without_noise_is_the_model_and_the_vertical_offset_mostly_confounded():
    """Noise off, the attitude sampled with the magnetometer (no interpolation): the model at
    the truth reproduces the survey exactly. The offset's efficiencies against R and B: the
    vertical one below CONFOUND_RATIO (the tilts of +-10 deg), the horizontal ones above."""
    spec = survey("quiet", noise_nT=0.0, att_rate_hz=50.0, hard_iron={"offset_nT": OFFSET})
    data = fit_data(spec, every=2)
    st = truth_state(spec, Term(EffectKind.HARD_IRON))
    r = data.y_nT - evaluate(st, data, jacobian=False).y_nT
    assert np.abs(r).max() < 1e-6  # nT
    J = evaluate(st, data).jac.reshape(-1, st.n_params())
    eff, X = _efficiencies(J[:, :6], J[:, 6:9])
    assert eff[0] < CONFOUND_RATIO < eff[1]
    assert abs(X[2, 0]) > 0.99  # the weak combination is the mag z axis (body up, R ~ 2 deg)


def test_the_restricted_jacobian_is_the_full_one_on_the_fitted_combinations():
    """``J_full A`` for a partial term and ``J_full U`` for what it holds, checked by central
    differences of the prediction through the state's own update."""
    spec = survey("jac", hard_iron={"offset_nT": OFFSET})
    data = fit_data(spec, every=10)
    u = np.array([0.02, 0.02, 1.0]) / np.linalg.norm([0.02, 0.02, 1.0])
    A = np.linalg.svd(np.eye(3) - np.outer(u, u))[0][:, :2]
    As = np.linalg.qr(np.random.default_rng(1).normal(size=(5, 3)))[0]
    hi = Term(EffectKind.HARD_IRON).restricted(A, fixed=[1.0, 2.0, 3.0])
    si = Term(EffectKind.SOFT_IRON).restricted(As)
    st0 = truth_state(spec, hi).with_term(si)
    assert float(u @ st0.values[0]) == pytest.approx(float(u @ OFFSET))
    np.testing.assert_allclose(st0.values[1], 0.0)  # appended at ``fixed``: zero
    st = st0.update(np.r_[np.zeros(6), 50.0, -30.0, 0.01, 0.003, -0.002])
    # an update moves the fitted combinations only
    assert float(u @ st.values[0]) == pytest.approx(float(u @ OFFSET), abs=1e-9)
    assert float(u @ Term(EffectKind.HARD_IRON).restricted(A, [1.0, 2.0, 3.0]).null_value()) \
        == pytest.approx(float(u @ [1.0, 2.0, 3.0]))
    ev = evaluate(st, data)
    assert ev.jac.shape[2] == 6 + 2 + 3 and ev.J_held is not None
    assert ev.J_held.shape[2] == 1 + 2
    for p in range(st.n_params()):
        h = 1e-6 if p < 3 else (1e-3 if p < 8 else 1e-5)
        dx = np.zeros(st.n_params())
        dx[p] = h
        fd = (evaluate(st.update(dx), data, jacobian=False).y_nT
              - evaluate(st.update(-dx), data, jacobian=False).y_nT) / (2 * h)
        assert np.max(np.abs(fd - ev.jac[:, :, p])) < 1e-6 * np.max(np.abs(fd)), p
    vals = list(st.values)
    h = 1e-2
    vals[0] = st.values[0] + h * hi.undetermined()[:, 0]
    yp = evaluate(ModelState(st.R_body_mag, st.B_enu_nT, st.terms, tuple(vals)), data,
                  jacobian=False).y_nT
    vals[0] = st.values[0] - h * hi.undetermined()[:, 0]
    ym = evaluate(ModelState(st.R_body_mag, st.B_enu_nT, st.terms, tuple(vals)), data,
                  jacobian=False).y_nT
    np.testing.assert_allclose((yp - ym) / (2 * h), ev.J_held[:, :, 0], atol=1e-9)


def test_more_tilt_would_determine_the_vertical_offset(monkeypatch):
    """Held under a tight prior, the vertical offset would be determined by a larger tilt,
    beyond the recording's +-10 deg roll (plus swings) and below 90 deg: its data sigma
    falls as the tilt grows."""
    monkeypatch.setitem(IRON_PRIOR, "hard_iron", TIGHT_PRIOR_NT)
    spec = survey("tilt", hard_iron={"offset_nT": OFFSET})
    data = fit_data(spec, every=4)
    u = np.array([0.0, 0.0, 1.0])
    hi = Term(EffectKind.HARD_IRON).restricted(np.eye(3)[:, :2])
    res = fit(truth_state(spec, hi), data)
    assert hi.undetermined()[:, 0] == pytest.approx(u)
    per_unit = _info_per_unit(res, data, _decimated(data), robust_sigma(res.residual_nT))
    need = tilt_to_determine_deg(res.state, 0, data, per_unit)
    assert need is not None and 14.0 < need < 60.0


def test_a_combination_is_held_only_where_the_data_know_it_less_than_the_prior():
    """One survey, one model: under the noise it has, the whole offset is tested; under a
    noise that leaves the vertical part a sigma beyond the prior (and the horizontal ones
    within it), only the vertical part is held."""
    spec = survey("which", hard_iron={"offset_nT": OFFSET})
    data = fit_data(spec, every=2)
    cur = fit(ModelState(truth_state(spec, Term(EffectKind.HARD_IRON)).R_body_mag,
                         np.asarray(spec.B_enu_nT, float), (), ()), data)
    sig = robust_sigma(cur.residual_nT)
    whole = partial_candidate(cur, Term(EffectKind.HARD_IRON), data, sig)
    assert whole is not None and not whole.term.partial
    # the vertical part's data sigma is under 1 nT, the horizontal ones' 4-8 times smaller:
    # at 2,000 times the noise the vertical one is beyond the 500 nT prior, they are not
    held = partial_candidate(cur, Term(EffectKind.HARD_IRON), data, 2000.0 * sig)
    assert held is not None and held.term.partial
    (u,) = held.term.undetermined().T
    assert abs(u[2]) > 0.99
    # at 20,000 times the noise the horizontal parts' sigmas are beyond the prior too, but
    # they are not confounded (efficiencies 0.04 and 0.14): noisy, not undetermined, they are
    # still tested (and left to the evidence)
    noisy = partial_candidate(cur, Term(EffectKind.HARD_IRON), data, 2e4 * sig)
    assert noisy is not None and noisy.term.undetermined().shape[1] == 1


@pytest.fixture(scope="module")
def surveyed(tmp_path_factory):
    """The survey with the offset and without it, diagnosed as ``magalign diagnose`` does,
    under the effect's prior and under :data:`TIGHT_PRIOR_NT` (whose offset has no vertical
    part: the held value, zero, is then the truth)."""
    cases = {"whole": ({"hard_iron": {"offset_nT": OFFSET}}, None),
             "clean": ({}, None),
             "held": ({"hard_iron": {"offset_nT": HELD_OFFSET}}, TIGHT_PRIOR_NT),
             "held_clean": ({}, TIGHT_PRIOR_NT)}
    out = {}
    for name, (effects, prior) in cases.items():
        spec = survey(name, **effects)
        path = write(spec, tmp_path_factory.mktemp(name) / f"{name}.mcap")
        with pytest.MonkeyPatch.context() as mp:
            if prior is not None:
                mp.setitem(IRON_PRIOR, "hard_iron", prior)
            out[name] = (spec, diagnose_file(path))
    return out


def _rot_err_deg(ctx, spec) -> np.ndarray:
    cal = ctx.need_calibration()
    return np.abs(np.asarray(cal.rotvec_body_mag_deg) - np.asarray(spec.rotvec_body_mag_deg))


def _the_offset(diag):
    """The one ``hard_iron`` finding, its offset and sigma (nT); no absorber beside it."""
    effects = [f.effect for f in diag.findings]
    assert effects.count("hard_iron") == 1 and not ABSORBERS & set(effects), effects
    hi = diag.findings[effects.index("hard_iron")]
    return hi, np.asarray(hi.params["offset_nT"]), np.asarray(hi.sigma["offset_nT"])


def test_the_survey_determines_the_whole_offset(surveyed):
    """Under the effect's own prior the tilts determine the vertical part: fitted, not held."""
    spec, ctx = surveyed["whole"]
    diag = ctx.diagnosis
    hi, o, s = _the_offset(diag)
    assert np.all(np.abs(o - OFFSET) < np.maximum(3 * s, 1.0)), (o, s)  # nT
    assert s[2] < 2.0 and "not determined" not in hi.explanation
    assert "hard_iron" not in dict(diag.not_identifiable)
    cal = ctx.need_calibration()
    assert "undetermined_iron" not in cal.checks or \
        "held" not in cal.checks["undetermined_iron"]
    err = _rot_err_deg(ctx, spec)
    assert err.max() < 0.01, err  # deg
    assert np.all(err <= 3 * np.asarray(cal.sigma_rotvec_deg))


def test_under_a_tight_prior_the_vertical_part_is_held(surveyed):
    spec, ctx = surveyed["held"]
    diag = ctx.diagnosis
    hi, o, s = _the_offset(diag)
    effects = [f.effect for f in diag.findings]
    assert np.all(np.abs(o[:2] - HELD_OFFSET[:2]) < 5.0), o  # nT
    # the vertical part: held at zero (the held combination is along mag z to 2 %, so the
    # z component takes 2 % of the horizontal part), its sigma the prior's, and said in words
    # with the data's sigma and the motion that would determine it
    (u,) = ctx.need_calibration().checks["undetermined_iron"]["held"]["hard_iron"]
    assert abs(float(np.dot(u, o))) < 1e-6 and abs(o[2]) < 5.0
    assert s[2] == pytest.approx(TIGHT_PRIOR_NT, rel=0.01)
    assert np.all(s[:2] < 50.0)
    words = hi.explanation
    assert "vertical" in words and "not determined" in words and "tilting" in words
    assert "from the data" in words
    assert "hard_iron" not in dict(diag.not_identifiable)
    # the misalignment as without the offset, and within its sigma
    cal = ctx.need_calibration()
    err = _rot_err_deg(ctx, spec)
    assert err.max() < 0.01, err  # deg
    assert np.all(err <= 3 * np.asarray(cal.sigma_rotvec_deg))
    # the calibration carries the same offset and says which part of it is held
    np.testing.assert_allclose(cal.offset_nT, o)
    np.testing.assert_allclose(cal.sigma_offset_nT, s)
    held = np.asarray(cal.checks["undetermined_iron"]["held"]["hard_iron"])
    assert held.shape == (1, 3) and abs(held[0, 2]) > 0.99
    assert "hard_iron" in cal.checks["undetermined_iron"]["terms"]
    # the rotation's doubt keeps the words the verdict turns into advice
    (doubt,) = [d for d in cal.checks["doubts"] if d.startswith("the motion cannot determine")]
    assert "holds 1 combination" in doubt and plain_words(doubt)[1] is not None
    # the restore applies the calibration's offset (the held part left in the vertical
    # field): over every sample its residual is the fit's
    assert cal.residual_rms_nT == pytest.approx(hi.evidence["rms_after_nT"], rel=0.05)
    again = Calibration.from_json(cal.to_json())
    np.testing.assert_allclose(again.offset_nT, cal.offset_nT)
    # an export says the held component is a reference, not a measurement
    for fmt in ("yaml", "ardupilot", "magcal"):
        words = [w for w in export_text(again, fmt).split() if w not in ("#", "%")]
        assert "was not determined by the motion: it is held at 0 nT" in " ".join(words), fmt
    # diagnosis.json: CONVENTIONS keys only, the params those of hard_iron
    d = json.loads(json.dumps(diag.to_dict()))
    f = d["findings"][effects.index("hard_iron")]
    assert set(f) == {"effect", "params", "sigma", "evidence", "where", "explanation"}
    assert set(f["params"]) == {"offset_nT"} and set(f["sigma"]) == {"offset_nT"}


def test_the_same_survey_without_the_offset_stays_clean(surveyed):
    """Without an offset nothing is named; under the effect's prior the offset is determined
    (so not listed), under the tight one its vertical part is not, and the sigma covers one
    of the prior's size."""
    for name, listed in (("clean", False), ("held_clean", True)):
        spec, ctx = surveyed[name]
        assert [f.effect for f in ctx.diagnosis.findings] == [], name
        assert _rot_err_deg(ctx, spec).max() < 0.01, name  # deg
        assert ("hard_iron" in dict(ctx.diagnosis.not_identifiable)) is listed, name
        und = ctx.need_calibration().checks.get("undetermined_iron", {})
        assert ("hard_iron" in und.get("terms", [])) is listed, name


def test_a_reference_field_determines_the_whole_offset(tmp_path):
    """With the field given, the vertical offset no longer reads as the vertical field: the
    whole offset is fitted and nothing is held."""
    spec = survey("ref", hard_iron={"offset_nT": OFFSET})
    ctx = diagnose_file(write(spec, tmp_path / "ref.mcap"),
                        reference_field_enu_nT=tuple(spec.B_enu_nT))
    hi, o, _ = _the_offset(ctx.diagnosis)
    assert np.all(np.abs(o - OFFSET) < 5.0)
    assert "not determined" not in hi.explanation
    assert "held" not in ctx.need_calibration().checks.get("undetermined_iron", {})
    assert _rot_err_deg(ctx, spec).max() < 0.01


def test_an_offset_of_typical_size_beside_buried_objects_is_fitted_whole(tmp_path):
    """The objects' survey of tests/test_survey_products.py with a sensor offset of the
    prior's size along mag z: the vertical part is 99.7 % confounded with the vertical field
    but known to under a nanotesla. Held, it would leave its signature (about 20 nT over 1 nT
    of noise) for other terms and hide an object; fitted, both objects are found."""
    from test_survey_products import OBJECTS, SPECS

    offset = [40.0, -30.0, 500.0]
    spec = dataclasses.replace(SPECS["objects"], name="iron",
                               effects={**SPECS["objects"].effects,
                                        "hard_iron": {"offset_nT": offset}})
    ctx = diagnose_file(write(spec, tmp_path / "iron.mcap"))
    diag = ctx.diagnosis
    hi, o, s = _the_offset(diag)
    assert np.all(np.abs(o - offset) < 3 * s + 1.0), (o, s)  # nT
    assert s[2] < 50.0 and "not determined" not in hi.explanation
    sources = [f for f in diag.findings if f.effect == "local_source"]
    assert len(sources) == len(OBJECTS), [f.effect for f in diag.findings]

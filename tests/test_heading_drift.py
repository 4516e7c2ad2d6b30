"""heading_drift: the attitude source's heading error growing during a recording.

Tests named ``test_wiring_*`` are self-model tests: their data come from
``tests/_diag_sim.py``, which makes them with ``stages.diagnose.model.evaluate``, the model
the diagnosis fits. They check the wiring (search, fit, Jacobians, evidence, output),
not the physics: a sign or convention error shared by the model and the data passes
them. ``test_independent_*`` checks the effect on a recording written
by ``tests/indep_gen.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _diag_sim import make_data
from indep_gen import Spec, sized, write

from pipeline.app.commands.diagnose import diagnose_file
from pipeline.core.vocabulary import EffectKind
from stages.diagnose.catalogue import explanation, identifiability_reason, motion_stats
from stages.diagnose.model import (
    ModelState,
    Term,
    evaluate,
    heading_drift_params,
    heading_signature_fraction,
)
from stages.diagnose.search import diagnose_data


def test_wiring_heading_jacobian_matches_finite_differences():
    terms = (Term(EffectKind.HARD_IRON), Term(EffectKind.HEADING_DRIFT))
    vals = (np.array([30.0, -20.0, 10.0]), np.radians([0.5, -0.2]))
    data, truth = make_data(terms, vals, duration_s=30.0, rate_hz=50.0, seed=4)
    J = evaluate(truth, data).J
    P = truth.n_params()
    eps = np.array([1e-6] * 3 + [1e-2] * 3 + [1e-2] * 3 + [1e-6] * 2)
    for k in range(P):
        dx = np.zeros(P)
        dx[k] = eps[k]
        yp = evaluate(truth.update(dx), data, jacobian=False).y_nT
        ym = evaluate(truth.update(-dx), data, jacobian=False).y_nT
        num = (yp - ym) / (2 * eps[k])
        assert np.max(np.abs(J[:, :, k] - num)) <= 1e-4 * (np.max(np.abs(num)) + 1e-9), k


def test_wiring_heading_drift_is_a_rotation_of_the_field_about_up():
    # exact: the reading with a heading error h is R.T C_rep.T Rz(h) B; E, N change in the
    # ratio -B_N : B_E and U, |B| do not (CONVENTIONS heading_drift)
    v = np.radians([0.3, 0.0])
    data, st = make_data((Term(EffectKind.HEADING_DRIFT),), (v,), duration_s=20.0, noise_nT=0.0)
    base = ModelState(st.R_body_mag, st.B_enu_nT)
    y1 = evaluate(st, data, jacobian=False).y_nT
    y0 = evaluate(base, data, jacobian=False).y_nT
    assert np.allclose(np.linalg.norm(y1, axis=1), np.linalg.norm(y0, axis=1), atol=1e-6)
    h_end = np.radians(0.3)  # P1 = 1 at the end
    B = st.B_enu_nT
    dB = np.array([np.cos(h_end) * B[0] - np.sin(h_end) * B[1],
                   np.sin(h_end) * B[0] + np.cos(h_end) * B[1], B[2]]) - B
    assert heading_signature_fraction(dB[None, :], B) == pytest.approx(1.0, abs=1e-4)
    assert heading_signature_fraction(np.array([[0.0, 0.0, 5.0]]), B) == pytest.approx(0.0)
    p = heading_drift_params(v, data)
    assert p["peak_to_peak_deg"] == pytest.approx(0.6, rel=1e-3)
    assert p["rate_deg_per_h"] == pytest.approx(0.6 / (data.track.t_s[-1] / 3600.0), rel=1e-3)


def test_heading_drift_words_and_identifiability():
    text = explanation(EffectKind.HEADING_DRIFT, {"rate_deg_per_h": 0.9,
                                                  "peak_to_peak_deg": 0.03}, 120.0)
    assert "about Up" in text and "|B|" in text
    data, _ = make_data(duration_s=20.0)
    st = motion_stats(data)
    assert identifiability_reason(EffectKind.HEADING_DRIFT, st, data, 1.0,
                                  horizontal_fraction=0.5) is None
    why = identifiability_reason(EffectKind.HEADING_DRIFT, st, data, 1.0,
                                 horizontal_fraction=0.01)
    assert why is not None and "vertical" in why


def test_wiring_concealed_heading_drift_found_as_heading_drift_not_field_drift():
    # 0.03 deg over 120 s (an INS gyro bias of 0.9 deg/h), low noise
    T = 120.0
    rate = 0.03 / T * 3600.0
    v = np.radians([0.03 / 2, 0.0])  # P1 over [-1, 1]: a linear change of 0.03 deg
    data, _ = make_data((Term(EffectKind.HEADING_DRIFT),), (v,), duration_s=T, rate_hz=50.0,
                        noise_nT=0.3, seed=21)
    diag, _ = diagnose_data(data)
    eff = [f.effect for f in diag.findings]
    assert eff == ["heading_drift"], eff
    f = diag.findings[0]
    err = abs(f.params["rate_deg_per_h"] - rate)
    assert err <= max(3 * f.sigma["rate_deg_per_h"], 0.1 * rate)


def test_wiring_field_drift_off_the_heading_direction_stays_field_drift():
    # a drift mostly in Up and |B| is no heading error
    vals = (np.r_[5.0, 5.0, 40.0, np.zeros(9)],)
    data, _ = make_data((Term(EffectKind.FIELD_DRIFT),), vals, duration_s=60.0, noise_nT=1.0,
                        seed=22)
    diag, _ = diagnose_data(data)
    assert [f.effect for f in diag.findings] == ["field_drift"]


def test_independent_heading_drift_recording(tmp_path: Path):
    # independent generator: the attitude written turned about Up, 15x the threshold
    base = Spec(name="hd", seed=31, duration_s=60.0, mag_rate_hz=50.0, att_rate_hz=50.0,
                att_noise_deg=0.002, mag_noise_nT=0.5)
    spec, rep, exp, st = sized(base, "heading_drift", 15.0, np.random.default_rng(8))
    ctx = diagnose_file(write(spec, tmp_path / "hd.mcap"))
    found = {f.effect: f for f in ctx.diagnosis.findings}
    assert set(found) == {"heading_drift"}
    f = found["heading_drift"]
    err = abs(f.params["rate_deg_per_h"] - exp["rate_deg_per_h"])
    assert err <= max(3 * f.sigma["rate_deg_per_h"], 0.1 * abs(exp["rate_deg_per_h"]))

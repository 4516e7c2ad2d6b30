"""The window scan against the residual's own correlation, and pieces of one offset merged.

The scan (``stages.diagnose.search.scan_windows``) proposes the windows of transient terms.
On noise alone it must open none: its level is set by the residual's correlation time
(``block_mean_cov``, the moving means' chi-square tails shared along the recording),
so a residual correlated over a third of a second does not pass for an event. Two steps that
abut and hold one offset are one event, a disturbance that holds one offset in the sensor's
frame is a step (the nested simpler descriptions, ``stages.diagnose.nested.simplest``); two
steps that hold different offsets stay two, and a field's bump stays a disturbance.
"""

from __future__ import annotations

import numpy as np
import pytest
from _diag_sim import make_data
from scipy.signal import lfilter

from pipeline.core.vocabulary import EffectKind
from stages.diagnose.fit import fit
from stages.diagnose.model import ModelState, Term
from stages.diagnose.nested import simplest
from stages.diagnose.result import DiagnoseConfig, Finding
from stages.diagnose.search import scan_windows
from stages.diagnose.statistics import heldout_rms

RATE_HZ = 285.714  # the lab magnetometer's rate


def _ar1(rng: np.random.Generator, n: int, tau_s: float) -> np.ndarray:
    """Unit-variance Gaussian noise (n, 3) with correlation time ``tau_s`` (0: white)."""
    x = rng.normal(size=(n, 3))
    if tau_s <= 0:
        return x
    a = np.exp(-1.0 / (RATE_HZ * tau_s))
    # started in its stationary state: no quiet onset for the scan to see
    x[0] /= np.sqrt(1 - a * a)
    return lfilter([np.sqrt(1 - a * a)], [1.0, -a], x, axis=0)


@pytest.mark.parametrize("tau_s", [0.0, 0.05, 0.3, 1.0])
def test_noise_alone_opens_no_window_whatever_its_correlation_time(tau_s):
    rng = np.random.default_rng(7)
    t = np.arange(int(60 * RATE_HZ)) / RATE_HZ
    opened = sum(bool(scan_windows(650.0 * _ar1(rng, len(t), tau_s), t, DiagnoseConfig()))
                 for _ in range(20))
    # SCAN_FALSE_ALARM is 1e-3 per scan; 20 recordings may see one by chance (the white-noise
    # level alone opened 2-5 in 30)
    assert opened <= 1


@pytest.mark.parametrize("tau_s", [0.0, 0.05])
def test_a_held_offset_in_correlated_noise_still_opens_its_window(tau_s):
    rng = np.random.default_rng(3)
    t = np.arange(int(60 * RATE_HZ)) / RATE_HZ
    r = 650.0 * _ar1(rng, len(t), tau_s)
    on = (t >= 20.0) & (t < 23.0)
    r[on] += np.array([1200.0, -600.0, 400.0])  # 2 noise sigmas for 3 s
    wins = scan_windows(r, t, DiagnoseConfig())
    assert any(a < 21.5 < b for a, b in wins), wins


def _simplest(cur, data):
    """The nested move on ``cur`` with a placeholder finding per term."""
    findings = [Finding(effect=t.kind.value, params={}, sigma={}, evidence={}, where={},
                        explanation="") for t in cur.state.terms]
    cfg = DiagnoseConfig()
    return simplest(cur, heldout_rms(cur.state, data, cfg), findings, data, cfg, set())


def _two_pieces(offset_a, offset_b):
    step = Term(EffectKind.HARD_IRON_STEP, ((20.0, 30.0),))
    truth_terms = (Term(EffectKind.HARD_IRON_STEP, ((20.0, 25.0),)),
                   Term(EffectKind.HARD_IRON_STEP, ((25.0, 30.0),)))
    data, truth = make_data(truth_terms, (np.asarray(offset_a, float),
                                          np.asarray(offset_b, float)),
                            duration_s=50.0, noise_nT=20.0, seed=4)
    start = ModelState(truth.R_body_mag, truth.B_enu_nT, truth_terms,
                       (np.zeros(3), np.zeros(3)))
    return step, data, fit(start, data)


def test_abutting_pieces_of_one_offset_are_one_step():
    step, data, cur = _two_pieces([800.0, -400.0, 300.0], [800.0, -400.0, 300.0])
    got = _simplest(cur, data)
    assert got is not None
    res, findings = got
    assert [f.effect for f in findings] == ["hard_iron_step"]
    assert [t.windows_s for t in res.state.terms] == [step.windows_s]
    np.testing.assert_allclose(res.state.values[0], [800.0, -400.0, 300.0], atol=5.0)  # nT


def test_abutting_pieces_of_different_offsets_stay_two():
    _, data, cur = _two_pieces([800.0, -400.0, 300.0], [300.0, -100.0, 600.0])
    assert _simplest(cur, data) is None


def _disturbance_fitted_to(truth_term, truth_value):
    data, truth = make_data((truth_term,), (np.asarray(truth_value, float),), duration_s=50.0,
                            noise_nT=20.0, seed=5)
    dist = Term(EffectKind.DISTURBANCE, ((18.25, 28.75),), knot_step_s=1.75)
    start = ModelState(truth.R_body_mag, truth.B_enu_nT, (dist,), (np.zeros(dist.n_params()),))
    return data, fit(start, data)


def test_a_disturbance_that_holds_a_sensor_frame_offset_becomes_a_step():
    """A magnet's 7 s offset first named as an ENU disturbance over its padded window."""
    data, cur = _disturbance_fitted_to(Term(EffectKind.HARD_IRON_STEP, ((20.0, 27.0),)),
                                       [800.0, -1500.0, -1000.0])
    got = _simplest(cur, data)
    assert got is not None
    last, findings = got
    assert [f.effect for f in findings] == ["hard_iron_step"]
    (a, b), = last.state.terms[-1].windows_s
    assert abs(a - 20.0) <= 0.05 and abs(b - 27.0) <= 0.05  # s, the 50 Hz spacing is 0.02 s
    np.testing.assert_allclose(last.state.values[-1][:3], [800.0, -1500.0, -1000.0],
                               atol=10.0)  # nT


def test_a_disturbance_of_the_field_stays_a_disturbance():
    """A smooth ENU bump while the sensor tumbles: no offset in its frame explains it."""
    dist = Term(EffectKind.DISTURBANCE, ((20.0, 27.0),), knot_step_s=1.75)
    k = dist.n_params() // 3
    bump = np.sin(np.pi * np.arange(1, k + 1) / (k + 1))[:, None] * np.array([600.0, -300.0,
                                                                                  740.0])
    data, cur = _disturbance_fitted_to(dist, bump.ravel())
    assert _simplest(cur, data) is None

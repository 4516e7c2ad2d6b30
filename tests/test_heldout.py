"""Held-out folds warm-started by one Newton step: the same held-out error as fits from zero.

``heldout_rms`` refits each fold on its training blocks. Its fits start one Newton step from
the whole fit (``stages.diagnose.fit.fold_starts``), not from the whole fit with the local
terms' values at zero. The start must change how fast a fold converges, never where: the
held-out error is that of the fold's converged fit from zero, a window wholly held out is
learnt from nothing (zero), and the step lands nearer the fold's optimum than the cold start.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _diag_sim import lissajous_m, make_data

from pipeline.core.vocabulary import EffectKind
from stages.diagnose.fit import fit, fold_starts
from stages.diagnose.model import LOCAL_KINDS, FitData, ModelState, Term, evaluate
from stages.diagnose.result import DiagnoseConfig
from stages.diagnose.statistics import fold_of, heldout_rms

CFG = DiagnoseConfig()


def _local_mask(state: ModelState) -> np.ndarray:
    mask = np.zeros(state.n_params(), dtype=bool)
    for t, o in zip(state.terms, state.offsets(), strict=True):
        if t.kind in LOCAL_KINDS:
            mask[o : o + t.n_params()] = True
    return mask


def _cold_heldout(state: ModelState, data: FitData) -> float:
    """The held-out RMS from fits started at ``state`` with local values at zero, converged."""
    folds = fold_of(data.t_s, CFG, state)
    cold = dataclasses.replace(state, values=tuple(
        np.zeros_like(v) if t.kind in LOCAL_KINDS else v
        for t, v in zip(state.terms, state.values, strict=True)))
    sq, cnt = 0.0, 0
    for j in range(CFG.n_folds):
        test = folds == j
        res = fit(cold, data.subset(~test), max_iter=80, rtol=1e-12)
        e = data.y_nT[test] - evaluate(res.state, data.subset(test), jacobian=False).y_nT
        sq, cnt = sq + float(np.sum(e * e)), cnt + e.size
    return float(np.sqrt(sq / cnt))


def _step_and_lag() -> tuple[FitData, ModelState]:
    """A 2000 nT step held 8 s and a 12 ms lag, fitted to all the data."""
    terms = (Term(EffectKind.TIME_OFFSET), Term(EffectKind.HARD_IRON_STEP, ((21.0, 29.0),)))
    values = (np.array([0.012]), np.array([2000.0, -900.0, 500.0]))
    data, truth = make_data(terms, values, duration_s=50.0, noise_nT=20.0, seed=11)
    start = ModelState(truth.R_body_mag, truth.B_enu_nT, terms,
                       (np.zeros(1), np.zeros(3)))
    return data, fit(start, data).state


def _source_on_a_path() -> tuple[FitData, ModelState]:
    """A dipole fixed in the surroundings, passed by a path: position enters nonlinearly."""
    t = np.arange(0.0, 60.0, 1.0 / 50.0)
    p = lissajous_m(t)
    term = Term(EffectKind.LOCAL_SOURCE)
    value = np.array([0.25, 0.1, 1.0, 0.4, -0.2, 0.6])  # position m, moment A m^2
    data, truth = make_data((term,), (value,), duration_s=60.0, noise_nT=5.0, seed=5,
                            positions=p)
    start = ModelState(truth.R_body_mag, truth.B_enu_nT, (term,), (value * 1.05,))
    return data, fit(start, data).state


@pytest.mark.parametrize("case", [_step_and_lag, _source_on_a_path])
def test_warm_folds_give_the_converged_heldout_error(case):
    data, state = case()
    assert heldout_rms(state, data, CFG) == pytest.approx(_cold_heldout(state, data), rel=1e-5)


def test_a_window_wholly_held_out_starts_and_stays_at_zero():
    data, state = _step_and_lag()
    # the step's window is held out whole by fold j: its blocks inside are in j alone
    window = (data.t_s >= 21.0) & (data.t_s < 29.0)
    folds = np.where(window, 0, fold_of(data.t_s, CFG, state))
    folds[~window & (folds == 0)] = 1
    starts = fold_starts(state, data, folds, CFG.n_folds, _local_mask(state))
    i_step = [t.kind for t in state.terms].index(EffectKind.HARD_IRON_STEP)
    assert np.linalg.norm(state.values[i_step]) > 1000.0
    assert starts[0] is not None
    np.testing.assert_array_equal(starts[0].values[i_step], 0.0)
    # every other fold sees the window: the step's value is learnt, near the whole fit's
    for s in starts[1:]:
        assert s is not None
        np.testing.assert_allclose(s.values[i_step], state.values[i_step], atol=60.0)


def test_the_step_lands_nearer_the_fold_optimum_than_the_cold_start():
    data, state = _source_on_a_path()
    folds = fold_of(data.t_s, CFG, state)
    starts = fold_starts(state, data, folds, CFG.n_folds, _local_mask(state))
    for j, warm in enumerate(starts):
        assert warm is not None
        train = data.subset(folds != j)
        best = fit(state, train, max_iter=80, rtol=1e-12).state
        gap_warm = np.linalg.norm(warm.values[0] - best.values[0])
        gap_cold = np.linalg.norm(state.values[0] - best.values[0])
        assert gap_warm < 0.2 * gap_cold, (j, gap_warm, gap_cold)

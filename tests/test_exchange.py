"""The search's exchange move (``stages/diagnose/search.py``: ``_Search.exchange``).

A term local in time named before what explains its window (a step standing for a source
fixed in the room, named before the search located any source) is offered every effect's
candidates at its window once the rounds end; the best by the evidence replaces it when it
beats the model by the margin and predicts the held-out blocks better; a step that is a
magnet riding on the platform stays. The recordings come
from the independent generator (``tests/indep_gen.py``); the model the search is left with is
built by hand, as the rounds of a larger recording left it (``bench/spatial.py indoor``,
room_b, docs/effects.md "The exchange move").
"""

from __future__ import annotations

import numpy as np
from indep_gen import Spec, effect_params, position_m, source_field_nT, write

from pipeline.core.vocabulary import EffectKind
from pipeline.io.mcap_read import read_recording
from stages.context import Context
from stages.diagnose.catalogue import motion_stats
from stages.diagnose.fit import fit, wahba_init
from stages.diagnose.model import Term
from stages.diagnose.result import DiagnoseConfig
from stages.diagnose.search import GLOBAL_KINDS, _finding, _Search
from stages.diagnose.stage import fit_data_from
from stages.diagnose.statistics import (
    evidence_between,
    evidence_change,
    heldout_rms,
    robust_sigma,
    score_test,
)
from stages.resample import Resample

#: The generator's magnetometer noise, nT per component.
NOISE_NT = 2.0


def _fit_data(spec: Spec, path):
    rec = read_recording(write(spec, path))
    return fit_data_from(rec, Resample().run(Context(source=str(path), recording=rec))
                         .need_aligned())


def _search_holding(data, step: Term) -> tuple[_Search, object, float]:
    """The search as its rounds left it: the baseline with ``step`` fitted, and its finding."""
    cfg = DiagnoseConfig()
    base = fit(wahba_init(data), data)
    cur = fit(base.state.with_term(step), data)
    cv_base, cv = heldout_rms(base.state, data, cfg), heldout_rms(cur.state, data, cfg)
    st = score_test(base, step, data, robust_sigma(base.residual_nT))
    found = _finding(base, cur, step, st, evidence_change(cur, base, data), cv_base, cv, data)
    return (_Search(data, cfg, motion_stats(data), list(GLOBAL_KINDS), 0.0, cur, cv,
                    findings=[found]), cur, cv)


def test_a_step_that_stands_for_a_source_in_the_room_is_exchanged_for_it(tmp_path):
    """A magnet on the floor 10 cm below a place the hand passes, taken for a step.

    Over its strongest pass the model holds a ``hard_iron_step``,
    fitted; the exchange replaces it by a ``local_source`` within 3 cm of the magnet, with
    more evidence by the margin and a lower held-out error, and says what it replaced.
    """
    s0 = Spec("swap", seed=13, duration_s=60.0, mag_noise_nT=NOISE_NT)
    c = position_m(s0, np.array([20.0]))[0] + np.array([0.0, 0.0, -0.10])
    spec = Spec("swap", seed=13, duration_s=60.0, mag_noise_nT=NOISE_NT, effects={
        "local_source": {"position_m": c.tolist(), "moment_Am2": [0.01, -0.004, 0.006]}})
    data = _fit_data(spec, tmp_path / "swap.mcap")
    # the pass the rounds took for a step: where the magnet's field is above a quarter of its
    # peak, about the closest approach
    size = np.linalg.norm(source_field_nT(spec, data.t_s), axis=1)
    k = int(np.argmax(size))
    low = np.flatnonzero(size < 0.25 * size[k])
    a = float(data.t_s[low[low < k][-1] + 1])
    b = float(data.t_s[low[low > k][0]])
    assert 0.5 < b - a < 10.0 and size[k] > 50 * NOISE_NT, (a, b, size[k])

    search, cur, cv = _search_holding(data, Term(EffectKind.HARD_IRON_STEP, ((a, b),)))
    assert search.exchange()
    kinds = [t.kind for t in search.cur.state.terms]
    assert EffectKind.HARD_IRON_STEP not in kinds and EffectKind.LOCAL_SOURCE in kinds, kinds
    where = search.cur.state.values[kinds.index(EffectKind.LOCAL_SOURCE)][:3]
    assert np.linalg.norm(where - c) < 0.03, (where, c)
    assert evidence_between(search.cur, cur, data) < -search.cfg.bic_margin
    assert search.cv_cur < cv
    assert len(search.findings) == len(kinds)
    said = search.findings[kinds.index(EffectKind.LOCAL_SOURCE)].told_apart
    assert f"replaces a hard_iron_step named at {a:.1f}-{b:.1f} s" in said, said


def test_a_magnet_riding_on_the_platform_stays_a_step(tmp_path):
    """The null of the move: a 50 nT offset that turns with the platform for 6-12 s (25 noise
    sigmas, a nominal step), in a recording with positions, is not exchanged."""
    _, p, _ = effect_params("hard_iron_step", np.random.default_rng(21), 1.0, 60.0)
    spec = Spec("stay", seed=21, duration_s=60.0, mag_noise_nT=NOISE_NT,
                effects={"hard_iron_step": p})
    data = _fit_data(spec, tmp_path / "stay.mcap")
    (a, b), = p["windows_s"]
    search, cur, _ = _search_holding(data, Term(EffectKind.HARD_IRON_STEP, ((a, b),)))
    assert not search.exchange()
    assert search.cur is cur and [t.kind for t in cur.state.terms] == [
        EffectKind.HARD_IRON_STEP]

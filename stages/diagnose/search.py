"""The diagnosis search.

From the baseline model, the strongest candidate term is refitted and kept when it lowers
the evidence and the held-out error, until nothing qualifies (``diagnose_data``); effects local
in time are located first by a scan of the robust residual norm (``scan_windows``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from functools import partial
from typing import Any

import numpy as np
from scipy.special import chdtri

from pipeline.core import progress
from pipeline.core.errors import EstimationError
from pipeline.core.geometry import quat_to_matrix
from pipeline.core.vocabulary import EffectKind
from pipeline.model import parallel
from pipeline.model.effects import EFFECTS
from pipeline.model.effects.base import CONFOUND_RATIO
from pipeline.model.effects.field_gradient import gradient_matrix
from stages.diagnose.candidates import REFINED, RIVALS, Event, event_candidates, scored
from stages.diagnose.catalogue import explanation, identifiability_reason, motion_stats
from stages.diagnose.field_map import MapCandidate, map_candidate
from stages.diagnose.fit import FitResult, fit, wahba_init
from stages.diagnose.model import (
    LOCAL_KINDS,
    FitData,
    ModelState,
    Term,
    estimate_noise_model,
    evaluate,
    interpolation_error_nT,
    interpolation_error_proxy,
    moved_last_to,
    term_params,
    without_term,
)
from stages.diagnose.nested import (
    ABSORBING,
    DECISIVE_FACTOR,
    IN_PARTS,
    NESTED_SIMPLER,
    RAMP_REACH_S,
    REQUIRES,
    absorbed,
    earns_beside_lookalikes,
    explained_by_refinement,
    hypothesis,
    refine_step,
    refinements,
    required,
    simplest,
    told_apart,
)
from stages.diagnose.partial import PARTIAL_KINDS, held_words, partial_candidate
from stages.diagnose.result import DiagnoseConfig, Diagnosis, Finding, Signature
from stages.diagnose.sources import (
    plausible,
    pulled_away,
    relocated,
)
from stages.diagnose.statistics import (
    INTERP_MARGIN,
    ScoreTest,
    effective_samples,
    evidence,
    evidence_between,
    evidence_change,
    heldout_ok,
    heldout_rms,
    interp_reason,
    occam,
    param_covariance,
    robust_sigma,
    score_test,
    sigma_for,
)

#: The effects offered in every round, in CONVENTIONS' order (``EffectKind``'s)
#: (:attr:`~pipeline.model.effects.base.Effect.each_round`).
GLOBAL_KINDS = tuple(kind for kind in EffectKind if EFFECTS[kind].each_round)

#: The kind each nested simpler kind is a special case of (a time offset: an eddy term)
_CONTAINED_IN = {simpler: kind for kind, simpler in NESTED_SIMPLER.items()}


#: The noise model is measured again when a component of it moves by more than this fraction
#: (its own estimate scatters by a few per cent).
NOISE_MODEL_RTOL = 0.2


#: Largest time offset the search is built for, s (lags up to +-100 ms).
MAX_LAG_S = 0.1

#: Longest transition modelled as a curve, s: carrying a magnet onto a platform by hand
#: takes a fraction of a second to a second.
MAX_RAMP_S = 2.0
#: Knot spacing of a transition, s: the field of an approaching magnet grows as ``1/r^3``,
#: most of it in the last tenths of a second.
RAMP_KNOT_S = 0.1
#: Margin of a transition around the excess that called for it, s.
RAMP_PAD_S = 0.1


def ramp_candidate(state: ModelState, w: tuple[float, float], noise_nT: float
                   ) -> tuple[int, Term] | None:
    """Return the ``hard_iron_step`` whose edge the excess ``w`` touches, with that transition.

    A magnet brought near the sensor, left and taken away is one event: the excess at the
    edges of its plateau (the field while the magnet moved) is modelled as the step's
    onset or release (:func:`pipeline.model.forward.ramp_profile`), the window extended to
    where the transition starts or ends, rather than as further steps.

    Returns
    -------
    (index of the step in ``state.terms``, the step with the transition) or None
        None when ``w`` is near no step's edge, or the transition would be longer than
        ``MAX_RAMP_S``, overlap the other one, or change nothing.

    """
    w0, w1 = float(w[0]), float(w[1])
    for i, t in enumerate(state.terms):
        if t.kind is not EffectKind.HARD_IRON_STEP or len(t.windows_s) != 1:
            continue
        (a, b), ramps = t.windows_s[0], list(t.ramps_s)
        on = next((r for r in ramps if abs(r[0] - a) < 1e-9), None)
        off = next((r for r in ramps if abs(r[1] - b) < 1e-9), None)
        edge_a = a if on is None else on[1]  # where the plateau starts and ends now
        edge_b = b if off is None else off[0]

        def near(edge: float) -> bool:
            return edge - RAMP_REACH_S <= w1 and w0 <= edge + RAMP_REACH_S

        def ramp(edge: float, lo: float, hi: float, old: tuple[float, float] | None,
                 onset: bool, a: float = a, b: float = b) -> tuple[float, float]:
            r0, r1 = min(lo, edge) - RAMP_PAD_S, max(hi, edge) + RAMP_PAD_S
            if old is not None:
                r0, r1 = min(r0, old[0]), max(r1, old[1])
            return (min(r0, a), r1) if onset else (r0, max(r1, b))

        new_on, new_off = on, off
        if w1 - w0 <= MAX_RAMP_S and near(edge_a):  # an excess at the onset
            new_on = ramp(edge_a, w0, w1, on, True)
        elif w1 - w0 <= MAX_RAMP_S and near(edge_b):  # at the release
            new_off = ramp(edge_b, w0, w1, off, False)
        elif abs(w0 - edge_a) <= RAMP_REACH_S and abs(w1 - edge_b) <= RAMP_REACH_S:
            # the same plateau seen again with slightly different ends: the offset there
            # was a compromise with the transitions
            new_on = ramp(edge_a, w0, w0, on, True)
            new_off = ramp(edge_b, w1, w1, off, False)
        else:
            continue
        got = tuple(r for r in (new_on, new_off) if r is not None)
        if any(r1 - r0 > MAX_RAMP_S for r0, r1 in got) or (
                new_on is not None and new_off is not None and new_on[1] >= new_off[0]):
            continue
        window = (new_on[0] if new_on is not None else a,
                  new_off[1] if new_off is not None else b)
        # the prior of the transition's shape: as large as the magnet's own offset, on
        # the time scale of the modes (a person's hand moving it)
        new = Term(EffectKind.HARD_IRON_STEP, (window,), knot_step_s=RAMP_KNOT_S,
                   ramps_s=got, ramp_scale_s=RAMP_KNOT_S,
                   prior_nT=float(np.linalg.norm(state.values[i][:3])),
                   noise_nT=float(noise_nT))
        if new.windows_s == t.windows_s and new.ramps_s == t.ramps_s:
            continue
        return i, new
    return None


def _ramp_fit(cur: FitResult, i: int, term: Term, data: FitData, cfg: DiagnoseConfig
              ) -> tuple[float, ScoreTest, FitResult] | None:
    """Refit with step ``i`` replaced by ``term`` (the same magnet with a transition).

    Returns ``(delta -2 log evidence against the current model, statistic, fit)`` with the new
    step last, when it raises the evidence by ``bic_margin``; else None. The statistic is the
    likelihood ratio ``(RSS_cur - RSS_new) / sigma^2`` (the score test needs the step at zero,
    which a transition of a step in the model is not).
    """
    wo = without_term(cur.state, i)
    start = np.zeros(term.n_params())
    start[:3] = cur.state.values[i][:3]
    res = fit(dataclasses.replace(wo, terms=wo.terms + (term,), values=wo.values + (start,)),
              data)
    if not res.rss < cur.rss:
        return None
    n_eff = effective_samples(res, data)
    dbic = evidence(res, data, n_eff) - evidence(cur, data, n_eff)
    if dbic > -cfg.bic_margin:
        return None
    s2 = robust_sigma(cur.residual_nT) ** 2
    k = term.n_params() - cur.state.terms[i].n_params()
    cost = occam(res, data, n_eff) - occam(cur, data, n_eff)
    return float(dbic), ScoreTest(term, float((cur.rss - res.rss) / s2), 1.0, k, cost), res


def _excess_runs(s: np.ndarray, med: float, level: float, open_level: float | None = None
                 ) -> list[tuple[int, int]]:
    """Index runs where ``s`` stays above half-way to ``level`` and crosses ``open_level``.

    ``open_level`` (default ``level``) decides whether there is an event; ``level`` how far
    it extends, so that a higher bar to open a window does not also shorten it.
    """
    above = s > (level if open_level is None else max(open_level, level))
    if not above.any():
        return []
    low_mask = s > med + 0.5 * (level - med)
    idx = np.flatnonzero(np.diff(np.concatenate([[0], low_mask.astype(int), [0]])))
    return [(int(a), int(b)) for a, b in zip(idx[0::2], idx[1::2], strict=True)
            if above[a:b].any()]


def scan_windows(
    residual_nT: np.ndarray, t_s: np.ndarray, cfg: DiagnoseConfig
) -> list[tuple[float, float]]:
    """Windows where the residual stands out from its own noise (a multi-scale scan).

    Statistics scanned along the recording, each against the level noise alone exceeds
    anywhere in it with probability :data:`SCAN_FALSE_ALARM` shared by the statistics
    (:func:`scan_level`):

    - the squared residual norm, in units of a robust noise scale, smoothed over
      ``scan_smooth_s``: a magnet or a vehicle brought near the sensor;
    - only when that opens nothing, the moving mean of the residual vector over 4, 8, 16...
      smoothing widths (up to an eighth of the recording), finest first: a weak offset held
      for seconds (a hard-iron step) barely lifts the squared norm but moves the mean, and
      the longer it is held, the more a mean over its length stands out (a discrete
      generalised likelihood ratio over the event's length).

    Each statistic is also held to an empirical level, its median plus ``scan_sigma`` robust
    sigmas of its own series, so that a very quiet recording does not turn its smallest
    excess into an event. A window opens where a statistic crosses both levels and is
    widened to where it falls back half-way to the empirical level (the higher bar decides
    whether there is an event, not how long it lasts); windows closer than one smoothing
    width are merged.

    Returns
    -------
    list of (start_s, end_s)
        Half-open windows, s from the first magnetometer sample.

    """
    n = len(t_s)
    if n < 50:
        return []
    dt = float(np.median(np.diff(t_s)))
    w = max(3, int(round(cfg.scan_smooth_s / dt)))
    scales = _mean_scales(n, w)
    tests = 1 + len(scales)
    # the spread of a mean over the smoothing width: both statistics' noise model
    cov_w = block_mean_cov(residual_nT, w)
    s, med, level_emp, level = _norm_statistic(residual_nT, w, cov_w, tests, cfg)
    wins = _windows(_excess_runs(s, med, level_emp, level), t_s, w)
    if wins:
        return wins
    if _windows(_excess_runs(s, med, level_emp), t_s, w):
        # the norm stands out, but no more than noise with the residual's own correlation
        # reaches: the residual is not quiet (a map's remainder along the path, correlated
        # over seconds), and the moving mean of such a residual is no held offset either
        return []
    # only then: the mean scan's windows would otherwise crowd the few refits of each round
    for wk, cov in zip(scales, _mean_spreads(residual_nT, w, cov_w, scales), strict=True):
        sv, med_v, lev_v, lev_c = _mean_statistic(residual_nT, wk, cov, tests, cfg)
        wins = _windows(_excess_runs(sv, med_v, lev_v, lev_c), t_s, w)
        if wins:
            return wins
    return []


def _mean_scales(n: int, w: int) -> list[int]:
    """Widths of the moving means, samples: 4, 8, 16... times ``w``, at most ``n / 8``."""
    out = [min(n, 4 * w)]
    while 2 * out[-1] <= n // 8:
        out.append(2 * out[-1])
    return out


def _spans(n: int, w: int) -> np.ndarray:
    """Return the samples (n,) each centred window of ``w`` holds (fewer at the ends)."""
    lo = np.clip(np.arange(n) - w // 2, 0, n)
    hi = np.clip(np.arange(n) + w // 2 + 1, 0, n)
    return np.asarray(hi - lo, dtype=float)


def _moving_mean(x: np.ndarray, w: int) -> np.ndarray:
    """Centred moving mean of ``x`` (n,) or (n, m) over ``w`` samples, shortened at the ends."""
    n = len(x)
    c = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])
    lo = np.clip(np.arange(n) - w // 2, 0, n)
    span = _spans(n, w)
    hi = lo + span.astype(int)
    return np.asarray((c[hi] - c[lo]) / (span if x.ndim == 1 else span[:, None]))


def _norm_statistic(r: np.ndarray, w: int, cov_w: np.ndarray, tests: int,
                    cfg: DiagnoseConfig) -> tuple[np.ndarray, float, float, float]:
    """Smooth the squared norm; return it, its median, empirical level and noise level.

    The moving mean of ``z = |r|^2 / (3 sigma^2)`` over ``w`` samples is, for Gaussian noise,
    a scaled chi-square over ``nu`` degrees of freedom (Satterthwaite): ``w / c`` independent
    samples, ``c`` the variance inflation of a mean over ``w`` correlated samples, each
    carrying the effective number of directions of the noise (3 when it is the same along
    every direction; attitude noise crossed with the field lies in the plane normal to it: 2).
    """
    sig = robust_sigma(r)
    z = np.sum(r**2, axis=1) / (3 * sig * sig)
    # robust to single spikes: a moving median would be ideal; a trimmed value keeps it cheap
    z = np.minimum(z, np.percentile(z, 99.9) * 4)
    s = _moving_mean(z, w)
    med = float(np.median(s))
    mad = float(1.4826 * np.median(np.abs(s - med))) + 1e-12
    # (a bound: squares are less correlated than the residual itself)
    nu = 3.0 * _directions(cov_w) * sig * sig / max(float(np.trace(cov_w)), 1e-30)
    level_emp = max(med + cfg.scan_sigma * mad, med + 2.0)
    level = med * scan_level(nu, len(r), tests, w) / float(chdtri(nu, 0.5))
    return s, med, level_emp, max(level_emp, level)


def _mean_spreads(r: np.ndarray, w: int, cov_w: np.ndarray, scales: list[int]
                  ) -> list[np.ndarray]:
    """Covariance of a mean over each of ``scales`` samples of ``r`` under noise alone.

    Measured at the smoothing width ``w`` (``cov_w``, :func:`block_mean_cov`), where a
    recording holds many blocks and an event held for seconds disturbs few of their
    differences, and carried to a wider mean as ``w / wk`` times the variance inflation the
    wider blocks show beyond that (a residual correlated over longer than ``w``: the mean of
    a wider window varies more than ``w / wk`` says). The inflation is measured where the
    recording holds ``4 BLOCK_LAG`` blocks of the width; wider, the widest measured one is
    kept (the residual assumed correlated over less than a sixteenth of the recording). It
    never falls with the width, as for any positively correlated noise.
    """
    tr_w = max(w * float(np.trace(cov_w)), 1e-300)
    out, inflation = [], 1.0
    for wk in scales:
        if len(r) // wk >= 4 * BLOCK_LAG:
            inflation = max(inflation, wk * float(np.trace(block_mean_cov(r, wk))) / tr_w)
        out.append(cov_w * (w / wk) * inflation)
    return out


def _mean_statistic(r: np.ndarray, wk: int, cov: np.ndarray, tests: int,
                    cfg: DiagnoseConfig) -> tuple[np.ndarray, float, float, float]:
    """Scan the mean over ``wk`` samples; return its squared norm, median and two levels.

    In units of its spread under noise alone (``cov``, :func:`_mean_spreads`), the squared
    norm of a mean over ``wk`` samples is chi-square over the noise's effective number of
    directions. Near the recording's ends a mean holds fewer samples and varies more, in
    proportion (``cov`` is the full width's): each position is scaled by its own span.
    """
    m = _moving_mean(np.asarray(r, dtype=float), wk)
    d = _directions(cov)
    span = _spans(len(r), wk)
    sv = np.sum(m * m, axis=1) * d / max(float(np.trace(cov)), 1e-300) * (span / span.max())
    med_v = float(np.median(sv))
    mad_v = float(1.4826 * np.median(np.abs(sv - med_v))) + 1e-12
    lev_v = max(med_v + cfg.scan_sigma * mad_v, med_v + 2.0)
    return sv, med_v, lev_v, scan_level(d, len(r), tests)


def _windows(runs: list[tuple[int, int]], t_s: np.ndarray, w: int
             ) -> list[tuple[float, float]]:
    """Index runs as half-open windows in s; runs closer than ``w`` samples are one.

    A window longer than half the recording is not local (a global term's job) and is left
    out, as is one shorter than two samples.
    """
    n = len(t_s)
    dt = float(np.median(np.diff(t_s)))
    merged: list[list[int]] = []
    for a, b in runs:
        if merged and a - merged[-1][1] < w:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    out = []
    for a, b in merged:
        start, end = float(t_s[a]), float(t_s[min(b, n - 1)])
        if 2 * dt <= end - start <= 0.5 * (t_s[-1] - t_s[0]):
            out.append((start, end))
    return out


#: Chance that noise alone opens a window anywhere in a recording, per scan.
SCAN_FALSE_ALARM = 1e-3


def scan_level(nu: float, n: int, tests: int, w: int | None = None) -> float:
    """Chi-square level (``nu`` degrees of freedom) a moving statistic passes by chance.

    Each of ``tests`` statistics is compared with its level at every one of ``n`` samples;
    :data:`SCAN_FALSE_ALARM` is shared by the statistics. The maximum of a moving window
    exceeds a level far more often than its ``n / w`` disjoint windows' tails say, as the
    window peaks between their centres.

    - ``w`` given (a window of ``w`` samples whose spread is measured from many blocks):
      ``P(max > b) ~ (n / w) b^2 P(Z > b)`` for a level ``b`` standard deviations high
      (Pickands' approximation for a window's triangular correlation, Pickands' constant 1;
      Siegmund & Venkatraman 1995), solved for the per-position tail by fixed point.
    - ``w`` None: shared by every position (a union bound, whatever the windows' overlap),
      for statistics whose spread is estimated from few blocks, whose scatter widens the
      tail beyond the approximation's (measured: docs/effects.md).
    """
    if w is None:
        return float(chdtri(nu, SCAN_FALSE_ALARM / max(1.0, float(n * tests))))
    windows = tests * max(1.0, n / max(w, 1))
    tail = SCAN_FALSE_ALARM / windows
    for _ in range(3):
        b2 = float(chdtri(1.0, 2.0 * tail))  # the same tail of a standard normal, squared
        tail = SCAN_FALSE_ALARM / (windows * max(1.0, b2))
    return float(chdtri(nu, tail))


#: Lag, in blocks, of the block-mean differences :func:`block_mean_cov` measures.
BLOCK_LAG = 4


def _mad(d: np.ndarray) -> np.ndarray:
    """Robust spread (1.4826 MAD) of ``d`` along its first axis."""
    return np.asarray(1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0))


def _directions(cov: np.ndarray) -> float:
    """Effective number of directions (1-3) of a spread: (trace)^2 / (sum of squares)."""
    return float(np.clip(np.trace(cov) ** 2 / max(float(np.sum(cov * cov)), 1e-30), 1.0,
                         float(len(cov))))


def block_mean_cov(x: np.ndarray, w: int) -> np.ndarray:
    """Covariance (m, m) of a mean over ``w`` consecutive samples of ``x`` (n, m).

    Measured robustly from the differences of block means ``BLOCK_LAG`` blocks apart, far
    enough for the residual's correlation to have faded: an event held for many blocks
    disturbs only the differences that straddle its edges, so what is measured is the
    residual's own correlation, not the events the scan looks for. A mean over ``w``
    correlated samples varies more than ``var / w``; this is how much more. The variances
    are MADs, the covariances the spreads of the sums and differences of the standardised
    columns (Gnanadesikan & Kettenring 1972).
    """
    x = np.asarray(x, dtype=float)
    n = len(x) // max(w, 1)
    if n < 4 * BLOCK_LAG:
        return np.atleast_2d(np.cov(x, rowvar=False, bias=True)) / max(w, 1)
    m = x[: n * w].reshape(n, w, -1).mean(axis=1)
    d = m[BLOCK_LAG:] - m[:-BLOCK_LAG]
    s = _mad(d)
    cov = np.diag(s * s)
    u = d / np.maximum(s, 1e-300)
    for i in range(d.shape[1]):
        for j in range(i):
            plus, minus = float(_mad(u[:, i] + u[:, j])), float(_mad(u[:, i] - u[:, j]))
            cov[i, j] = cov[j, i] = s[i] * s[j] * (plus * plus - minus * minus) / 4.0
    return np.asarray(cov / 2.0)


def _above_noise(contrib_nT: np.ndarray, t_s: np.ndarray, sigma_nT: float,
                 gap_s: float = 1.0) -> list[list[float]]:
    """Spans where a term's contribution stands out, s (half-open).

    Its magnitude smoothed over 0.1 s, above three times the residual's per-component sigma
    (the noise) and a tenth of its own peak (its tails: over quiet survey data a buried
    object's field stays above the noise for most of a line); spans closer than ``gap_s``
    are one.
    """
    if len(t_s) < 3:
        return []
    dt = float(np.median(np.diff(t_s)))
    w = max(1, int(round(0.1 / max(dt, 1e-6))))
    mag = np.convolve(np.linalg.norm(contrib_nT, axis=1), np.ones(w) / w, mode="same")
    out: list[list[float]] = []
    for a, b in _excess_runs(mag, 0.0, max(3.0 * sigma_nT, 0.1 * float(mag.max()))):
        t0, t1 = float(t_s[a]), float(t_s[min(b, len(t_s) - 1)])
        if out and t0 - out[-1][1] < gap_s:
            out[-1][1] = t1
        else:
            out.append([t0, t1])
    return out


def _axes(x: np.ndarray) -> list[str]:
    rms = np.sqrt(np.mean(np.asarray(x) ** 2, axis=0))
    if not np.any(rms > 0):
        return []
    return [a for a, v in zip("xyz", rms, strict=True) if v >= 0.3 * rms.max()]


def _contribution(before: ModelState, after: ModelState, data: FitData) -> np.ndarray:
    """Prediction difference (mag frame) made by the last term at the fitted values."""
    without = after.with_terms(after.terms[:-1], after.values[:-1])
    return (
        evaluate(after, data, jacobian=False).y_nT - evaluate(without, data, jacobian=False).y_nT
    )


def _to_enu(v_mag: np.ndarray, state: ModelState, data: FitData) -> np.ndarray:
    """Map mag-frame vectors to ENU with the fitted rotation and attitude (inverse model)."""
    C = quat_to_matrix(data.track.at(data.t_s - state.tau_s()))
    v = np.linalg.solve(state.D(), v_mag.T).T @ state.R_body_mag.T
    return np.einsum("nij,nj->ni", C, v)


#: search rounds the progress line expects (most recordings need two or three)
_ROUNDS_SHOWN = 3


def _event(w: tuple[float, float], held: tuple[float, float], t_s: np.ndarray,
           edge_of_step: bool) -> Event:
    """Return the event at window ``w`` (held ``held``), padded as a bell-shaped transient needs.

    The scan sees where the excess is large; such a transient starts and ends earlier and
    later than that. The padded window's knots are a sixth of it, 0.75-2 s apart.
    """
    pad = max(0.5, 0.25 * (w[1] - w[0]))
    t0, t1 = float(t_s[0]), float(t_s[-1])
    wd = (max(t0, w[0] - pad), min(t1, w[1] + pad))
    return Event(w, held, wd, min(2.0, max(0.75, (wd[1] - wd[0]) / 6)), edge_of_step)


@dataclasses.dataclass
class _Search:
    """One diagnosis search: the model of the moment, its findings and what was tried.

    Each :meth:`round` names at most one term (forward), then lets the model settle
    (:meth:`_settle`: sources located again, the noise model measured again, the backward
    step, the nested simpler descriptions).
    """

    data: FitData
    cfg: DiagnoseConfig
    stats: Any
    kinds: list[EffectKind]
    e_int_nT: float
    cur: FitResult
    cv_cur: float
    findings: list[Finding] = dataclasses.field(default_factory=list)
    not_ident: dict[str, str] = dataclasses.field(default_factory=dict)
    #: failed in this round; retried once the model changes
    rejected: set[tuple] = dataclasses.field(default_factory=set)
    #: removed by the backward step; never re-added
    dropped: set[tuple] = dataclasses.field(default_factory=set)

    def round(self) -> bool:
        """Name the strongest candidate that qualifies; False when none does."""
        sig = robust_sigma(self.cur.residual_nT)
        present = {t.kind for t in self.cur.state.terms}
        cands, cand_start, ramps = self._candidates(sig, present)
        tests, starts, replace_trial = self._scored(cands, cand_start, sig, present)
        mc = self._map_candidate(sig, present)
        fits, replaces, map_fits = self._refits(tests, starts, ramps, mc, replace_trial, present)
        fits = self._absorbing_last(fits, map_fits)
        if not self._accept_first(fits, mc, replaces, sig, present):
            return False
        self._settle()
        return True

    def _candidates(self, sig: float, present: set[EffectKind]
                    ) -> tuple[list[Term], dict[int, np.ndarray], list[tuple[int, Term]]]:
        """Return the candidate terms of this round.

        The global effects not yet in the model, and every effect's candidates at each
        event the residual scan finds (:func:`~stages.diagnose.candidates.event_candidates`).
        With them, the start values of a candidate's refit by its index (a located
        source's), and the transitions of steps in the model that the scan asks for.
        """
        cands: list[Term] = [Term(k) for k in self.kinds if k not in present]
        taken = [w for t in self.cur.state.terms if t.kind in LOCAL_KINDS for w in t.windows_s]
        cand_start: dict[int, np.ndarray] = {}  # candidate index -> its refit's start values
        ramps: list[tuple[int, Term]] = []  # transitions of steps in the model
        for w in scan_windows(self.cur.residual_nT, self.data.t_s, self.cfg):
            ws = refine_step(w, self.cur.residual_nT, self.data.t_s)
            rc = ramp_candidate(self.cur.state, ws, sig)
            if rc is not None and rc not in ramps:
                ramps.append(rc)
            if any(w[0] >= a and w[1] <= b for a, b in taken):
                continue  # inside a window already modelled, not a new event
            event = _event(w, ws, self.data.t_s, edge_of_step=rc is not None)
            for term, start in event_candidates(self.cur, self.data, event):
                if start is not None:
                    cand_start[len(cands)] = start
                cands.append(term)
        return cands, cand_start, ramps

    def _scored(self, cands: list[Term], cand_start: dict[int, np.ndarray], sig: float,
                present: set[EffectKind]
                ) -> tuple[list[ScoreTest], dict[int, ModelState], Term | None]:
        """Return the score tests of the candidates the motion determines.

        With them, the state each refit starts at (by ``id`` of its test) and a field drift
        to try in place of a heading drift.
        """
        tests = []
        starts: dict[int, ModelState] = {}  # id of a ScoreTest -> the state its refit starts at
        replace_trial = None
        live: list[tuple[int, Term]] = []  # the candidates that get a score test
        for j, term in enumerate(cands):
            if hypothesis(term, present) in self.rejected | self.dropped:
                continue
            if term.kind in REQUIRES and not present & REQUIRES[term.kind]:
                continue  # it acts only through terms that are not in the model
            if NESTED_SIMPLER.get(term.kind) in present and term.kind not in IN_PARTS:
                # the simpler term in the model spans part of this one, which can only
                # replace it (tried below), not be added to it (a field drift over a
                # heading drift)
                replace_trial = term
                continue
            live.append((j, term))
        n = len(self.findings)

        def shown(k: int) -> None:
            progress.detail(f"search {n + 1}, candidate {k + 1}/{len(live)}",
                            n + 0.5 * (k + 1) / len(live), _ROUNDS_SHOWN)

        # every score test of the round at once (pipeline.model.parallel)
        for (_, term), (st, start) in zip(live, parallel.ordered(
                partial(self._score, cand_start, sig, present), live, shown), strict=True):
            if start is not None:
                starts[id(st)] = start
            if NESTED_SIMPLER.get(term.kind) not in present:
                term = st.term  # its scorer may shape it (the gradient's bearing)
            Bc = self.cur.state.B_enu_nT
            hfrac = float(np.linalg.norm(Bc[:2]) / max(float(np.linalg.norm(Bc)), 1e-9))
            reason = identifiability_reason(term.kind, self.stats, self.data, st.efficiency,
                                            horizontal_fraction=hfrac)
            if (reason is not None and term.kind in PARTIAL_KINDS and identifiability_reason(
                    term.kind, self.stats, self.data, 1.0, horizontal_fraction=hfrac) is None):
                # confounded in some combinations: tried on every combination the
                # recording determines (its data sigma below the prior); the words stay for
                # when it is not named and part of it is held
                part = partial_candidate(self.cur, term, self.data, sig)
                if part is not None:
                    if not self.findings and part.term.partial:
                        self.not_ident.setdefault(term.kind.value, reason)
                    st, term, reason = part, part.term, None
            if reason is None and st.rot_efficiency < CONFOUND_RATIO\
                    and term.kind not in LOCAL_KINDS:
                reason = (
                    f"with it the motion leaves the misalignment confounded (only "
                    f"{st.rot_efficiency:.1e} of its weakest combination stays determined): it "
                    "would trade against the misalignment; rotate through more attitudes"
                )
            if (reason is None and st.statistic < INTERP_MARGIN**2 * st.interp_statistic
                    and st.statistic > st.penalty):
                # it would have been tried, but the interpolation error could produce it
                reason = interp_reason(self.data)
            if reason is not None:
                if term.kind in LOCAL_KINDS:
                    continue
                if not self.findings:
                    self.not_ident.setdefault(term.kind.value, reason)
                elif (outer := _CONTAINED_IN.get(term.kind)) is not None and outer in present:
                    self.not_ident.setdefault(term.kind.value, (
                        f"a {term.kind.value} is a special case of the {outer.value} term "
                        "already in the model: the two cannot be told apart"))
                continue
            tests.append(st)
        return tests, starts, replace_trial

    def _score(self, cand_start: dict[int, np.ndarray], sig: float, present: set[EffectKind],
               cand: tuple[int, Term]) -> tuple[ScoreTest, ModelState | None]:
        """Return candidate ``(j, term)``'s score test and the state its refit starts at."""
        j, term = cand
        if NESTED_SIMPLER.get(term.kind) in present:
            # only what the simpler part in the model cannot explain: the rest (for an
            # eddy term beside a time offset, the anisotropic part of E_s)
            return IN_PARTS[term.kind][1](self.cur, self.data, sig), None
        return scored(self.cur, self.data, term, sig, cand_start.get(j))

    def _map_candidate(self, sig: float, present: set[EffectKind]) -> MapCandidate | None:
        """Return the field map candidate of this round, or None (why, in ``not_ident``)."""
        # the field beyond the gradient's first order: tried once the gradient is in the
        # model, its complexity chosen on the held-out blocks (stages.diagnose.field_map)
        mc: MapCandidate | None = None
        if EffectKind.FIELD_MAP not in present and hypothesis(
                Term(EffectKind.FIELD_MAP), present) not in self.rejected | self.dropped:
            got = map_candidate(self.cur, self.data, sig, self.cfg)
            if isinstance(got, str):
                self.not_ident.setdefault(EffectKind.FIELD_MAP.value, got)
            elif got is not None:
                st = got.test
                if st.rot_efficiency < CONFOUND_RATIO:
                    self.not_ident.setdefault(EffectKind.FIELD_MAP.value, (
                        "with it the motion leaves the rotation R_body_mag confounded (only "
                        f"{st.rot_efficiency:.1e} of its weakest combination stays determined)"))
                elif st.statistic < INTERP_MARGIN**2 * st.interp_statistic:
                    self.not_ident.setdefault(EffectKind.FIELD_MAP.value, interp_reason(self.data))
                else:
                    mc = got
        return mc

    def _refits(self, tests: list[ScoreTest], starts: dict[int, ModelState],
                ramps: list[tuple[int, Term]], mc: MapCandidate | None,
                replace_trial: Term | None, present: set[EffectKind]
                ) -> tuple[list, dict[int, int], list]:
        """Refit the strongest candidates.

        Returns the fits that raise the evidence by the margin, the steps whose transition a fit
        replaces (by ``id`` of its test) and the map's fits.
        """
        tests.sort(key=lambda s: -s.statistic + s.penalty)
        # the score test ranks the candidates; the few strongest are refitted and the one
        # with the most evidence is the strongest (a score statistic far from the null is only
        # a local approximation when much is still unmodelled)
        top = []
        for st in tests[: self.cfg.n_refit]:
            if -st.statistic + st.penalty > 0:
                break
            top.append(st)
        live_ramps = [(i, r) for i, r in ramps
                      if hypothesis(r, present) not in self.rejected | self.dropped]
        try_map = mc is not None and -mc.test.statistic + mc.test.penalty <= 0
        # every refit of the round at once (pipeline.model.parallel); what they mean is
        # decided below in the same order as one after the other
        jobs: list[partial[Any]] = [
            partial(_refit, self.cur, st.term, self.data, self.cfg, start=starts.get(id(st)))
            for st in top]
        jobs += [partial(_ramp_fit, self.cur, i, r, self.data, self.cfg) for i, r in live_ramps]
        if mc is not None and try_map:
            jobs.append(partial(_refit, self.cur, mc.test.term, self.data, self.cfg))
        if replace_trial is not None:
            jobs.append(partial(_replacement_fit, self.cur, NESTED_SIMPLER[replace_trial.kind],
                                replace_trial, self.data, self.cfg))
        n = len(self.findings)

        def shown(k: int) -> None:
            progress.detail(f"search {n + 1}, refit {k + 1}/{len(jobs)}",
                            n + 0.5 + 0.5 * (k + 1) / len(jobs), _ROUNDS_SHOWN)

        done: Iterator[Any] = iter(parallel.ordered(parallel.call, jobs, shown))  # in order
        fits: list[tuple[float, ScoreTest, FitResult]] = []
        for st in top:
            fr = next(done)
            if fr is None or not plausible(fr[0], self.data) or pulled_away(
                    starts.get(id(st)), fr[0], self.data):
                self.rejected.add(hypothesis(st.term, present))
                continue
            fits.append((fr[1], st, fr[0]))
        replaces: dict[int, int] = {}  # id of a ScoreTest -> the step its fit replaces
        for i_step, ramp in live_ramps:
            rf = next(done)
            if hypothesis(ramp, present) in self.rejected:
                continue  # a candidate of the same hypothesis failed above
            if rf is None:
                self.rejected.add(hypothesis(ramp, present))
                continue
            replaces[id(rf[1])] = i_step
            fits.append(rf)
        map_fits = []
        if mc is not None and try_map:
            fr = next(done)
            if fr is None:
                self.rejected.add(hypothesis(mc.test.term, present))
            else:
                map_fits.append((fr[1], mc.test, fr[0]))
        if replace_trial is not None and (rt := next(done)) is not None:
            fits.append(rt)
        fits.sort(key=lambda x: x[0])
        return fits, replaces, map_fits

    def _absorbing_last(self, fits: list, absorbing_fits: list) -> list:
        """Return the fits in the order they are tried: an absorbing term after what is not its.

        Whatever a term local in time or space or a global term explains is theirs; an
        absorbing term (:data:`~stages.diagnose.nested.ABSORBING`) is for what none of them
        can. A term that no longer earns its margin beside it was fitting its field (a bump
        in time where a survey line crosses a smooth anomaly) and waits until it was tried.
        """
        if absorbing_fits:
            first: list[tuple[float, ScoreTest, FitResult]] = []
            later: list[tuple[float, ScoreTest, FitResult]] = []
            by = absorbing_fits[0][2]
            gone = parallel.ordered(lambda f: absorbed(by, f[2], self.data, self.cfg), fits)
            for f, g in zip(fits, gone, strict=True):
                (later if g else first).append(f)
            fits = first + absorbing_fits + later
        return fits

    def _accept_first(self, fits: list, mc: MapCandidate | None, replaces: dict[int, int],
                      sig: float, present: set[EffectKind]) -> bool:
        """Name the first fit that passes every check; False when none does."""
        accepted = False
        refined: list[list[tuple[int, FitResult]]] = []  # fitted once a round, when asked
        k_fit = 0
        while k_fit < len(fits):
            dbic, st, res = fits[k_fit]
            k_fit += 1
            told = mc.words if mc is not None and st is mc.test else ""
            if st.term.kind in RIVALS:
                told, margin, alts = told_apart(self.cur, res, self.data)
                if margin < DECISIVE_FACTOR * self.cfg.bic_margin:
                    self.rejected.add(hypothesis(st.term, present))
                    if present & ABSORBING:
                        # the absorbing term, fitted while a transient was still hidden
                        # under the smooth field, took a share of it: what is left of the
                        # transient looks spatial enough to rank the term first. A rival
                        # that fits better is tried in its place (without one the scan
                        # proposes the transients itself, with their own minimum lengths)
                        for look in alts:
                            fr = _refit(self.cur, look, self.data, self.cfg)
                            if fr is not None:
                                look_st = score_test(self.cur, look, self.data, sig)
                                fits.insert(k_fit, (fr[1], look_st, fr[0]))
                    continue
            if (len(res.state.terms) == len(self.cur.state.terms) + 1
                    and not earns_beside_lookalikes(res, self.cur, len(self.cur.state.terms),
                                                    self.data, self.cfg)):
                self.rejected.add(hypothesis(st.term, present))
                continue
            if (st.term.kind in LOCAL_KINDS and present & REFINED.keys()
                    and id(st) not in replaces):
                if not refined:
                    refined.append(refinements(self.cur, self.data))
                if self._refined_instead(st.term, res, refined[0], present):
                    accepted = True
                    break
            if id(st) in replaces:
                # a transition lasts less than a held-out block: it is held out at its own
                # time scale, the current model on the same blocks (then the usual blocks
                # for the record)
                fine = dataclasses.replace(self.cfg, block_s=RAMP_KNOT_S)
                cv_fine = heldout_rms(self.cur.state, self.data, fine)
                ok = heldout_ok(self.cur, res, self.data, fine, cv_fine)
                cv_new = None if ok is None else heldout_rms(res.state, self.data, self.cfg)
            else:
                cv_new = heldout_ok(self.cur, res, self.data, self.cfg, self.cv_cur)
            if cv_new is None:
                self.rejected.add(hypothesis(st.term, present))
                continue
            term = res.state.terms[-1]
            gone = {t.kind for t in self.cur.state.terms} - {t.kind for t in res.state.terms}
            if gone:  # a replacement: the nested term it contains leaves the model
                self.findings = [f for f in self.findings if EffectKind(f.effect) not in gone]
                self.cur = fit(dataclasses.replace(res.state, terms=res.state.terms[:-1],
                                              values=res.state.values[:-1]), self.data)
            self.findings.append(_finding(self.cur, res, term, st, dbic, self.cv_cur, cv_new,
                                          self.data))
            if told:
                self.findings[-1] = dataclasses.replace(self.findings[-1], told_apart=told)
            if id(st) in replaces:
                # the step gained a transition: its finding is replaced in its place (the
                # evidence is measured again in the final order, _chain_evidence)
                i_step = replaces[id(st)]
                self.findings[i_step] = self.findings.pop()
                res = fit(moved_last_to(res.state, i_step), self.data)
            self.cur, self.cv_cur = res, cv_new
            accepted = True
            self.rejected.clear()
            break
        return accepted

    def _refined_instead(self, term: Term, res: FitResult,
                         refined: list[tuple[int, FitResult]], present: set[EffectKind]) -> bool:
        """Refine a held term in place of naming ``term`` when it explains it as well.

        ``res``: the current model with ``term`` added; ``refined``: the current model with
        each held term that has a finer form refined (:func:`~stages.diagnose.nested.
        refinements`). A term local in time that a refined held term explains as well, no
        worse on the held-out blocks, was that term's field where the sensor was then: the
        refined model becomes the current one and ``term`` is not tried again.
        """
        for i, rich in refined:
            cv_rich = explained_by_refinement(rich, res, self.data, self.cfg, self.cv_cur)
            if cv_rich is None:
                continue
            self.dropped.add(hypothesis(term, present))
            w0, w1 = term.windows_s[0]
            held = rich.state.terms[i]
            self.findings[i] = dataclasses.replace(self.findings[i], told_apart=(
                self.findings[i].told_apart + f"; refined to {REFINED[held.kind][1](held)} "
                f"when it explained a {term.kind.value} at {w0:.1f}-{w1:.1f} s as well (the "
                "field where the sensor was then), no worse on the held-out blocks"))
            self.cur, self.cv_cur = rich, cv_rich
            self.rejected.clear()
            return True
        return False

    def _settle(self) -> None:
        """Let the model settle after a term was named (sources, noise model, backward)."""
        moved = relocated(self.cur, self.data)
        if moved is not self.cur:
            self.cur, self.cv_cur = moved, heldout_rms(moved.state, self.data, self.cfg)
        # the noise model is measured on what the model leaves: the attitude noise may only
        # now stand out of it, and a model measured while an effect of thousands of nT was
        # unmodelled takes that effect for magnetometer noise. Its weights are then nearly
        # flat, and a lag gains by reading the noisy attitude where its interpolated noise is
        # smallest (sample_weights): a shift of tau that fits attitude noise, not a lag
        nm = estimate_noise_model(
            self.cur.residual_nT if self.cur.raw_residual_nT is None else self.cur.raw_residual_nT,
            self.data,
            self.e_int_nT)
        if nm is not None and (self.data.noise_model is None or not np.allclose(
                nm, self.data.noise_model, rtol=NOISE_MODEL_RTOL)):
            self.data = dataclasses.replace(self.data, noise_model=nm)
            self.cur = fit(self.cur.state, self.data)
            self.cv_cur = heldout_rms(self.cur.state, self.data, self.cfg)
        # a term named while other terms were missing may have stood in for what a later
        # term explains properly (the backward step), or contain another description that
        # now explains the data as well or better (a disturbance that is a magnet's step, two
        # pieces of one offset, a lag inside an eddy term): until neither changes the model
        self._backward()
        while (sm := simplest(self.cur, self.cv_cur, self.findings, self.data, self.cfg,
                              self.dropped)) is not None:
            self.cur, self.findings = sm
            self.cv_cur = heldout_rms(self.cur.state, self.data, self.cfg)
            self._backward()

    def exchange(self) -> bool:
        """Replace a term local in time by another effect's description of its window.

        The search names the strongest candidate of each round, so a term may be named
        while the terms that explain its window properly are still missing: a step that
        stands for a source the search has not located yet, after which the scan skips the
        window as modelled. The backward step asks only whether the model still needs such a
        term, not whether another effect explains its window better; this is the exchange
        move of stepwise selection (Miller 2002, ch. 3). Every effect's candidates at the
        term's window are fitted in its place, and the best one by the evidence replaces it
        when it raises the evidence by the margin and passes the held-out gate every new
        term passes. Each term is exchanged at most once (its hypothesis is dropped).
        Returns whether a term was replaced.
        """
        for i, old in enumerate(self.cur.state.terms):
            if not old.windows_s or old.kind not in LOCAL_KINDS:
                continue
            present = {t.kind for t in self.cur.state.terms}
            if hypothesis(old, present) in self.dropped:
                continue
            best = self._in_place_of(i)
            if best is None:
                continue
            res, st, dbic = best
            cv_new = heldout_ok(self.cur, res, self.data, self.cfg, self.cv_cur)
            if cv_new is None:
                continue
            (a, b), *_ = old.windows_s
            self.dropped.add(hypothesis(old, present))
            f = _finding(self.cur, res, res.state.terms[-1], st, dbic, self.cv_cur, cv_new,
                         self.data)
            self.findings.pop(i)
            self.findings.append(dataclasses.replace(f, told_apart=(
                f"; it replaces a {old.kind.value} named at {a:.1f}-{b:.1f} s before it "
                "was found: it explains that window better, by the evidence and on the "
                "held-out blocks")))
            self.cur, self.cv_cur = res, cv_new
            self.rejected.clear()
            self._settle()
            return True
        return False

    def _in_place_of(self, i: int) -> tuple[FitResult, ScoreTest, float] | None:
        """Return the best other description of term ``i``'s window: (fit, score test, delta).

        Candidates the score test ranks above the term itself (beside the model without it)
        are refitted, as the rounds refit the strongest; the fit with the most evidence is
        returned when it beats the current model by the margin (``delta``: its evidence
        change against the model without term ``i``).
        """
        old = self.cur.state.terms[i]
        wo = fit(without_term(self.cur.state, i), self.data)
        sig = robust_sigma(wo.residual_nT)
        w = old.windows_s[0]
        event = _event(w, w, self.data.t_s, edge_of_step=False)
        own = score_test(wo, old, self.data, sig)
        bar = own.penalty - own.statistic
        cands = [(term, start) for term, start in event_candidates(wo, self.data, event)
                 if not (term.kind is old.kind and term.windows_s == old.windows_s)]

        def tried(cand: tuple[Term, np.ndarray | None]
                  ) -> tuple[ScoreTest, tuple[FitResult, float] | None]:
            st, begin = scored(wo, self.data, cand[0], sig, cand[1])
            if st.penalty - st.statistic >= bar:
                return st, None
            # a located source the joint fit moves is kept here (a round refuses it,
            # sources.pulled_away): the rounds have ended, so no term the model lacks is
            # left for it to be fitting instead of its object
            return st, _refit(wo, st.term, self.data, self.cfg, start=begin)

        best: tuple[FitResult, ScoreTest, float] | None = None
        # every candidate at once (pipeline.model.parallel), compared in their order
        for st, fr in parallel.ordered(tried, cands):
            if fr is None or not plausible(fr[0], self.data):
                continue
            if evidence_between(fr[0], self.cur, self.data) > -self.cfg.bic_margin:
                continue
            if best is None or evidence_between(fr[0], best[0], self.data) < 0:
                best = (fr[0], st, fr[1])
        return best

    def _backward(self) -> None:
        """Drop each term that no longer earns its margin beside the others."""
        i = 0
        # the model without term k, fitted beside the one asked for: needed unless it goes
        without: parallel.Ahead[int, FitResult] = parallel.Ahead(
            lambda k: fit(without_term(self.cur.state, k), self.data))
        while i < len(self.cur.state.terms) - 1:
            t_i = self.cur.state.terms[i]
            terms = self.cur.state.terms
            if required(i, terms):
                i += 1  # another term acts through it (nested.REQUIRES)
                continue
            left = [k for k in range(i, len(terms) - 1) if not required(k, terms)]
            res_wo = without.get(left, 0)
            keep = evidence_change(self.cur, res_wo, self.data)
            # a term that earned its margin only by trading with a look-alike goes as well
            if keep > -self.cfg.bic_margin or not earns_beside_lookalikes(
                    self.cur, res_wo, i, self.data, self.cfg):
                self.dropped.add(hypothesis(t_i, {t.kind for t in self.cur.state.terms}))
                self.findings.pop(i)
                self.cur = res_wo
                self.cv_cur = heldout_rms(self.cur.state, self.data, self.cfg)
                without.forget()
                continue
            i += 1


def diagnose_data(
    data: FitData,
    init: ModelState | None = None,
    cfg: DiagnoseConfig | None = None,
    *,
    turntable: bool = False,
) -> tuple[Diagnosis, FitResult]:
    """Run detection, selection and location on prepared data.

    Parameters
    ----------
    data : FitData
        Stamps, readings and attitude track.
    init : ModelState, optional
        Baseline starting values (``R_body_mag``, ``B_enu``); Wahba initialisation otherwise.
    cfg : DiagnoseConfig, optional
        Thresholds (defaults when omitted).
    turntable : bool
        The attitude comes from a single-axis turntable (``axis_tilt`` is then a candidate).

    Returns
    -------
    (Diagnosis, FitResult)
        The diagnosis and the final fit.

    """
    cfg = cfg or DiagnoseConfig()
    if len(data) < 30:
        raise EstimationError("too few magnetometer samples with an attitude to diagnose")
    from_wahba = init is None
    if init is None:
        init = wahba_init(data)
    cur = fit(ModelState(init.R_body_mag, init.B_enu_nT), data)
    if not from_wahba:
        # a poor starting point (e.g. an estimator that assumed a clean sensor) must not
        # decide the baseline: keep the better of it and Wahba's start
        alt = fit(wahba_init(data), data)
        if alt.rss < cur.rss:
            cur = alt
    stats = motion_stats(data)
    # the likelihood's weights for what the attitude noise does between attitude samples
    # (stages.diagnose.model.sample_weights); the baseline is the model refitted with them,
    # the one the first finding's evidence starts from (one number in both places)
    e_int_nT = interpolation_error_nT(data)  # measured once, from the attitude track
    nm = estimate_noise_model(cur.residual_nT, data, e_int_nT)
    if nm is not None:
        data = dataclasses.replace(data, noise_model=nm)
        cur = fit(cur.state, data)
    base_rms = cur.rms_nT
    if e_int_nT > 0.05 * robust_sigma(cur.residual_nT):
        # the attitude's own interpolation error stands out of the noise: what it could
        # produce is not named (ScoreTest.interp_statistic)
        data = dataclasses.replace(data,
                                   interp_error_nT=interpolation_error_proxy(cur.state, data))
    cv_cur = heldout_rms(cur.state, data, cfg)
    baseline = {"effects": [], "residual_rms_nT": base_rms, "heldout_rms_nT": cv_cur}
    base_fit, cv_base = cur, cv_cur
    not_ident: dict[str, str] = {}
    known = data.B_known_enu_nT is not None
    kinds = [k for k in GLOBAL_KINDS if turntable or known or not EFFECTS[k].turntable_only]
    if turntable and not known:
        for k in GLOBAL_KINDS:
            if EFFECTS[k].turntable_only:
                why = identifiability_reason(k, stats, data, 0.0)
                not_ident[k.value] = why or ""
    search = _Search(data, cfg, stats, kinds, e_int_nT, cur, cv_cur, not_ident=not_ident)
    while len(search.findings) < cfg.max_findings and (search.round() or search.exchange()):
        pass
    data, cur, cv_cur, findings = search.data, search.cur, search.cv_cur, search.findings
    # the evidence of each finding was measured against the model of the moment it was added;
    # later rounds may have dropped or replaced terms before it. Re-measure it as a build-up in
    # the final order so that the numbers chain from the baseline to the final model.
    canon = canonical_rate_terms(cur, data)
    if canon is not cur:
        cur, cv_cur = canon, heldout_rms(canon.state, data, cfg)
    findings = _chain_evidence(findings, cur, base_fit, cv_base, cv_cur, data, cfg)
    cov_final = param_covariance(cur, data)
    note = gradient_note(cur, data, not_ident)
    findings = [
        dataclasses.replace(
            f,
            params=(p := term_params(cur.state.terms[i], cur.state.values[i], cur.state, data)),
            sigma=sigma_for(cur, i, cov_final, data),
            explanation=explanation(cur.state.terms[i].kind, p, data.duration_s, note=note)
            + _transition_words(cur.state.terms[i]) + held_words(cur, i, data) + f.told_apart,
        )
        for i, f in enumerate(findings)
    ]
    final: dict[str, Any] = {
        "effects": [f.effect for f in findings],
        "residual_rms_nT": cur.rms_nT,
        "heldout_rms_nT": cv_cur,
    }
    diag = Diagnosis(
        baseline=baseline,
        final=final,
        findings=tuple(findings),
        not_identifiable=tuple(
            (k, v) for k, v in not_ident.items() if k not in final["effects"]
        ),
        duration_s=data.duration_s,
    )
    return diag, cur

def gradient_note(cur: FitResult, data: FitData, not_ident: dict[str, str]) -> str | None:
    """Return what the test of a spatial gradient found, for the drift explanation.

    None without positions (the drift explanation then says that drift and gradient cannot
    be separated).
    """
    if data.p_m is None:
        return None
    for t, v in zip(cur.state.terms, cur.state.values, strict=True):
        if t.kind is EffectKind.FIELD_GRADIENT:
            g = float(np.linalg.norm(gradient_matrix(v, t.yaw_rad))) / 1e3
            return (
                "The recording carries positions: a spatial field gradient was tested and is "
                f"in the model (field_gradient, {g:.2f} uT/m); this drift is the change left "
                "in time once the field's variation along the path is modelled"
            )
    why = not_ident.get(EffectKind.FIELD_GRADIENT.value)
    if why:
        return (
            "The recording carries positions, but a spatial field gradient could not be "
            f"tested: {why}; the term may still stand for both"
        )
    return (
        "The recording carries positions: a spatial field gradient was tested and did not "
        "raise the evidence and lower the held-out error, so this is a change in time rather than "
        "the field varying along the sensor's path"
    )


def _prefix(state: ModelState, k: int) -> ModelState:
    """``state`` with only its first ``k`` terms (values as fitted in ``state``)."""
    return state.with_terms(state.terms[:k], state.values[:k])


def _chain_evidence(
    findings: list[Finding],
    final: FitResult,
    base: FitResult,
    cv_base: float,
    cv_final: float,
    data: FitData,
    cfg: DiagnoseConfig,
) -> list[Finding]:
    """Recompute each finding's evidence as a sequential build-up in the final order.

    Finding ``k`` is measured between the model with the findings before it and the model
    that adds it, so ``rms_after`` of finding ``k`` is ``rms_before`` of finding ``k + 1``,
    the first ``rms_before`` is the baseline's and the last ``rms_after`` the final model's
    (the same for the held-out RMS). Intermediate models are refitted from the final values.

    Parameters
    ----------
    findings : list of Finding
        In the order of ``final.state.terms``.
    final, base : FitResult
        The final and the baseline fit.
    cv_base, cv_final : float
        Their held-out RMS, nT.
    data : FitData
        The fitted samples.
    cfg : DiagnoseConfig
        Cross-validation settings.

    Returns
    -------
    list of Finding
        Same effects and order; evidence, ``where`` and signature re-measured.

    """
    K = len(findings)
    if K == 0:
        return findings
    prefixes = parallel.ordered(lambda k: fit(_prefix(final.state, k), data), range(1, K))
    fits = [base] + prefixes + [final]
    cvs = [cv_base] + [heldout_rms(f.state, data, cfg) for f in fits[1:K]] + [cv_final]
    out = []
    for k, fd in enumerate(findings):
        before, after = fits[k], fits[k + 1]
        term = after.state.terms[-1]
        st = score_test(before, term, data, robust_sigma(before.residual_nT))
        dbic = evidence_change(after, before, data)
        new = _finding(before, after, term, st, float(dbic), cvs[k], cvs[k + 1], data)
        out.append(dataclasses.replace(new, params=fd.params, sigma=fd.sigma,
                                       told_apart=fd.told_apart))
    return out


def _replacement_fit(
    cur: FitResult, simple: EffectKind, term: Term, data: FitData, cfg: DiagnoseConfig
) -> tuple[float, ScoreTest, FitResult] | None:
    """Replace the nested ``simple`` term of the model by ``term``, which contains it.

    Returns ``(delta -2 log evidence against the current model, score test, fit)`` when the
    replacement raises the evidence by ``bic_margin`` (the extra parameters counted), else
    None. The score test is made against the model without ``simple``.
    """
    i = next(k for k, t in enumerate(cur.state.terms) if t.kind is simple)
    wo = fit(without_term(cur.state, i), data)
    res = fit(wo.state.with_term(term), data)
    if not res.rss < cur.rss:
        return None
    dbic = evidence_change(res, cur, data)
    if dbic > -cfg.bic_margin:
        return None
    st = score_test(wo, term, data, robust_sigma(wo.residual_nT))
    return float(dbic), st, res


def canonical_rate_terms(res: FitResult, data: FitData) -> FitResult:
    """Store each gauged term's value off the direction it shares (``E_s`` traceless).

    A term held off the direction it shares with another in the model
    (:meth:`~stages.diagnose.model.ModelState.gauged`: an eddy term beside a time offset)
    is read by :func:`evaluate` through its projector only, so removing the rest changes
    neither the prediction nor the fit (``data``: kept for the callers' signature).
    """
    gauged = res.state.gauged()
    if not gauged:
        return res
    vals = tuple(EFFECTS[t.kind].gauge_projector() @ v if t.kind in gauged else v
                 for t, v in zip(res.state.terms, res.state.values, strict=True))
    return dataclasses.replace(res, state=dataclasses.replace(res.state, values=vals))


def _transition_words(term: Term) -> str:
    """Words on a step's transitions: when the magnet was carried on and off, s."""
    if term.kind is not EffectKind.HARD_IRON_STEP or not term.ramps_s:
        return ""
    (a, b), parts = term.windows_s[0], []
    for r0, r1 in term.ramps_s:
        what = "brought on" if abs(r0 - a) <= abs(r1 - b) else "taken away"
        parts.append(f"{what} over {r0:.2f}-{r1:.2f} s")
    return (". One event: the object was " + " and ".join(parts) + "; the field while it "
            "moved is modelled as a smooth curve from no offset to the plateau (and back), "
            "not as further steps")


def _refit(
    cur: FitResult, term: Term, data: FitData, cfg: DiagnoseConfig,
    start: ModelState | None = None,
) -> tuple[FitResult, float] | None:
    """Refit with ``term``; return (fit, delta -2 log evidence) if it drops by ``bic_margin``.

    ``start``: the state the fit starts from (``term`` appended with its start values);
    default ``term`` appended at zero.
    """
    res = canonical_rate_terms(fit(cur.state.with_term(term) if start is None else start,
                                   data), data)
    if not res.rss < cur.rss:
        return None
    dbic = evidence_change(res, cur, data)
    if dbic > -cfg.bic_margin:
        return None
    return res, float(dbic)


def _finding(
    cur: FitResult,
    res: FitResult,
    term: Term,
    st: ScoreTest,
    dbic: float,
    cv_before: float,
    cv_after: float,
    data: FitData,
) -> Finding:
    info = EFFECTS[term.kind]
    i = len(res.state.terms) - 1
    params = term_params(term, res.state.values[i], res.state, data)
    contrib = _contribution(cur.state, res.state, data)
    resid = cur.residual_nT
    frame = info.frame
    if frame == "enu":
        contrib_f = _to_enu(contrib, res.state, data)
        resid_f = _to_enu(resid, res.state, data)
    else:
        contrib_f, resid_f = contrib, resid
    if term.windows_s:
        windows = [[float(a), float(b)] for a, b in term.windows_s]
        m = term.indicator(data.t_s) > 0
        axes = _axes(contrib_f[m]) if m.any() else []
    else:
        windows = [[0.0, float(data.t_s[-1])]]
        if EFFECTS[term.kind].local_in_space:
            # local in space and present throughout: it acts where the sensor passes it,
            # where its own field (the model with and without its values) stands out
            off = dataclasses.replace(res.state, values=res.state.values[:i] + (
                np.zeros_like(res.state.values[i]),) + res.state.values[i + 1:])
            own = (evaluate(res.state, data, jacobian=False).y_nT
                   - evaluate(off, data, jacobian=False).y_nT)
            windows = _above_noise(own, data.t_s, robust_sigma(res.residual_nT)) or windows
        axes = _axes(contrib_f)
    stride = max(1, len(data) // 4000)
    regressor = None
    if EFFECTS[term.kind].rate_signature:
        regressor = evaluate(cur.state, data, jacobian=False).ydot0_nT_s[::stride]
    sigtr = Signature(data.t_s[::stride], resid_f[::stride], contrib_f[::stride], regressor)
    expl = explanation(term.kind, params, data.duration_s)
    return Finding(
        effect=term.kind.value,
        params=params,
        sigma={},
        evidence={
            "statistic": float(st.statistic),
            "delta_bic": float(dbic),
            "rms_before_nT": cur.rms_nT,
            "rms_after_nT": res.rms_nT,
            "heldout_rms_before_nT": float(cv_before),
            "heldout_rms_after_nT": float(cv_after),
        },
        where={"windows_s": windows, "axes": axes, "frame": frame},
        explanation=expl,
        signature=sigtr,
    )

"""``field_map`` in the diagnosis: its box, its complexity chosen on held-out blocks, the candidate.

The basis is :mod:`pipeline.model.field_map` (the Laplace eigenfunctions of a box, Solin et
al. 2018; the forward model and restore use the same one). Here:

- **The box** is the positions' bounding box padded on every side by a quarter of its largest
  extent
  (:func:`pipeline.model.field_map.domain_for`), in the position frame; its bearing is the
  one the ``field_gradient`` term located (``Term.yaw_rad``), which the map requires.
- **Complexity** ``n`` (2..8, at most :data:`MAX_BASIS` functions) is the number of modes
  along the box's longest axis; the other axes get as many as the same wavelength fits (at
  least two, a flat axis exactly two,
  :func:`~pipeline.model.field_map.axis_counts`), and the GP prior's length scale goes with
  it (:func:`~pipeline.model.field_map.length_scale_for`). With the box fixed, the bases of
  successive complexities are nested, so one Jacobian serves all: each is scored by the
  held-out blocks of the diagnosis (:func:`stages.diagnose.statistics.fold_of`: one-second
  blocks dealt to five folds), the model refitted on the other folds by one Gauss-Newton
  step from the current fit (exact for the weights, which enter linearly; the other
  parameters are at their optimum), and the held-out error of the folds summed. The
  complexity with the lowest held-out error is the candidate; it is offered only if that
  error is below the current model's. The search then refits it and keeps it by the gates
  every term has (the evidence's margin, held-out RMS of
  :func:`~stages.diagnose.statistics.heldout_rms`).
- **Identifiability.** A map along a path that visits every place once is any function of
  time: it would fit a disturbance or a drift. A complexity is tried only when at least half
  the samples have the sensor within its length scale of them at another time, at least
  :data:`REVISIT_GAP_S` apart (a survey's neighbouring lines, a hand-held sensor coming back).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.field_gradient import MIN_POSITION_INDEPENDENT, MIN_POSITION_SPREAD_M
from pipeline.model.field_map import (
    axis_counts,
    domain_for,
    length_scale_for,
    mode_indices,
)
from pipeline.model.solve import gram
from stages.diagnose.catalogue import (
    position_confounding,
)
from stages.diagnose.fit import FitResult
from stages.diagnose.model import F64, FitData, Term, evaluate
from stages.diagnose.result import DiagnoseConfig
from stages.diagnose.statistics import ScoreTest, fold_of, score_from_J

#: Complexities tried: modes along the box's longest axis.
COMPLEXITIES = (2, 3, 4, 5, 6, 7, 8)

#: Most basis functions of a candidate: the fit's cost grows with their square (a cube at
#: complexity 4 has 64, a flat survey at complexity 8 about 60).
MAX_BASIS = 64

#: At least this many samples per basis function.
MIN_SAMPLES_PER_BASIS = 40

#: Prior standard deviation of each field component, in units of the current residual's RMS:
#: weak where the data are (the data decide the weights there), it holds the combinations of
#: the basis the path leaves unobserved at zero.
PRIOR_FACTOR = 3.0

#: A place counts as revisited when the sensor was within the map's length scale of it at
#: least this long before or after, s: longer than a transient a ``disturbance`` describes.
REVISIT_GAP_S = 10.0

#: Fraction of the samples that must be revisited at a complexity's length scale.
MIN_REVISITED = 0.5

#: Samples used for the revisit test (every k-th).
_REVISIT_SAMPLES = 3000


def revisited_fraction(data: FitData, scale_m: float, gap_s: float = REVISIT_GAP_S) -> float:
    """Fraction of samples whose position the sensor passed within ``scale_m`` at another time.

    "Another time" is at least ``gap_s`` away: the samples are cut into time slices of
    ``gap_s``; each slice is compared (nearest neighbour) with the samples of the slices not
    adjacent to it.
    """
    if data.p_m is None or len(data) < 2:
        return 0.0
    step = max(1, len(data) // _REVISIT_SAMPLES)
    p = np.asarray(data.p_m, dtype=float)[::step]
    t = np.asarray(data.t_s, dtype=float)[::step]
    sl = np.floor((t - t[0]) / gap_s).astype(np.int64)
    hit = np.zeros(len(p), dtype=bool)
    for k in np.unique(sl):
        far = np.abs(sl - k) >= 2
        if not far.any():
            continue
        here = sl == k
        d, _ = cKDTree(p[far]).query(p[here], k=1)
        hit[here] = d <= scale_m
    return float(np.mean(hit))


def positions_extent(data: FitData) -> F64:
    """Extent of the positions along each position-frame axis, m, (3,)."""
    p = np.asarray(data.p_m, dtype=float)
    return np.ptp(p, axis=0) if len(p) else np.zeros(3)


def map_term(data: FitData, domain_m: F64, n: int, yaw_rad: float, prior_nT: float,
             noise_nT: float) -> Term:
    """Return the ``field_map`` term of complexity ``n`` on the box ``domain_m`` (3, 2)."""
    return Term(EffectKind.FIELD_MAP, yaw_rad=float(yaw_rad),
                domain_m=tuple((float(a), float(b)) for a, b in np.asarray(domain_m)),
                n_axis=axis_counts(domain_m, n, positions_extent(data)),
                length_scale_m=length_scale_for(domain_m, n),
                prior_nT=float(prior_nT), noise_nT=float(noise_nT))


def _ladder(dom: F64, data: FitData) -> list[int]:
    """Return the complexities a map on the box ``dom`` may have, ascending.

    Each is within the basis cap and revisited at its length scale.
    """
    cap = min(MAX_BASIS, len(data) // MIN_SAMPLES_PER_BASIS)
    ladder: list[int] = []
    for n in COMPLEXITIES:
        if int(np.prod(axis_counts(dom, n, positions_extent(data)))) > cap:
            break
        if revisited_fraction(data, length_scale_for(dom, n)) < MIN_REVISITED:
            break
        ladder.append(n)
    return ladder


def finer_map_term(term: Term, data: FitData) -> Term | None:
    """Return the map one complexity finer than ``term`` (its box, prior, noise), or None.

    The ladder is :func:`map_candidate`'s (the same cap and revisit rule), so the finer map is
    one the candidate could have chosen.
    """
    dom = np.asarray(term.domain_m, dtype=float)
    n = max(term.n_axis) + 1  # the complexity is the modes along the box's longest axis
    if n not in _ladder(dom, data):
        return None
    return map_term(data, dom, n, term.yaw_rad, term.prior_nT, term.noise_nT)


@dataclass(frozen=True)
class MapCandidate:
    """A ``field_map`` candidate: its score test and how its complexity was chosen.

    Attributes
    ----------
    test : ScoreTest
        Of the chosen complexity (its term), with the prior in its information.
    heldout_nT : dict of int to float
        Held-out RMS (weighted residual, nT) of each complexity tried, 0 the current model.
    words : str
        The choice, for the explanation.

    """

    test: ScoreTest
    heldout_nT: dict[int, float]
    words: str


def map_candidate(cur: FitResult, data: FitData, sigma: float,
                  cfg: DiagnoseConfig) -> MapCandidate | str | None:
    """Return the ``field_map`` candidate of the current model, why it cannot be, or None.

    Only with positions and a ``field_gradient`` in the model (the map is the field beyond
    the gradient's first order; it takes the gradient's bearing). None when no complexity
    predicts the held-out blocks better than the current model.
    """
    grad = next((t for t in cur.state.terms if t.kind is EffectKind.FIELD_GRADIENT), None)
    if data.p_m is None or grad is None:
        return None
    spread, indep = position_confounding(data)
    if spread < MIN_POSITION_SPREAD_M or indep < MIN_POSITION_INDEPENDENT:
        return "the sensor's path is too short or too much a function of time for a field map"
    dom = domain_for(np.asarray(data.p_m))
    r = cur.residual_nT
    prior_nT = PRIOR_FACTOR * float(np.sqrt(np.mean(r * r)))
    ladder = _ladder(dom, data)
    if not ladder:
        return (
            "the path visits its places once at the scale of a field map (fewer than "
            f"{100 * MIN_REVISITED:.0f} % of the samples are revisited {REVISIT_GAP_S:.0f} s or "
            "more later): a map along it cannot be told from a change in time"
        )
    terms = {n: map_term(data, dom, n, grad.yaw_rad, prior_nT, sigma) for n in ladder}
    big = terms[ladder[-1]]
    ev = evaluate(cur.state.with_term(big), data)
    J = ev.jac if ev.sqrt_w is None else ev.jac * ev.sqrt_w[:, None, None]
    p0 = cur.state.n_params()
    base = np.arange(p0) if data.B_known_enu_nT is None else np.r_[0:3, 6:p0]
    # each complexity's modes among the largest one's columns (n_3 fastest)
    N = np.asarray(big.n_axis)
    cols: dict[int, np.ndarray] = {0: base}
    precs: dict[int, np.ndarray] = {0: np.zeros(len(base))}
    idx: dict[int, np.ndarray] = {}
    for n in ladder:
        m = mode_indices(terms[n].n_axis) - 1
        idx[n] = (m[:, 0] * N[1] + m[:, 1]) * N[2] + m[:, 2]
        cols[n] = np.r_[base, p0 + idx[n]]
        precs[n] = np.r_[np.zeros(len(base)), terms[n].prior_precision()]
    folds = fold_of(data.t_s, cfg)
    Jf_all = J.reshape(len(data), 3, -1)
    per_fold = []
    for j in range(cfg.n_folds):
        te = folds == j
        if te.sum() == 0 or (~te).sum() < 10:
            continue
        Jt = Jf_all[te].reshape(-1, J.shape[-1])
        rt = r[te].reshape(-1)
        per_fold.append((Jt, rt, gram(Jt, Jt), gram(Jt, rt[:, None])[:, 0]))
    H = sum(f[2] for f in per_fold)
    g = sum(f[3] for f in per_fold)
    cv: dict[int, float] = {}
    for n, c in cols.items():
        sq, cnt = 0.0, 0
        for Jt, rt, Ht, gt in per_fold:
            A = (H - Ht)[np.ix_(c, c)] + np.diag(precs[n])
            A += 1e-12 * float(np.max(np.diag(A))) * np.eye(len(c))
            try:
                dx = np.linalg.solve(A, (g - gt)[c])
            except np.linalg.LinAlgError:
                dx = np.linalg.lstsq(A, (g - gt)[c], rcond=None)[0]
            e = rt - Jt[:, c] @ dx
            sq += float(e @ e)
            cnt += e.size
        cv[n] = float(np.sqrt(sq / max(cnt, 1)))
    best = min(ladder, key=lambda n: cv[n])
    if not cv[best] < cv[0]:
        return None
    term = terms[best]
    Jc = J.reshape(-1, J.shape[-1])[:, np.r_[np.arange(p0), p0 + idx[best]]]
    st = score_from_J(cur, term, Jc, data, sigma, prior=term.prior_precision())
    tried = ", ".join(f"{n} ({int(np.prod(terms[n].n_axis))} functions) {cv[n]:.3g} nT"
                      for n in ladder)
    words = (
        f". Its complexity was chosen on the held-out one-second blocks: modes along the "
        f"longest axis {tried}, against {cv[0]:.3g} nT without the map (each fold refitted "
        f"from the fit of the moment); {best} was the best"
    )
    return MapCandidate(st, cv, words)

"""The diagnosis statistics.

Score (Lagrange multiplier) tests of candidate terms at the current fit, robust noise and
its inflation by residual correlation, the Laplace evidence with effective samples,
held-out time blocks, the covariance of a fit.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.model import parallel
from pipeline.model.effects import EFFECTS
from pipeline.model.parallel import PerThread
from pipeline.model.solve import gram
from stages.diagnose.fit import FitResult, fit
from stages.diagnose.model import (
    LOCAL_KINDS,
    FitData,
    ModelState,
    Term,
    evaluate,
    sample_weights,
    term_sigma,
)
from stages.diagnose.result import DiagnoseConfig
from stages.estimators.base import (
    RELATIVE_INFO_THRESHOLD,
    information_ratio,
    solve_many_truncated,
)

#: Yaw grid of the search for a position frame rotated about Up (``field_gradient``), deg.
YAW_GRID_DEG = np.arange(0.0, 360.0, 10.0)


def robust_sigma(r: np.ndarray) -> float:
    """Robust noise scale of residual components: 1.4826 MAD, nT."""
    x = np.asarray(r).ravel()
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) + 1e-12


def inflation(r: np.ndarray, t_s: np.ndarray, block_s: float = 0.5) -> float:
    """Variance inflation of the mean from residual correlation (>= 1).

    Attitude noise that is correlated in time makes neighbouring residuals alike; the
    information per sample is then smaller than white-noise theory says. The ratio of the
    variance of block means to the variance expected for independent samples measures it.
    """
    n = len(t_s)
    if n < 20:
        return 1.0
    dt = float(np.median(np.diff(t_s)))
    L = max(2, int(round(block_s / max(dt, 1e-9))))
    nb = n // L
    if nb < 5:
        return 1.0
    x = np.asarray(r)[: nb * L].reshape(nb, L, -1)
    v = np.var(np.asarray(r)[: nb * L], axis=0)
    vb = np.var(x.mean(axis=1), axis=0)
    ratio = float(np.sum(vb * L) / max(np.sum(v), 1e-30))
    return max(1.0, ratio)


@dataclass(frozen=True)
class ScoreTest:
    """Score (Lagrange multiplier) test of a candidate term at the current fit.

    Attributes
    ----------
    term : Term
    statistic : float
        ``g' I_eff^-1 g / sigma^2`` (chi-square with ``k`` dof under the null, white noise).
    efficiency : float
        Smallest generalised eigenvalue of ``I_eff`` vs the term's own information (0: fully
        confounded with parameters already in the model).
    k : int
        The term's free parameters (a partial term: the combinations the motion determines).
    penalty : float
        What the term costs in the statistic's units, its ``-2 log`` Occam factor
        (:func:`occam`): ``k log n`` under the unit-information prior, less for parameters
        with a stated prior that the data see only in part (a field map's fine modes). The
        term is worth a refit when the statistic exceeds it.
    rot_efficiency : float
        The same fraction for the rotation ``R_body_mag`` once the term is in the model, when
        the term at least halves it (else 1): a term that leaves the rotation confounded
        (below ``CONFOUND_RATIO``) is not admitted, however well it fits.
    interp_statistic : float
        The same statistic for the attitude's interpolation error alone
        (``FitData.interp_error_nT``): a term whose statistic is not well beyond it
        (``INTERP_MARGIN``) could be the interpolation error and is not named.

    """

    term: Term
    statistic: float
    efficiency: float
    k: int
    penalty: float
    rot_efficiency: float = 1.0
    interp_statistic: float = 0.0


def gradient_candidate(cur: FitResult, data: FitData, sigma: float) -> ScoreTest:
    """Return the ``field_gradient`` term with the best position-frame yaw and its score test.

    Positions in ENU: yaw 0. Positions in the attitude source's frame (rotated about Up by an
    unknown angle): the Jacobian columns are ``cos(a) A + sin(a) B + C`` in the yaw ``a``, so
    three evaluations give them for every yaw; the score statistic is maximised over a
    10-degree grid and refined by a parabola through the best grid point. The yaw is then
    held (like the window of a local term); the search costs about one degree of freedom,
    well inside the evidence's margin.
    """
    if data.position_frame != "attitude_source_local":
        return score_test(cur, Term(EffectKind.FIELD_GRADIENT), data, sigma)
    p0 = cur.state.n_params()
    cols = []
    for yaw in (0.0, np.pi / 2, np.pi):
        ev = evaluate(cur.state.with_term(Term(EffectKind.FIELD_GRADIENT, yaw_rad=yaw)), data)
        J = ev.jac if ev.sqrt_w is None else ev.jac * ev.sqrt_w[:, None, None]
        cols.append(J.reshape(-1, J.shape[-1]))
    Jb = cols[0][:, :p0]
    C = 0.5 * (cols[0][:, p0:] + cols[2][:, p0:])
    A = 0.5 * (cols[0][:, p0:] - cols[2][:, p0:])
    Bm = cols[1][:, p0:] - C

    def at(deg: float) -> ScoreTest:
        a = np.radians(deg)
        J = np.concatenate([Jb, np.cos(a) * A + np.sin(a) * Bm + C], axis=1)
        return score_from_J(cur, Term(EffectKind.FIELD_GRADIENT, yaw_rad=float(a)), J, data,
                             sigma)

    tests = parallel.ordered(at, [float(d) for d in YAW_GRID_DEG])
    stats = np.array([t.statistic for t in tests])
    i = int(np.argmax(stats))
    s_m, s_0, s_p = stats[i - 1], stats[i], stats[(i + 1) % len(stats)]
    den = s_m - 2 * s_0 + s_p
    step = float(YAW_GRID_DEG[1] - YAW_GRID_DEG[0])
    shift = 0.5 * (s_m - s_p) / den * step if den < 0 else 0.0
    best = at(float(YAW_GRID_DEG[i]) + float(np.clip(shift, -step, step)))
    return best if best.statistic >= tests[i].statistic else tests[i]


def score_test(cur: FitResult, term: Term, data: FitData, sigma: float,
               start: ModelState | None = None) -> ScoreTest:
    """Score test of adding ``term`` to the model of ``cur`` (no refit).

    ``start``: the model with ``term`` appended at its null values (default zero), for a
    term whose Jacobian depends on where it is (a source's position).
    """
    st = cur.state.with_term(term) if start is None else start
    ev = evaluate(st, data)
    w = None if ev.sqrt_w is None else ev.sqrt_w[:, None, None]
    J = ev.jac if w is None else ev.jac * w
    held = None
    if ev.J_held is not None:
        held = (ev.J_held if w is None else ev.J_held * w).reshape(-1, ev.J_held.shape[-1])
    return score_from_J(cur, term, J.reshape(-1, J.shape[-1]), data, sigma,
                         held=held if held is not None else np.zeros((J.shape[0] * 3, 0)))


_HELD_CACHE: PerThread[list[tuple[Any, np.ndarray | None]]] = PerThread(list)


def held_columns(state: ModelState, data: FitData) -> np.ndarray | None:
    """Weighted columns (3N, Q) of the combinations the partial terms of ``state`` hold.

    None without partial terms. Kept for the last (state, data) asked for: every candidate
    of a search round is tested against the same model.
    """
    if not state.has_partial:
        return None
    last = _HELD_CACHE.value
    if last and last[0][0][0] is state and last[0][0][1] is data:
        return last[0][1]
    ev = evaluate(state, data)
    assert ev.J_held is not None  # the state has partial terms
    Jh = ev.J_held if ev.sqrt_w is None else ev.J_held * ev.sqrt_w[:, None, None]
    out = Jh.reshape(-1, Jh.shape[-1])
    last[:] = [((state, data), out)]
    return out


def score_from_J(
    cur: FitResult, term: Term, J: np.ndarray, data: FitData, sigma: float,
    prior: np.ndarray | None = None, held: np.ndarray | None = None,
) -> ScoreTest:
    """Score test from the Jacobian (3N, P) of the model with ``term`` appended.

    ``prior``: the ridge of the term's parameters (a ``field_map``'s GP prior, per nT^2,
    :meth:`~stages.diagnose.model.Term.prior_precision`), added to their information: the
    statistic and the rotation's efficiency are then those of the fit, which has it.

    ``held``: weighted columns (3N, Q) of the combinations partial terms hold at their
    reference (:attr:`~stages.diagnose.model.Evaluation.J_held`); default those of the
    model of ``cur`` (:func:`held_columns`). They are profiled out like the fitted
    parameters: what the motion cannot tell from them is no evidence for another term, so
    a drift, a step or a disturbance cannot take up the part of an offset the fit holds.
    """
    r = cur.residual_nT.reshape(-1)
    p0 = cur.state.n_params()
    if data.B_known_enu_nT is not None:
        keep = np.r_[0:3, 6:p0]
        Jb = J[:, keep]
    else:
        keep = np.arange(p0)
        Jb = J[:, :p0]  # the same columns, without a copy
    Jc = J[:, p0:]
    if held is None:
        held = held_columns(cur.state, data)
    n_held = 0 if held is None else held.shape[1]
    if n_held:
        Jb = np.concatenate([Jb, held], axis=1)
    Hbb, rot_base = _base_information(Jb)
    Hbc, Hcc = gram(Jb, Jc), gram(Jc, Jc)
    base_prior = cur.state.prior_precision()
    if base_prior is not None:  # a field_map in the model: its ridge is information too
        base_prior = np.r_[base_prior[keep], np.zeros(n_held)]
        Hbb = Hbb + np.diag(base_prior)
        rot_base = _rot_efficiency_H(Hbb)
    if prior is not None:
        Hcc = Hcc + np.diag(prior)
    g = gram(Jc, r[:, None])[:, 0]
    gb = gram(Jb, r[:, None])[:, 0]  # ~0 at a converged fit (not along held columns)
    if base_prior is not None:  # the posterior's gradient: the ridge pulls too
        gb = gb - base_prior * np.r_[cur.state.flat_values()[keep], np.zeros(n_held)]
    sb = np.sqrt(np.clip(np.diag(Hbb), 1e-30, None))
    Hbb_n = Hbb / np.outer(sb, sb)
    try:
        X = np.linalg.lstsq(Hbb_n + 1e-12 * np.eye(len(sb)), (Hbc / sb[:, None]), rcond=None)[0]
        xb = np.linalg.lstsq(Hbb_n + 1e-12 * np.eye(len(sb)), gb / sb, rcond=None)[0]
    except np.linalg.LinAlgError:
        return ScoreTest(term, 0.0, 0.0, term.n_params(), term.n_params() * np.log(r.size))
    Ieff = Hcc - (Hbc / sb[:, None]).T @ X
    geff = g - (Hbc / sb[:, None]).T @ xb
    sc = np.sqrt(np.clip(np.diag(Hcc), 1e-30, None))
    In = Ieff / np.outer(sc, sc)
    In = 0.5 * (In + In.T)
    ev_all = np.linalg.eigvalsh(In)
    Hn = Hcc / np.outer(sc, sc)
    try:
        Lc = np.linalg.cholesky(0.5 * (Hn + Hn.T) + 1e-12 * np.eye(len(sc)))
        Li = np.linalg.inv(Lc)
        effs = np.linalg.eigvalsh(Li @ In @ Li.T)
    except np.linalg.LinAlgError:
        effs = ev_all
    # e.g. a tilted turntable axis with a known field (see Effect.identifiable_in_part)
    partial = EFFECTS[term.kind].identifiable_in_part
    eff = float(effs[-1] if partial else effs[0])
    # pseudo-inverse with a relative floor: confounded directions carry no evidence
    w, V = np.linalg.eigh(In)
    good = w > 1e-8 * max(float(w[-1]), 1e-30)
    z = V.T @ (geff / sc)
    stat = float(np.sum(z[good] ** 2 / w[good])) / sigma**2
    stat_int = 0.0
    if data.interp_error_nT is not None:
        # the same statistic for what the interpolation error alone leaves (weighted as r)
        sw = sample_weights(data, cur.state.tau_s())
        e = data.interp_error_nT if sw is None else data.interp_error_nT * np.sqrt(sw)[:, None]
        e = e.reshape(-1)
        ge = gram(Jc, e[:, None])[:, 0]
        gbe = gram(Jb, e[:, None])[:, 0]
        xbe = np.linalg.lstsq(Hbb_n + 1e-12 * np.eye(len(sb)), gbe / sb, rcond=None)[0]
        ze = V.T @ ((ge - (Hbc / sb[:, None]).T @ xbe) / sc)
        stat_int = float(np.sum(ze[good] ** 2 / w[good])) / sigma**2
    k = max(int(np.count_nonzero(good)) if partial else term.n_params(), 1)
    penalty = k * float(np.log(r.size))
    if prior is not None and np.any(prior > 0):
        nb = 3 if data.B_known_enu_nT is not None else 6  # the misalignment and the field
        Hb0c = Hbc[:nb]
        Ibase = Hcc - Hb0c.T @ np.linalg.lstsq(Hbb[:nb, :nb], Hb0c, rcond=1e-12)[0]
        penalty = _prior_penalty(Ieff, geff, Ibase, prior, term.noise_nT**2, r.size, sigma)
    # from the blocks already formed (with a field_map's ridge when there is one): the full
    # product of [Jb, Jc] would be the costliest step of the test
    rot_with = _rot_efficiency_H(np.block([[Hbb, Hbc], [Hbc.T, Hcc]]))
    # what the term itself costs the rotation: below 1 when it trades against R
    rot_eff = rot_with if rot_with < 0.5 * rot_base else 1.0
    return ScoreTest(term, stat, max(eff, 0.0), k, penalty, rot_eff, stat_int)


def _prior_penalty(Ieff: np.ndarray, geff: np.ndarray, Ibase: np.ndarray, prior: np.ndarray,
                   noise2: float, n: int, sigma: float) -> float:
    """Return the :func:`occam` factor of a candidate with a prior, from its score test.

    ``Ieff`` (k, k): the candidate's information beyond the model's parameters, its prior's
    ridge ``prior`` included, and ``geff`` its gradient there: ``theta`` is the one Newton
    step from zero the score test stands for. ``Ibase``: its information beyond the
    misalignment and the field only, what :func:`occam` charges it for; ``noise2`` the noise
    variance its ridge was set against. Its parameters without a prior cost ``log n`` each
    (:func:`prior_occam` for the others).
    """
    theta = np.linalg.lstsq(0.5 * (Ieff + Ieff.T), geff, rcond=1e-12)[0]
    q = prior > 0
    return int(np.sum(~q)) * float(np.log(n)) + prior_occam(
        0.5 * (Ibase + Ibase.T), prior, np.full(len(prior), noise2), theta,
        np.ones(len(prior), dtype=bool), 1.0, sigma**2)


#: A term is named only when its score statistic exceeds this factor squared times the one
#: of the attitude's interpolation error alone (its amplitude three times that error's).
INTERP_MARGIN = 3.0


def interp_reason(data: FitData) -> str:
    """Why a term the interpolation error could produce is not named, in words."""
    rate = 1.0 / max(data.track.step_s, 1e-9)
    rms = float(np.sqrt(np.mean(np.asarray(data.interp_error_nT) ** 2)))
    return (f"the attitude at {rate:.3g} Hz is too slow for this motion: its own "
            f"interpolation error (about {rms:.3g} nT RMS at the magnetometer) could produce "
            "this term; record the attitude faster or move more slowly")


_BASE_CACHE: PerThread[list[tuple[np.ndarray, np.ndarray, float]]] = PerThread(list)


def _base_information(Jb: np.ndarray) -> tuple[np.ndarray, float]:
    """``Jb.T Jb`` and the rotation's efficiency of the current model's columns ``Jb``.

    Every candidate of a search round is tested against the same model, whose columns come
    out of its evaluation bit for bit alike: the product is kept for the last ``Jb`` seen
    (compared in full, far cheaper than forming it again).
    """
    last = _BASE_CACHE.value
    if last and last[0][0].shape == Jb.shape and np.array_equal(last[0][0], Jb):
        return last[0][1], last[0][2]
    H = gram(Jb, Jb)
    rot = _rot_efficiency_H(H)
    last[:] = [(Jb.copy(), H, rot)]
    return H, rot


def _rot_efficiency(J: np.ndarray) -> float:
    """Fraction of the rotation's weakest information left with the other columns free."""
    return _rot_efficiency_H(gram(J, J))


def _rot_efficiency_H(H: np.ndarray) -> float:
    """:func:`_rot_efficiency` from the information ``J.T J`` (rotation in its first 3 rows)."""
    lam = information_ratio(H, slice(0, 3))
    live = lam[lam >= RELATIVE_INFO_THRESHOLD]
    return float(np.min(live)) if live.size else 1.0


def fold_of(t_s: np.ndarray, cfg: DiagnoseConfig, state: ModelState | None = None
            ) -> np.ndarray:
    """Fold index of each sample: contiguous blocks of ``block_s`` dealt round-robin.

    Inside the transitions of a ``hard_iron_step`` of ``state`` the blocks are as short as
    the transition's own modes (``Term.knot_step_s``): a curve that resolves a tenth of a
    second is held out at that scale, as every other term is at the scale of a second; a
    whole transition held out at once would test a magnet's path nobody could predict.
    """
    blocks = np.floor((t_s - t_s[0]) / cfg.block_s).astype(np.int64)
    for t in () if state is None else state.terms:
        for r0, r1 in t.ramps_s if t.kind is EffectKind.HARD_IRON_STEP else ():
            m = (t_s >= r0) & (t_s < r1)
            blocks[m] = np.floor((t_s[m] - t_s[0]) / t.knot_step_s).astype(np.int64)
    return blocks % cfg.n_folds


def heldout_rms(state: ModelState, data: FitData, cfg: DiagnoseConfig) -> float:
    """RMS prediction error on held-out time blocks, nT.

    The model is refitted without each fold and predicts it (:func:`fold_errors`). Random
    samples are never held out: neighbouring samples share attitude noise and would leak.
    """
    folds = fold_of(data.t_s, cfg, state)
    sq, cnt = 0.0, 0
    for _, e in fold_errors(state, data, data, folds, folds, cfg.n_folds):
        sq += float(np.sum(e * e))
        cnt += e.size
    return float(np.sqrt(sq / max(cnt, 1)))


def fold_errors(state: ModelState, train: FitData, test: FitData, fold_train: np.ndarray,
                fold_test: np.ndarray, n_folds: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each fold's held-out errors: the model fitted without the fold predicts it.

    Each fold is refitted from ``state`` on the ``train`` samples outside it, with the
    values of local terms reset to zero (so that a window's amplitude is learnt only from
    training samples), then predicts the ``test`` samples inside it. ``train`` and
    ``test`` may differ (the repeats of a sample-and-hold sensor are predicted although only
    the first copies are fitted). The folds are fitted side by side
    (:mod:`pipeline.model.parallel`).

    Returns
    -------
    list of (ndarray of bool, ndarray (k, 3))
        In fold order, for each fold with test samples and at least 10 training samples:
        its mask over ``test`` and the errors there, nT.

    """
    start = dataclasses.replace(
        state,
        values=tuple(
            np.zeros_like(v) if t.kind in LOCAL_KINDS else v
            for t, v in zip(state.terms, state.values, strict=True)
        ),
    )
    folds = [(fold_test == j, fold_train != j) for j in range(n_folds)]
    folds = [(te, tr) for te, tr in folds if te.any() and tr.sum() >= 10]

    def error(fold: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        te, tr = fold
        # the fold's state alone predicts: its information is not formed again at the end
        res = fit(start, train.subset(tr), max_iter=6, rtol=1e-6, final_information=False)
        sub = test.subset(te)
        return sub.y_nT - evaluate(res.state, sub, jacobian=False).y_nT

    return list(zip([te for te, _ in folds], parallel.ordered(error, folds), strict=True))


def heldout_ok(
    cur: FitResult, res: FitResult, data: FitData, cfg: DiagnoseConfig, cv_old: float
) -> float | None:
    """Held-out RMS of the model ``res``, or None if it does not improve on ``cur`` enough.

    The improvement in chi-square units of the (correlation-discounted) noise must clear the
    same bar as the evidence (the model's :func:`occam` factor and the margin): a term that
    only fits noise does not predict new blocks.
    """
    cv_new = heldout_rms(res.state, data, cfg)
    n_eff = effective_samples(res, data)
    s2 = res.rss / res.residual_nT.size
    cost = occam(res, data, n_eff) - occam(cur, data, n_eff)
    gain = (cv_old**2 - cv_new**2) * n_eff / s2
    if cv_new < cv_old * (1.0 - cfg.heldout_margin) and gain >= cost + cfg.bic_margin:
        return cv_new
    return None


def occam(res: FitResult, data: FitData, n_eff: float) -> float:
    """Return ``-2 log`` of the Occam factor of the model of ``res`` (Laplace's method).

    The evidence of a model is its best fit's likelihood times the Occam factor, the share
    of its parameters' prior that the data leave standing (MacKay 1992, Bayesian
    interpolation, section 1; the Laplace approximation, Kass & Raftery 1995, Eq. 4). Each
    effect states its prior (:meth:`~pipeline.model.effects.base.Effect.prior_precision`):

    - parameters with a prior (``Q``: a field map's weights, a step's transitions, GP
      priors of stated size): ``log det(I + P^-1 S / c) + theta' P theta / s2``, with ``P``
      their prior's ridge, ``S`` the information the data hold on them beyond the
      misalignment and the field (the Schur complement of the fit's information; each term
      pays for its own, whatever else is in the model), ``c = n / n_eff`` the
      residual's correlation inflation (``n`` its entries) and ``s2 = rss / n`` its
      variance per entry, the noise each ridge is weighed against (the GP's ``noise_nT``).
      A direction the data do not see costs nothing and gains nothing; a well-seen one
      costs the log of how much the data narrow its prior;
    - every other free parameter: the unit-information prior (one effective sample's
      information, Kass & Wasserman 1995), ``log n_eff`` each: the BIC's count.

    Without a prior in the model this is ``n_free log n_eff`` and the evidence is the BIC.
    """
    st = res.state
    prec = st.prior_precision()
    k = st.n_free()
    if prec is None or not np.any(prec > 0):
        return k * float(np.log(n_eff))
    # the information on them beyond the misalignment and the field only: each term pays for
    # its own, and a term added beside it (a drift beside a map, sharing directions with it)
    # never makes it cheaper, as with the BIC's count
    base = np.zeros(prec.size, dtype=bool)
    base[:6] = True
    if data.B_known_enu_nT is not None:
        base[3:6] = False  # held at the known field: no information, no prior
    q = prec > 0
    c = max(res.residual_nT.size / n_eff, 1.0)
    return (k - int(q.sum())) * float(np.log(n_eff)) + prior_occam(
        res.info, prec, st.prior_noise2(), st.flat_values(), base | q, c,
        res.rss / res.residual_nT.size)


def prior_occam(H: np.ndarray, prec: np.ndarray, noise2: np.ndarray, theta: np.ndarray,
                fitted: np.ndarray, c: float, s2: float) -> float:
    """Return ``-2 log`` of the Occam factor of the parameters with a prior (Gaussian).

    ``log det(I + V^1/2 (S - P) V^1/2 / (c s2)) + theta_Q' V^-1 theta_Q`` (:func:`occam`):
    ``H`` (P, P) the posterior's information ``J' W J + diag(prec)``, ``prec`` (P,) the
    prior's ridge (zero: no prior), ``noise2`` (P,) the noise variance each ridge was set
    against, so that ``V = diag(noise2 / prec)`` is the prior's own covariance, ``theta``
    (P,) the fit, ``fitted`` (P,) the parameters the fit moves, ``S`` the Schur complement
    of ``H`` on the parameters with a prior given the other fitted ones (``S - P`` the
    data's information on them), ``c`` the residual's correlation inflation and ``s2`` the
    residual's variance per entry. For a linear model with white Gaussian noise of variance
    ``s2`` (``c = 1``) this with ``rss / s2 + n log(2 pi s2)`` is the exact ``-2 log``
    marginal likelihood (MacKay 1992), whatever noise the ridge was set against: the prior
    is ``V``, a physical size in the parameters' units. Weighing the ridge against the
    residual of the moment instead would tighten the prior by the ratio of the two
    variances as the model improves, and charge a term the more, the more it explains.
    """
    q = prec > 0
    o = fitted & ~q
    S = H[np.ix_(q, q)]
    if np.any(o):
        Hoq = H[np.ix_(o, q)]
        S = S - Hoq.T @ np.linalg.lstsq(H[np.ix_(o, o)], Hoq, rcond=1e-12)[0]
    P = prec[q]
    s2 = max(s2, 1e-300)
    # a ridge without a stated noise was set against the residual's own variance
    n2 = np.asarray(noise2, dtype=float)[q]
    v = np.where(n2 > 0, n2, s2) / P
    sv = np.sqrt(v)
    A = (sv[:, None] * (S - np.diag(P)) * sv[None, :]) / (c * s2) + np.eye(int(q.sum()))
    sign, logdet = np.linalg.slogdet(0.5 * (A + A.T))
    t = theta[q]
    return (float(logdet) if sign > 0 else 0.0) + float(np.sum(t * t / v))


def evidence(res: FitResult, data: FitData, n_eff: float, rss: float | None = None) -> float:
    """Return ``-2 log`` of the Laplace evidence of the model of ``res``, up to a constant.

    The noise profiled out over ``n_eff`` effective samples (``n_eff log(rss / n_eff)``)
    plus the :func:`occam` factor; without any prior in the model, the BIC. ``rss``: the
    model's parameters judged at another fit's residual (its look-alikes held, nested.
    earns_beside_lookalikes); default that of ``res``.
    """
    rss = res.rss if rss is None else rss
    return n_eff * float(np.log(rss / n_eff)) + occam(res, data, n_eff)


def effective_samples(res: FitResult, data: FitData) -> float:
    """Return a fit's independent samples: its residual's size over the correlation inflation."""
    return res.residual_nT.size / inflation(res.residual_nT, data.t_s)


def evidence_change(after: FitResult, before: FitResult, data: FitData) -> float:
    """:func:`evidence` of ``after`` minus that of ``before``, with ``after``'s sample count.

    The change a step of the search makes (a term added, refined or dropped), counted with the
    effective samples of the model it arrives at (``delta_bic`` in the findings).
    """
    n = effective_samples(after, data)
    return evidence(after, data, n) - evidence(before, data, n)


def evidence_between(a: FitResult, b: FitResult, data: FitData) -> float:
    """:func:`evidence` of fit ``a`` minus that of ``b``, both with one effective sample count.

    Each candidate's evidence is discounted by the correlation of its own residual; two
    candidates are compared with the smaller of their two counts (the conservative one), so
    the difference measures their fits and their Occam factors, not their residuals'
    texture.
    """
    n = min(effective_samples(a, data), effective_samples(b, data))
    return evidence(a, data, n) - evidence(b, data, n)


def rest_score_test(kind: EffectKind) -> Callable[[FitResult, FitData, float], ScoreTest]:
    """Return the score test of what a ``kind`` term adds beside the effect it shares with.

    A term that shares a direction with another effect
    (:attr:`~pipeline.model.effects.base.Effect.shares_with`: the isotropic part of
    ``E_s`` is a time offset's, ``E_s = -tau I`` to first order) has, with that effect in the
    model, only the directions it keeps
    (:meth:`~pipeline.model.effects.base.Effect.kept_basis`: for an eddy term the 8 traceless
    ones, :meth:`~stages.diagnose.model.ModelState.gauged`); so the nested simpler term keeps
    what it explains and the term is admitted only for what it cannot. ``k``: the kept
    directions, its free parameters there.
    """
    basis = EFFECTS[kind].kept_basis()

    def test(cur: FitResult, data: FitData, sigma: float) -> ScoreTest:
        term = Term(kind)
        ev = evaluate(cur.state.with_term(term), data)
        J = ev.jac if ev.sqrt_w is None else ev.jac * ev.sqrt_w[:, None, None]  # as residual
        J = J.reshape(-1, J.shape[-1])
        p0 = cur.state.n_params()
        Jt = np.concatenate([J[:, :p0], J[:, p0:] @ basis.T], axis=1)
        return dataclasses.replace(score_from_J(cur, term, Jt, data, sigma), k=len(basis),
                                   penalty=len(basis) * float(np.log(J.shape[0])))

    return test


#: Directions of the information kept by the covariance: eigenvalues of the information
#: scaled to a unit diagonal (:func:`~stages.estimators.base.solve_many_truncated`, Jacobi
#: scaling) above this fraction of the largest. Unscaled, the parameters' units (rad, nT,
#: nT/m, s) spread the diagonal over 12 orders or more, and a cut relative to the largest
#: dropped or kept a gradient's directions by the rounding of the sums; scaled, only the
#: directions the data do not determine fall under it.
INFORMATION_CUT = 1e-13


def param_covariance(res: FitResult, data: FitData) -> np.ndarray:
    """Parameter covariance: ``s^2 (J'J)^-1`` times the residual-correlation inflation."""
    P = res.info.shape[0]
    dof = max(res.residual_nT.size - P, 1)
    s2 = res.rss / dof * inflation(res.residual_nT, data.t_s)
    H = res.info.copy()
    if data.B_known_enu_nT is not None:
        H[3:6, :] = 0.0
        H[:, 3:6] = 0.0
        H[3:6, 3:6] = np.eye(3)
    kinds = [t.kind for t in res.state.terms]
    for kind in res.state.gauged():
        # held off the shared directions (canonical_rate_terms: tr(E_s) = 0): they belong to
        # the effect it shares them with (tau)
        o = res.state.offsets()[kinds.index(kind)]
        for d in EFFECTS[kind].shared_basis():
            a = np.zeros(P)
            a[o : o + len(d)] = d
            H = H + float(np.max(np.diag(H))) * np.outer(a, a)
    return s2 * solve_many_truncated(H, np.eye(P), INFORMATION_CUT)


def sigma_for(res: FitResult, i: int, cov: np.ndarray, data: FitData) -> dict[str, Any]:
    """Return the 1-sigma report of term ``i`` from the parameter covariance ``cov``."""
    term = res.state.terms[i]
    o = res.state.offsets()[i]
    blk = cov[o : o + term.n_params(), o : o + term.n_params()]
    return term_sigma(term, blk, res.state, data)

"""Terms the motion determines only in part: fit what it determines, hold and name the rest.

A ground survey tilts the sensor by a few degrees: a constant offset along the body's
vertical then reads the same as the vertical field, while the horizontal components turn
with the heading and are well determined (the same holds for the scale of the vertical axis
in the soft-iron matrix, which :data:`PARTIAL_KINDS` leaves out for now). Refusing the whole
term leaves the horizontal part to terms that can mimic it (a field drift along the lines,
offset steps in the calibration turns) and biases the rotation; fitting the whole term fits
the vertical part on model errors.

The combinations a recording determines come from the term's Fisher information with the
model's parameters profiled out (the Schur complement of :func:`stages.diagnose.statistics.
score_test`): generalised eigenvectors of that information against the term's own, each with
its efficiency (the fraction of its information the other parameters cannot mimic). Those
below :data:`~stages.diagnose.model.CONFOUND_RATIO` are held at their reference (zero: no
iron) and reported; the term is fitted along the orthogonal complement
(:meth:`stages.diagnose.model.Term.restricted`, Jacobian ``J_full A``). The held combinations
stay nuisance parameters of every later score test (``held`` of
:func:`~stages.diagnose.statistics.score_from_J`), so no other term is named for what they
could explain, and the rotation's sigma includes what one of typical size would do to it
(:func:`stages.diagnose.stage.with_undetermined_iron`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.core.geometry import matrix_to_quat, quat_to_matrix, so3_exp
from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects import IRON_PRIOR
from pipeline.model.effects.base import CONFOUND_RATIO
from pipeline.model.solve import gram
from stages.diagnose.fit import FitResult
from stages.diagnose.model import (
    F64,
    AttitudeTrack,
    FitData,
    ModelState,
    Term,
    evaluate,
    held_directions,
)
from stages.diagnose.statistics import ScoreTest, inflation, robust_sigma, score_test

#: Terms that may be fitted in part. Iron has a natural reference for what the motion cannot
#: determine (no iron), and the rotation's sigma already carries a prior for it
#: (:data:`~pipeline.model.effects.IRON_PRIOR`); a drift or an eddy term held at zero along
#: some combinations would be a different effect, not a part of one. Soft iron works the same
#: way (a survey's held combination is the scale of mag z against x and y) but is left out
#: until its effect on the real recordings is checked: on lab_01 it would add a soft iron of
#: 1.3 % scale differences, unlike the 0.4 % the same sensor's other recordings determine.
PARTIAL_KINDS = frozenset({EffectKind.HARD_IRON})

#: A term is fitted in part only when the motion determines at least this fraction of its
#: combinations. A term the motion leaves mostly undetermined (a line that barely turns: two
#: of soft iron's five) is better refused whole: its few fitted combinations would take up
#: whatever else the model lacks, and the rotation's sigma covers it as left out.
MIN_DETERMINED_FRACTION = 0.5

#: Most samples used to find the combinations and the tilt that would determine them: the
#: efficiencies are ratios of sums over the motion, which a decimated track keeps.
_MAX_SAMPLES = 3000


def _decimated(data: FitData) -> FitData:
    step = max(1, int(np.ceil(len(data) / _MAX_SAMPLES)))
    if step == 1:
        return data
    return data.subset(np.arange(len(data)) % step == 0)


def _weighted(ev_J: F64, sqrt_w: F64 | None) -> F64:
    J = ev_J if sqrt_w is None else ev_J * sqrt_w[:, None, None]
    return J.reshape(-1, J.shape[-1])


def _base_columns(state: ModelState, J: F64, data: FitData) -> F64:
    """Return the fitted columns of ``J`` (3N, P): without ``B_enu`` when the field is given."""
    p0 = state.n_params()
    keep = np.r_[0:3, 6:p0] if data.B_known_enu_nT is not None else np.arange(p0)
    return J[:, keep]


def _regression(Jb: F64, Jc: F64) -> F64:
    """Coefficients ``C`` (P, k) of ``Jc`` on ``Jb``: ``Hbb^-1 Hbc``, solved Jacobi-scaled.

    ``Jc - Jb C`` are the term's columns with every other parameter profiled out.
    """
    Hbb = gram(Jb, Jb)
    sb = np.sqrt(np.clip(np.diag(Hbb), 1e-30, None))
    B = np.linalg.lstsq(Hbb / np.outer(sb, sb) + 1e-12 * np.eye(len(sb)),
                        gram(Jb, Jc) / sb[:, None], rcond=None)[0]
    return B / sb[:, None]


def _efficiencies(Jb: F64, Jc: F64) -> tuple[F64, F64]:
    """Efficiencies (k,) ascending and their directions (k, k) in the term's parameters.

    Generalised eigenproblem ``I_eff x = e H_cc x``: ``H_cc = Jc'Jc`` the term's own
    information, ``I_eff = H_cc - H_cb H_bb^-1 H_bc`` what is left with the columns ``Jb``
    free. Columns of the directions have unit length.
    """
    Hcc = gram(Jc, Jc)
    Ieff = Hcc - gram(Jb, Jc).T @ _regression(Jb, Jc)
    sc = np.sqrt(np.clip(np.diag(Hcc), 1e-30, None))
    In = 0.5 * (Ieff + Ieff.T) / np.outer(sc, sc)
    Hn = 0.5 * (Hcc + Hcc.T) / np.outer(sc, sc)
    Li = np.linalg.inv(np.linalg.cholesky(Hn + 1e-12 * np.eye(len(sc))))
    e, E = np.linalg.eigh(Li @ In @ Li.T)
    X = (Li.T @ E) / sc[:, None]
    return e, X / np.linalg.norm(X, axis=0)


def combination_sigmas(eff: F64, own: F64, info_per_unit: float) -> F64:
    """Return each combination's data sigma (the term's units) with the other terms free.

    ``eff``: the combinations' efficiencies; ``own``: their own information ``x' H_cc x``
    (``x`` of unit length) in units of a decimated Gram. The generalised eigenvectors of
    :func:`_efficiencies` are uncorrelated under ``I_eff``, so each coefficient has
    information ``e x' H_cc x``, times ``info_per_unit`` (:func:`_info_per_unit`).
    """
    return 1.0 / np.sqrt(np.clip(eff * own * info_per_unit, 1e-300, None))


def _info_per_unit(cur: FitResult, data: FitData, sub: FitData, sigma: float) -> float:
    """Information per unit of a Gram over ``sub``: ``(N / N_sub) / (sigma^2 inflation)``."""
    return len(data) / len(sub) / (sigma**2 * inflation(cur.residual_nT, data.t_s))


#: Blocks of the sandwich sigma (:func:`sandwich_sigmas`): as long as the recording allows
#: with this many of them, so that the variance it estimates has about as many degrees of
#: freedom (a relative error of about 1 / sqrt(2 * 20), 16 %).
SANDWICH_BLOCKS = 20


def sandwich_sigmas(Jb: F64, Jc: F64, X: F64, r: F64, t_s: F64) -> F64:
    """Return each combination's sigma from the residual itself, correlation of any length.

    The coefficient along ``x_k`` is estimated from the efficient score ``x_k' Jr' r``,
    ``Jr = Jc - Jb Hbb^-1 Hbc`` (the combination's columns with every other parameter
    profiled out). Its variance is the variance of that score over the information squared
    (the sandwich, Huber 1967; White 1980), the score's variance summed over time blocks
    (:data:`SANDWICH_BLOCKS`) so that a residual correlated over seconds counts as what it
    is. ``r``: the weighted residual (3N,) with the candidate fitted (projected off
    ``[Jb, Jc]``), so its own signal does not count as noise.
    """
    A = np.concatenate([Jb, Jc], axis=1)
    sa = np.linalg.norm(A, axis=0)
    As = A / np.where(sa > 0, sa, 1.0)
    rp = r - As @ np.linalg.lstsq(As, r, rcond=None)[0]
    Jr = (Jc - Jb @ _regression(Jb, Jc)) @ X
    t = np.repeat(t_s - t_s[0], 3)
    span = max(float(t[-1]), 1e-9)
    blocks = np.minimum((t * SANDWICH_BLOCKS / span).astype(np.int64), SANDWICH_BLOCKS - 1)
    score = np.zeros((SANDWICH_BLOCKS, Jr.shape[1]))
    np.add.at(score, blocks, Jr * rp[:, None])
    info = np.sum(Jr * Jr, axis=0)
    return np.sqrt(np.sum(score * score, axis=0)) / np.clip(info, 1e-300, None)


def partial_candidate(cur: FitResult, term: Term, data: FitData, sigma: float
                      ) -> ScoreTest | None:
    """Score test of ``term`` fitted along every combination the recording determines.

    A combination is undetermined when the data know it less well than the effect's prior
    does: its data sigma, with every other parameter free, exceeds
    :data:`~pipeline.model.effects.IRON_PRIOR` (MacKay 1992: the evidence gains nothing from
    a parameter whose posterior is its prior). The sigma is the larger of the noise model's
    (:func:`combination_sigmas`) and the residual's own (:func:`sandwich_sigmas`): a lab's
    residual correlated over seconds (the unmodelled field of a room) pulls a confounded
    combination far more than its noise says. Its efficiency must also be below
    :data:`CONFOUND_RATIO`: a combination that is only noisy, not confounded, is fitted and
    carries its sigma. A ratio alone is not the test: a combination the other terms mimic
    to 0.3 % may still be known to a thirtieth of its prior on a long, quiet recording (a
    survey's vertical offset of 500 nT fitted as 486 +- 17 nT), and holding it leaves its
    signature in the residual for other terms to take up.

    The undetermined combinations are held at zero and the term is restricted to the
    orthogonal complement; with none, the term is tested whole.

    Returns
    -------
    ScoreTest or None
        The test of the (restricted) term (``.term`` is it), or None when the recording
        determines less than :data:`MIN_DETERMINED_FRACTION` of its combinations.

    """
    if term.kind not in PARTIAL_KINDS or term.partial:
        return None
    ev = evaluate(cur.state.with_term(term), data)
    J = _weighted(ev.jac, ev.sqrt_w)
    p0 = cur.state.n_params()
    Jb = _base_columns(cur.state, J, data)
    if ev.J_held is not None:  # what partial terms already hold stays free
        Jb = np.concatenate([Jb, _weighted(ev.J_held, ev.sqrt_w)], axis=1)
    Jc = J[:, p0:]
    eff, X = _efficiencies(Jb, Jc)
    own = np.einsum("ik,ij,jk->k", X, gram(Jc, Jc), X)
    r = data.y_nT - ev.y_nT
    r = (r if ev.sqrt_w is None else r * ev.sqrt_w[:, None]).reshape(-1)
    sig = np.maximum(combination_sigmas(eff, own, _info_per_unit(cur, data, data, sigma)),
                     sandwich_sigmas(Jb, Jc, X, r, data.t_s))
    weak = (eff < CONFOUND_RATIO) & (sig > IRON_PRIOR[term.kind.value])
    k, n_held = len(eff), int(np.count_nonzero(weak))
    if n_held == 0:
        return score_test(cur, term, data, sigma)
    if k - n_held < MIN_DETERMINED_FRACTION * k:
        return None
    # hold the undetermined combinations; fit along what is orthogonal to them
    U = np.linalg.qr(X[:, weak])[0]
    A = np.linalg.svd(np.eye(k) - U @ U.T)[0][:, : k - n_held]
    return score_test(cur, term.restricted(A), data, sigma)


def _up_axis_body(track: AttitudeTrack) -> F64:
    """Return the body axis (3,) that points up on average over the track, unit length."""
    C = quat_to_matrix(track.q_enu_body)
    a = np.mean(C[:, 2, :], axis=0)  # rows C.T e_up: ENU up in the body frame
    n = float(np.linalg.norm(a))
    return a / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])


def _tilts_rad(track: AttitudeTrack) -> tuple[F64, F64]:
    """Tilt of each attitude sample from its level pose: angles (M,) rad, axes (M, 3) ENU.

    The level pose keeps the heading and turns the body's mean up axis
    (:func:`_up_axis_body`) to ENU up; the tilt turns it from there to where it points.
    """
    C = quat_to_matrix(track.q_enu_body)
    v = C @ _up_axis_body(track)  # the body's up axis in ENU, (M, 3)
    n = np.cross(np.array([0.0, 0.0, 1.0]), v)
    s = np.linalg.norm(n, axis=1)
    theta = np.arctan2(s, v[:, 2])
    axis = np.where(s[:, None] > 1e-12, n / np.maximum(s, 1e-12)[:, None], 0.0)
    return theta, axis


def tilted(data: FitData, factor: float) -> FitData:
    """Return ``data`` with every attitude's tilt from level times ``factor``, heading kept.

    ``C' = Rot(n, (factor - 1) theta) C`` with ``theta``, ``n`` the sample's tilt
    (:func:`_tilts_rad`); the readings are unchanged (only the model's Jacobian is used).
    """
    theta, axis = _tilts_rad(data.track)
    C = quat_to_matrix(data.track.q_enu_body)
    Cn = so3_exp(axis * ((factor - 1.0) * theta)[:, None]) @ C
    track = AttitudeTrack(data.track.t_s, matrix_to_quat(Cn), lam=data.track.lam)
    return dataclasses.replace(data, track=track, interp_error_nT=None)


def _held_efficiency(state: ModelState, i: int, data: FitData) -> tuple[F64, F64, F64]:
    """Efficiency (Q,) of each held combination of term ``i``, its columns and the base's.

    Each held column's information left with every fitted parameter (and the other held
    combinations) free, over its own.
    """
    ev = evaluate(state, data)
    J = _weighted(ev.jac, ev.sqrt_w)
    assert ev.J_held is not None  # term i is partial
    H = _weighted(ev.J_held, ev.sqrt_w)
    j0 = sum(t.full_size() - t.n_params() for t in state.terms[:i])
    q = state.terms[i].full_size() - state.terms[i].n_params()
    Jb = _base_columns(state, J, data)
    out = np.zeros(q)
    for c in range(q):
        others = np.delete(H, j0 + c, axis=1)
        out[c] = _efficiencies(np.concatenate([Jb, others], axis=1), H[:, [j0 + c]])[0][0]
    return out, H[:, j0 : j0 + q], Jb


#: Tilt factors tried for the tilt that would determine a held combination.
_TILT_FACTORS = np.geomspace(1.0, 30.0, 25)


def tilt_to_determine_deg(state: ModelState, i: int, data: FitData, info_per_unit: float
                          ) -> float | None:
    """Largest tilt from level (deg) that would determine every held combination of term ``i``.

    The recording's attitudes are tilted further (:func:`tilted`, the heading kept) until
    every held combination is determined as :func:`partial_candidate` judges it: its data
    sigma at most the prior, or its efficiency at least :data:`CONFOUND_RATIO`. The answer is
    the largest tilt of that motion, interpolated on a log scale of the sigma between the
    factors tried. None when a tilt of 90 deg would not do (the combination needs turns
    about other axes).

    ``info_per_unit``: the information one unit of the decimated Gram stands for
    (:func:`_info_per_unit`).
    """
    sub = _decimated(data)
    top = float(np.max(_tilts_rad(sub.track)[0]))
    prior = IRON_PRIOR[state.terms[i].kind.value]
    if top <= 0:
        return None

    def shortfall(f: float) -> float:
        """How far the worst held combination is from determined (<= 1: it is)."""
        eff, H, _ = _held_efficiency(state, i, tilted(sub, f))
        sig = combination_sigmas(eff, np.sum(H * H, axis=0), info_per_unit)
        return float(np.max(np.where(eff >= CONFOUND_RATIO, 0.0, sig / prior)))

    prev: tuple[float, float] | None = None
    for f in _TILT_FACTORS:
        if f * top > 0.5 * np.pi:
            return None
        g = shortfall(float(f))
        if g <= 1.0:
            if prev is None:
                return float(np.degrees(top))
            f0, g0 = prev
            a = np.log(g0) / np.log(g0 / g) if g0 > 1.0 and g > 0 else 1.0
            return float(np.degrees(top) * f0 * (f / f0) ** a)
        prev = (float(f), g)
    return None


def _size(x: float) -> str:
    """Return a sigma in words: three significant figures, or "more than 1e6"."""
    return f"{x:.3g}" if x < 1e6 else "more than 1e6"


def _vec(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{float(x) + 0.0:.2f}" for x in v) + ")"


def _mat(M: np.ndarray) -> str:
    return "[" + ", ".join(_vec(r) for r in M) + "]"


def held_words(res: FitResult, i: int, data: FitData) -> str:
    """Words on what a partial term holds: which part, why, and what motion would determine it.

    For each held combination of ``hard_iron``: its direction in the mag and body frames,
    named after the body's mean up axis when it lies along it or across it; what the
    rest of the model does in its place (the regression of its column on the fitted ones:
    the field's Up component, its horizontal part, or the misalignment); the value it is held
    at and its prior sigma; and the tilt from level that would determine it
    (:func:`tilt_to_determine_deg`).

    Parameters
    ----------
    res : FitResult
        The final fit.
    i : int
        Index of the term in ``res.state.terms``.
    data : FitData
        The fitted samples.

    Returns
    -------
    str
        A clause to append to the finding's explanation ("" for a full term).

    """
    st = res.state
    term = st.terms[i]
    if not term.partial:
        return ""
    sub = _decimated(data)
    eff, H, Jb = _held_efficiency(st, i, sub)
    per_unit = _info_per_unit(res, data, sub, robust_sigma(res.residual_nT))
    data_sig = combination_sigmas(eff, np.sum(H * H, axis=0), per_unit)
    U = term.undetermined()
    up = _up_axis_body(sub.track)
    top = float(np.degrees(np.max(_tilts_rad(sub.track)[0])))
    offset = term.kind is EffectKind.HARD_IRON
    parts = []
    for c in range(U.shape[1]):
        u = U[:, c]
        beta = np.linalg.lstsq(Jb, H[:, c], rcond=None)[0]
        if offset:
            d = st.R_body_mag @ u
            along = float(abs(d @ up))
            where = ("along the body's vertical" if along > 0.95 else
                     "in the body's horizontal plane" if along < 0.3 else "")
            what = (f"its component {where + ' ' if where else ''}(mag-frame direction "
                    f"{_vec(u)}, body {_vec(d)})")
        elif term.kind is EffectKind.SOFT_IRON:
            M = np.asarray(held_directions(term)[c])
            zz = abs(M[2, 2]) > 0.75  # diag(1, 1, -2) / sqrt 6 has 0.82 there
            what = ("the scale of the mag z axis against x and y" if zz else
                    "a change of the soft-iron matrix") + (
                f" (D along {_mat(M)}, unit norm)")
        else:
            what = f"the combination {_vec(u)} of its parameters"
        mim = "the misalignment and the other terms"
        if data.B_known_enu_nT is None:
            b = beta[3:6]  # the field change (ENU, nT per unit) that reads the same
            nb = float(np.linalg.norm(b))
            if nb > 0.5 and abs(b[2]) > 0.9 * nb:
                mim = "the vertical field"
            elif nb > 0.5 and abs(b[2]) < 0.3 * nb:
                mim = "the horizontal field"
            elif nb > 0.5:
                mim = f"the field along ENU {_vec(b / nb)}"
        held = float(u @ term.null_value())
        prior = IRON_PRIOR.get(term.kind.value)
        unit = " nT" if offset else ""
        parts.append(
            f"{what} is not determined: it adds to {mim} (only {eff[c]:.1e} of it is "
            f"independent of the other terms, which leaves it a sigma of "
            f"{_size(data_sig[c])}{unit} from the data), so it is held at {held:g}{unit}"
            + (f" with the prior's sigma, {prior:g}{unit}" if prior else ""))
    need = tilt_to_determine_deg(st, i, data, per_unit)
    if need is not None:
        how = (f"tilting the platform by more than {np.ceil(need):.0f} deg (this recording "
               f"tilts it by up to {top:.0f} deg) would determine it")
    else:
        how = ("tilting alone would not determine it: turn the platform through large angles "
               "about all three axes")
    if data.B_known_enu_nT is None:
        how += ", and so would a reference field (--reference-field)"
    name = {EffectKind.HARD_IRON: "offset", EffectKind.SOFT_IRON: "soft-iron matrix"}.get(
        term.kind, "term")
    return f". Only part of the {name} is determined: " + "; ".join(parts) + "; " + how

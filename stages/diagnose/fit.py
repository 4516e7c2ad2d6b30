"""The diagnosis fit.

A model state fitted to the data by THE damped Gauss-Newton core
(``fit``, ``FitResult``) from a closed-form start (``wahba_init``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pipeline.core.geometry import quat_to_matrix, rows_times, so3_exp
from pipeline.core.vocabulary import EffectKind
from pipeline.model.solve import (
    Linearised,
    Solution,
    levenberg_marquardt,
    minimise,
    normal_equations,
)
from stages.diagnose.model import (
    F64,
    FitData,
    ModelState,
    evaluate,
    row_spans,
    sample_weights,
)


@dataclass(frozen=True)
class FitResult:
    """A Levenberg-Marquardt fit.

    Attributes
    ----------
    state : ModelState
    residual_nT : ndarray (N, 3)
        ``sqrt(w) (y - prediction)`` on the fitted samples (``w``: :func:`sample_weights`,
        1 without a noise model).
    rss : float
        Weighted residual sum of squares, nT^2.
    info : ndarray (P, P)
        ``J.T W J`` at the solution (unscaled information).
    n_iter : int
    raw_residual_nT : ndarray (N, 3) or None
        ``y - prediction`` unweighted (None: the same as ``residual_nT``).
    noise_model : (float, float, float) or None
        ``FitData.noise_model`` the fit was weighted with.

    """

    state: ModelState
    residual_nT: F64
    rss: float
    info: F64
    n_iter: int
    raw_residual_nT: F64 | None = None
    noise_model: tuple[float, float, float] | None = None

    @property
    def rms_nT(self) -> float:
        """RMS of the (unweighted) residual over all components, nT."""
        r = self.residual_nT if self.raw_residual_nT is None else self.raw_residual_nT
        return float(np.sqrt(np.sum(r * r) / max(r.size, 1)))


#: A fit has converged when an accepted step lowers the sum of squares by less than this many
#: samples' variance (a thousandth of one chi-square unit): near the minimum Gauss-Newton's
#: next steps gain less still, so every parameter is within a few hundredths of its sigma of
#: the optimum, far inside what any sigma, evidence margin or held-out test resolves.
CONVERGED_CHI2 = 1e-3


def fit(
    state: ModelState, data: FitData, *, max_iter: int = 40, rtol: float | None = None,
    final_information: bool = True,
) -> FitResult:
    """Levenberg-Marquardt over every parameter of ``state`` (rotations on SO(3)).

    Parameters
    ----------
    state : ModelState
        Starting values; also fixes which terms are in the model.
    data : FitData
        What to fit.
    max_iter : int
        Iteration limit.
    rtol : float, optional
        Stop when the relative decrease of the RSS falls below this; default
        :data:`CONVERGED_CHI2` over the number of residuals (the RSS is about that many
        samples' variance).
    final_information : bool
        False: ``info`` is that of the last step's start, not formed again at the solution
        (one Jacobian less, for a fit whose state alone is used: a held-out fold's); the
        state, residual and RSS are the same.

    Returns
    -------
    FitResult

    """
    if rtol is None:
        rtol = CONVERGED_CHI2 / max(3 * len(data), 1)
    fixed_B = data.B_known_enu_nT is not None
    if fixed_B:
        state = replace(state, B_enu_nT=np.asarray(data.B_known_enu_nT, dtype=float))

    def resid(st: ModelState, with_jacobian: bool) -> tuple[F64, F64 | None]:
        ev = evaluate(st, data, jacobian=with_jacobian)
        r, J = data.y_nT - ev.y_nT, ev.J
        if ev.sqrt_w is not None:  # the likelihood's weights (sample_weights)
            if J is not None:
                J *= ev.sqrt_w[:, None, None]  # J is this evaluation's own array
                i = _tau_index(st)
                if i is not None:
                    J[:, :, i] -= _sqrt_weight_rate(data, st.tau_s())[:, None] * r
            r = r * ev.sqrt_w[:, None]
        return r, J

    def update(st: ModelState, dx: F64) -> ModelState:
        return st.update(dx, fixed_B=fixed_B)

    def spans(st: ModelState) -> tuple[tuple[int, int, int, int], ...]:
        return row_spans(st, data.t_s)

    prec = state.prior_precision()
    if prec is None:
        sol = levenberg_marquardt(state, resid, update, max_iter=max_iter, rtol=rtol,
                                  row_spans=spans, relinearise_last=final_information)
    else:
        # the weights enter linearly: a relative decrease of 1e-8 is converged well within
        # the noise, and each iteration costs the map's columns squared
        sol = _fit_with_prior(state, resid, update, prec, max_iter, max(rtol, 1e-8), spans,
                              final_information)
    raw = None
    if data.noise_model is not None:
        raw = data.y_nT - evaluate(sol.state, data, jacobian=False).y_nT
    return FitResult(sol.state, sol.residual, sol.rss, sol.info, sol.n_iter, raw,
                     data.noise_model)


def _tau_index(state: ModelState) -> int | None:
    """Index of the time offset in the parameter vector, or None without one."""
    for t, o in zip(state.terms, state.offsets(), strict=True):
        if t.kind is EffectKind.TIME_OFFSET:
            return o if t.n_params() else None  # held: no column of its own
    return None


def _sqrt_weight_rate(data: FitData, tau_s: float) -> F64:
    """``d sqrt(w) / d tau`` (N,) of :func:`~stages.diagnose.model.sample_weights`, per s.

    The weights follow where ``t - tau`` falls between attitude samples, so the weighted
    residual ``r_w = sqrt(w(tau)) (y - f(tau))`` depends on tau through them too:
    ``d r_w / d tau = -sqrt(w) f' + (d sqrt(w) / d tau) (y - f)``. Without the second part
    the fit stops where ``sum w r f' = 0``, and the attitude noise the prediction reads
    correlates with its own rate where the samples fall at one place between attitude
    samples (rates in a ratio of small integers): ``E[n n'] = sigma^2 f'(s) / (2 dt)``
    with ``f(s)`` the interpolated noise factor. The lag then moves towards where that noise
    is smallest. With it, the fit minimises the weighted sum of squares itself, whose
    expectation does not depend on where the samples fall (the weights' purpose). Central
    difference over a microsecond, within one interval of the polynomial ``f``.
    """
    h = 1e-6
    wp = sample_weights(data, tau_s + h)
    wm = sample_weights(data, tau_s - h)
    if wp is None or wm is None:
        return np.zeros(len(data))
    return (np.sqrt(wp) - np.sqrt(wm)) / (2.0 * h)


def _fit_with_prior(state: ModelState, resid: Any, update: Any, prec: F64, max_iter: int,
                    rtol: float, spans: Any, relinearise_last: bool = True) -> Solution:
    """Run the damped Gauss-Newton fit of ``|r|^2 + sum_i prec_i x_i^2`` (a ``field_map``'s prior).

    The ridge is the GP prior of the map's weights (:meth:`ModelState.prior_precision`): it
    makes the fit well posed where the path leaves combinations of the basis unobserved.
    The normal equations returned are the posterior's (``J.T J + diag(prec)``), the RSS
    the data's alone (the evidence and held-out errors compare fits of the data).
    """

    def linearise(st: ModelState, with_normal: bool) -> Linearised:
        x = st.flat_values()
        pen = float(np.sum(prec * x * x))
        r, J = resid(st, with_normal)
        if not with_normal:
            return Linearised(float(np.sum(r * r)) + pen, aux=r)
        assert J is not None
        H, g = normal_equations(J, r, spans(st))
        return Linearised(float(np.sum(r * r)) + pen, H + np.diag(prec), g - prec * x, r)

    m = minimise(state, linearise, update, max_iter=max_iter, rtol=rtol,
                 relinearise_last=relinearise_last)
    r = m.at.aux
    assert m.at.H is not None  # at the last state, or the last step's start
    return Solution(m.state, r, float(np.sum(r * r)), m.at.H, m.n_iter)


def wahba_init(data: FitData, n_iter: int = 10) -> ModelState:
    """Baseline ``R_body_mag`` and ``B_enu`` without any prior: alternating Wahba / mean field.

    ``C_enu_body(t) R y(t) = B`` for every sample when the model holds, so for a given ``R``
    the field is the mean of the rotated readings, and for a given field ``R`` solves
    Wahba's problem between the readings (mag) and the field in the body frame. Several
    starting rotations guard against a poor local minimum.
    """
    q = data.track.at(data.t_s)
    C = quat_to_matrix(q)
    y = data.y_nT - np.mean(data.y_nT, axis=0) * 0.0
    best: tuple[float, F64, F64] | None = None
    starts = [np.eye(3)] + [so3_exp(np.array(v) * np.pi / 2) for v in
                            ([1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1])]
    starts += [so3_exp(np.array([np.pi, 0, 0])), so3_exp(np.array([0, np.pi, 0]))]
    for R in starts:
        B = data.B_known_enu_nT
        for _ in range(n_iter):
            if data.B_known_enu_nT is None:
                B = np.mean(rows_times(C, y @ R.T), axis=0)
            assert B is not None  # known, or the mean just computed
            b = B @ C  # rows C.T @ B
            # Wahba: R = argmin sum |b - R y|^2 (Kabsch)
            Hm = b.T @ y
            U, _, Vt = np.linalg.svd(Hm)
            Sd = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
            R = U @ Sd @ Vt
        assert B is not None, "wahba_init needs n_iter >= 1 without a known field"
        b = B @ C
        cost = float(np.sum((y - b @ R) ** 2))
        if best is None or cost < best[0]:
            best = (cost, R, np.asarray(B, dtype=float))
    assert best is not None
    return ModelState(R_body_mag=best[1], B_enu_nT=best[2])

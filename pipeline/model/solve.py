"""THE damped Gauss-Newton (Levenberg-Marquardt) core of every fit of the model.

More in docs/modules.md, ``pipeline.model.solve``.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import ThreadpoolController

F64 = NDArray[np.float64]


@functools.cache
def _blas_controller() -> Any:
    """Return the process' BLAS libraries as threadpoolctl sees them (scanned on first use)."""
    return ThreadpoolController()


def blas_threads() -> int:
    """Return the most threads this process's BLAS may use (0 when none is loaded).

    The cores the process may use, as its executor set them (:mod:`pipeline.model.parallel`).
    """
    return max((int(i["num_threads"]) for i in _blas_controller().info()
                if i.get("user_api") == "blas"), default=0)


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """Run the block with BLAS and LAPACK on one thread (restored on exit).

    On a loaded machine a threaded BLAS call for the products and factorizations of a fit
    can stall for tenths of a second (threads spinning for cores others hold); one thread is
    predictable. Changing the limit costs microseconds.
    """
    with _blas_controller().limit(limits=1, user_api="blas"):
        yield


def gram(A: F64, B: F64) -> F64:
    """``A.T @ B`` for tall matrices, on one BLAS thread (:func:`one_blas_thread`).

    BLAS rather than einsum's loop: for the diagnosis' Jacobians (3N, P) with P in the
    hundreds (a step's transitions, a field map) einsum is several times slower.
    """
    with one_blas_thread():
        return cast(F64, A.T @ B)


#: Columns ``[i, j)`` of a Jacobian (N, 3, P) that are zero outside samples ``[a, b)``
RowSpans = Sequence[tuple[int, int, int, int]]


def normal_equations(J: F64, r: F64, spans: RowSpans = ()) -> tuple[F64, F64]:
    """``J.T J`` and ``J.T r`` for J (N, 3, P) and r (N, 3).

    ``spans``: columns that act only in a window of samples (a transition, a disturbance's
    knots: :meth:`pipeline.model.effects.base.Effect.column_windows`), each ``(i, j, a, b)``
    once. Their products are summed over their own samples, where the rest of J meets
    them: the same sums without their zero terms. A Jacobian of a step's transitions and
    a disturbance's knots is mostly such columns (docs/performance.md).
    """
    P = J.shape[-1]
    Jf = J.reshape(-1, P)
    rf = r.reshape(-1)
    if not spans:
        return gram(Jf, Jf), gram(Jf, rf[:, None])[:, 0]
    windowed = np.zeros(P, dtype=bool)
    for i, j, _, _ in spans:
        windowed[i:j] = True
    dense, local = np.flatnonzero(~windowed), np.flatnonzero(windowed)
    H = np.empty((P, P))
    g = np.empty(P)
    with one_blas_thread():
        Jd = Jf[:, dense]
        H[np.ix_(dense, dense)] = Jd.T @ Jd
        g[dense] = Jd.T @ rf
        for i, j, a, b in spans:
            rows = slice(3 * a, 3 * b)
            block = Jf[rows, i:j]
            H[i:j] = block.T @ Jf[rows]
            g[i:j] = block.T @ rf[rows]
    H[np.ix_(dense, local)] = H[np.ix_(local, dense)].T
    return np.triu(H) + np.triu(H, 1).T, g  # one value per pair, as syrk gives


@dataclass(frozen=True)
class Solution:
    """Where the iterations stopped.

    Attributes
    ----------
    state : Any
        The caller's state at the minimum found.
    residual : ndarray (N, 3)
        Residual at ``state``.
    rss : float
        Sum of squared residuals.
    info : ndarray (P, P)
        ``J.T J`` at ``state``.
    n_iter : int

    """

    state: Any
    residual: F64
    rss: float
    info: F64
    n_iter: int


@dataclass(frozen=True)
class Linearised:
    """The objective at one state, as :func:`minimise` needs it.

    Attributes
    ----------
    cost : float
        The objective (a sum of squares, possibly weighted).
    H, g : ndarray (P, P), (P,) or None
        Normal equations ``J.T W J`` and ``J.T W r`` (None when not asked for).
    aux : Any
        Whatever the caller wants back at the final state (e.g. the residual).

    """

    cost: float
    H: F64 | None = None
    g: F64 | None = None
    aux: Any = None


@dataclass(frozen=True)
class Minimum:
    """Where :func:`minimise` stopped: the state, its cost and ``aux``, the normal equations."""

    state: Any
    at: Linearised
    n_iter: int


def damped_solve(H: F64, g: F64, lam: float, scale: F64) -> F64:
    """Solve the Marquardt step ``(H + lam diag(scale)) dx = g``."""
    return cast(F64, np.linalg.solve(H + lam * np.diag(scale), g))


def minimise(
    state: Any,
    linearise: Callable[[Any, bool], Linearised],
    update: Callable[[Any, F64], Any],
    *,
    solve_step: Callable[[F64, F64, float, F64], F64] = damped_solve,
    converged: Callable[[Linearised, Linearised, F64], bool] | None = None,
    max_iter: int = 40,
    rtol: float = 1e-10,
    lam0: float = 1e-4,
    accept_rtol: float = 0.0,
    accept_atol: float = 0.0,
    max_tries: int = 12,
    relinearise_last: bool = True,
    lam_up: float = 5.0,
    lam_down: float = 4.0,
    lam_min: float = 1e-9,
) -> Minimum:
    """Minimise by damped Gauss-Newton (docs/modules.md): THE core every fit of the model runs.

    Parameters
    ----------
    state : Any
        Starting state.
    linearise : callable
        ``(state, with_normal_equations) -> Linearised``.
    update : callable
        ``(state, dx (P,)) -> state``.
    solve_step : callable
        ``(H, g, lam, scale) -> dx``; default :func:`damped_solve` (a caller with
        unobservable directions solves with a truncated pseudo-inverse instead).
    converged : callable or None
        ``(before, after, dx) -> bool``, asked after each accepted step (``before`` holds the
        normal equations the step was solved from, ``after`` the cost at the new state): a
        caller's own stopping rule, besides ``rtol``.
    max_iter, rtol, lam0 : int, float, float
        Iteration limit; stop when the relative decrease of the cost falls below ``rtol``;
        first damping.
    accept_rtol, accept_atol : float
        A step is accepted when its cost does not exceed ``(1 + accept_rtol) cost + accept_atol``
        (``cost`` the current one).
    max_tries : int
        Damping increases per iteration before giving up.
    relinearise_last : bool
        False: the normal equations returned are those the last step was solved from (at
        most a negligible step away), saving one linearisation at the final state.
    lam_up, lam_down, lam_min : float
        The damping schedule: times ``lam_up`` after a rejected step, divided by ``lam_down``
        (not below ``lam_min``) after an accepted one.

    """
    cur = _with_normal(linearise, state)
    lam = lam0
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (it is reported)
        H, g = cast(F64, cur.H), cast(F64, cur.g)
        d = np.diag(H).copy()
        scale = d + 1e-9 * max(float(np.max(d)), 1e-30)
        step_ok = False
        for _ in range(max_tries):
            try:
                dx = solve_step(H, g, lam, scale)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            cand = update(state, dx)
            at_cand = linearise(cand, False)
            c = at_cand.cost
            if np.isfinite(c) and c <= cur.cost * (1.0 + accept_rtol) + accept_atol:
                step_ok = True
                break
            lam *= lam_up
        if not step_ok:
            break
        rel = (cur.cost - c) / max(cur.cost, 1e-30)
        state, before = cand, cur
        lam = max(lam / lam_down, lam_min)
        stop = rel < rtol or (converged is not None and converged(before, at_cand, dx))
        if stop and not relinearise_last:
            cur = Linearised(c, before.H, before.g, at_cand.aux)
            break
        cur = _with_normal(linearise, state)
        if stop:
            break
    return Minimum(state, cur, it)


def _with_normal(linearise: Callable[[Any, bool], Linearised], state: Any) -> Linearised:
    """Return the objective with its normal equations at ``state``."""
    lin = linearise(state, True)
    if lin.H is None or lin.g is None:
        raise ValueError("linearise(state, True) returned no normal equations")
    return lin


def levenberg_marquardt(
    state: Any,
    residual_and_jacobian: Callable[[Any, bool], tuple[F64, F64 | None]],
    update: Callable[[Any, F64], Any],
    *,
    max_iter: int = 40,
    rtol: float = 1e-10,
    lam0: float = 1e-4,
    row_spans: Callable[[Any], RowSpans] | None = None,
    relinearise_last: bool = True,
) -> Solution:
    """:func:`minimise` on the unweighted sum of squares ``sum_i r_i.T r_i``.

    Parameters
    ----------
    state : Any
        Starting state.
    residual_and_jacobian : callable
        ``(state, with_jacobian) -> (r (N, 3), J (N, 3, P) or None)`` with ``r = y - f(x)``
        and ``J = df/dx`` (so the step ``dx`` solves ``J dx ~ r``).
    update : callable
        ``(state, dx (P,)) -> state``.
    max_iter : int
        Iteration limit.
    rtol : float
        Stop when the relative decrease of the cost falls below this.
    lam0 : float
        First damping.
    row_spans : callable, optional
        ``state -> spans`` of :func:`normal_equations`: the Jacobian's windowed columns.
    relinearise_last : bool
        As :func:`minimise`: False returns ``info`` of the last step's start, saving the
        Jacobian at the final state (for a caller that needs the state only).

    Returns
    -------
    Solution

    """

    def linearise(st: Any, with_normal: bool) -> Linearised:
        if not with_normal:
            r, _ = residual_and_jacobian(st, False)
            return Linearised(float(np.sum(r * r)), aux=r)
        r, J = residual_and_jacobian(st, True)
        if J is None:
            raise ValueError("residual_and_jacobian(state, True) returned no Jacobian")
        H, g = normal_equations(J, r, row_spans(st) if row_spans is not None else ())
        return Linearised(float(np.sum(r * r)), H, g, r)

    m = minimise(state, linearise, update, max_iter=max_iter, rtol=rtol, lam0=lam0,
                 relinearise_last=relinearise_last)
    return Solution(m.state, m.at.aux, m.at.cost, cast(F64, m.at.H), m.n_iter)

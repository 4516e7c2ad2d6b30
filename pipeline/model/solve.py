"""THE damped Gauss-Newton (Levenberg-Marquardt) core of every fit of the model.

Minimises ``sum_i r_i(x)^T r_i(x)`` over a state ``x`` that may live on a manifold (rotations
are updated by ``Exp``, the rest additively: the caller's ``update``). Each iteration solves
the damped normal equations (Marquardt 1963; Nocedal & Wright 2006, Sect. 10.3)::

    (J^T J + lambda diag(J^T J)) dx = J^T r

accepts ``dx`` when the cost does not increase (then ``lambda <- lambda / 4``), else
``lambda <- 5 lambda`` and tries again; stops when the relative decrease of the cost falls
below ``rtol`` or no step decreases it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def gram(A: F64, B: F64) -> F64:
    """``A.T @ B`` for tall matrices, without multi-threaded BLAS.

    On a loaded machine a threaded BLAS call for these small products can stall for tenths
    of a second (threads spinning for cores others hold); einsum's single-threaded loop is
    predictable and fast enough for (3N, P) with P up to ~50.
    """
    return np.einsum("np,nq->pq", A, B)


def normal_equations(J: F64, r: F64) -> tuple[F64, F64]:
    """``J.T J`` and ``J.T r`` for J (N, 3, P) and r (N, 3)."""
    Jf = J.reshape(-1, J.shape[-1])
    return gram(Jf, Jf), gram(Jf, r.reshape(-1, 1))[:, 0]


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


def levenberg_marquardt(
    state: Any,
    residual_and_jacobian: Callable[[Any, bool], tuple[F64, F64 | None]],
    update: Callable[[Any, F64], Any],
    *,
    max_iter: int = 40,
    rtol: float = 1e-10,
    lam0: float = 1e-4,
) -> Solution:
    """Damped Gauss-Newton from ``state`` (module docstring).

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

    Returns
    -------
    Solution

    """
    r, J = _with_jacobian(residual_and_jacobian, state)
    rss = float(np.sum(r * r))
    lam = lam0
    it = 0
    H, g = normal_equations(J, r)
    for it in range(1, max_iter + 1):  # noqa: B007 (it is reported)
        d = np.diag(H).copy()
        scale = d + 1e-9 * max(float(np.max(d)), 1e-30)
        step_ok = False
        for _ in range(12):
            try:
                dx = cast(F64, np.linalg.solve(H + lam * np.diag(scale), g))
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            cand = update(state, dx)
            r_c, _ = residual_and_jacobian(cand, False)
            rss_c = float(np.sum(r_c * r_c))
            if np.isfinite(rss_c) and rss_c <= rss:
                step_ok = True
                break
            lam *= 5.0
        if not step_ok:
            break
        rel = (rss - rss_c) / max(rss, 1e-30)
        state, rss = cand, rss_c
        lam = max(lam / 4.0, 1e-9)
        r, J = _with_jacobian(residual_and_jacobian, state)
        H, g = normal_equations(J, r)
        if rel < rtol:
            break
    return Solution(state, r, rss, H, it)


def _with_jacobian(
    residual_and_jacobian: Callable[[Any, bool], tuple[F64, F64 | None]], state: Any
) -> tuple[F64, F64]:
    """Residual and Jacobian at ``state`` (the Jacobian asked for must be there)."""
    r, J = residual_and_jacobian(state, True)
    if J is None:
        raise ValueError("residual_and_jacobian(state, True) returned no Jacobian")
    return r, J

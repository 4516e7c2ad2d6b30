"""Li et al. 2020, Section 3: misalignment from the measured and a virtual trajectory.

More in docs/modules.md, ``stages.estimators.li2020``.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np
from scipy.optimize import least_squares

from pipeline.core.geometry import skew
from pipeline.model.calibration import Calibration
from stages.estimators.base import (
    F64,
    EstimationProblem,
    analyse,
    canonical_axis,
    init_rotation,
    rotation_words,
    sigma_with_null,
    wahba,
)

MIN_STEP_DEG = 2.0
#: Median angle the measured trajectory turns through inside one smoothing window, deg.
SMOOTH_TURN_DEG = 30.0
_SG_ORDER = 3


class Tangents(enum.Enum):
    """How the derivatives behind the tangents and normals (Li 2020, Eqs. 10-13) are taken."""

    FINITE_DIFFERENCE = "finite_difference"
    SMOOTHED = "smoothed"


def cayley(s: F64) -> F64:
    """``R = (I - S)^-1 (I + S)`` with ``S = [s]x`` (Li 2020, Eq. 3)."""
    S = skew(s)
    eye = np.eye(3)
    return cast(F64, np.linalg.solve(eye - S, eye + S))


def cayley_derivatives(s: F64) -> F64:
    """``dR/ds_k`` of :func:`cayley`, shape (3, 3, 3) (``k`` first).

    From ``(I - S) R = I + S``: ``-dS R + (I - S) dR = dS``, so
    ``dR = (I - S)^-1 dS (I + R)``.
    """
    eye = np.eye(3)
    A = np.linalg.inv(eye - skew(s))
    return A @ skew(eye) @ (eye + cayley(s))


def _unit(x: F64) -> F64:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.where(n > 0, n, 1.0)


def stride_for(x: F64, min_step_deg: float = MIN_STEP_DEG) -> int:
    """Smallest stride ``k`` whose median angular step of the trajectory is >= min_step_deg."""
    u = _unit(x)
    n = len(u)
    k = 1
    while k < n // 4:
        c = np.clip(np.sum(u[k:] * u[:-k], 1), -1.0, 1.0)
        if np.degrees(np.median(np.arccos(c))) >= min_step_deg:
            break
        k *= 2
    return k


def derivative_operator(
    x: F64, method: Tangents
) -> tuple[Callable[[F64], tuple[F64, F64]], int, int]:
    """Return the linear operator giving first and second derivatives along a trajectory.

    The window (or stride) is chosen on the measured trajectory ``x`` (N, 3) and the returned
    function applies the same linear filter to any array whose first axis has length N (the
    readings, or the attitude matrices ``E`` (N, 3, 3)). Derivatives are per sample index
    (their scale does not matter: only directions are used).

    Returns
    -------
    function X -> (X1, X2)
        ``X1 ~ x'`` and ``X2 ~ x''``, both (M, ...); ``M = N - 2k`` for finite differences
        (inner points), ``M = N`` for the smoothed version.
    first : int
        Sample index of the first derivative row (``k``, or 0).
    half_width : int
        Samples on either side that enter one derivative (``k``, or half the window).

    """
    n = len(x)
    if method is Tangents.FINITE_DIFFERENCE:
        k = stride_for(x)

        def fd(X: F64) -> tuple[F64, F64]:
            # (x_{i+k} - x_{i-k}) / 2 and x_{i+k} - 2 x_i + x_{i-k}: the paper's chords, since
            # (x_i - x_{i-k}) x (x_{i+k} - x_i) = X1 x X2 exactly (Li 2020, Eqs. 10-13).
            return 0.5 * (X[2 * k :] - X[: -2 * k]), X[2 * k :] - 2.0 * X[k:-k] + X[: -2 * k]

        return fd, k, k
    k = stride_for(x, SMOOTH_TURN_DEG / 2.0)
    w = min(2 * k + 1, n if n % 2 else n - 1)
    w = max(w, _SG_ORDER + 2 if (_SG_ORDER + 2) % 2 else _SG_ORDER + 3)

    from scipy.signal import savgol_filter  # pipeline.core.warm.LATE_IMPORTS

    def sg(X: F64) -> tuple[F64, F64]:
        return (
            savgol_filter(X, w, _SG_ORDER, deriv=1, axis=0, mode="interp"),
            savgol_filter(X, w, _SG_ORDER, deriv=2, axis=0, mode="interp"),
        )

    return sg, 0, w // 2


def normals_tangents(x1: F64, x2: F64) -> tuple[F64, F64, F64]:
    """Return unit tangents ``unit(x')`` and normals ``unit(x' x x'')`` (Li 2020, Eqs. 10-13).

    Returns
    -------
    t, n : ndarray (M, 3)
    ok : ndarray (M,) bool
        Where ``x'`` and ``x''`` are not parallel (the normal is defined).

    """
    cr = np.cross(x1, x2)
    ok = np.linalg.norm(cr, axis=1) > 1e-9 * np.linalg.norm(x1, axis=1) * np.linalg.norm(x2, axis=1)
    return _unit(x1), _unit(cr), ok


def _unit_jac(a: F64) -> F64:
    """``d unit(a) / da = (I - u u^T) / |a|`` per row, (M, 3, 3)."""
    na = np.linalg.norm(a, axis=1)
    u = a / np.where(na > 0, na, 1.0)[:, None]
    P = np.eye(3) - u[:, :, None] * u[:, None, :]
    return P / np.where(na > 0, na, 1.0)[:, None, None]


@dataclass(frozen=True)
class Li2020Estimator:
    """The method of Li et al. 2020, Section 3 (docs/modules.md for our choices).

    Attributes
    ----------
    tangents : Tangents
        Derivatives from a local cubic fit (default) or the paper's raw chords.
    max_nfev : int
        Cap on the Levenberg-Marquardt function evaluations.

    """

    name: str = "li2020"
    tangents: Tangents = Tangents.SMOOTHED
    max_nfev: int = 100

    def fit(self, p: EstimationProblem) -> Calibration:
        """Estimate ``R_body_mag`` (and the virtual vector ``V`` when no field is given)."""
        m = p.mag_nT
        C = p.C_enu_body
        E = np.swapaxes(C, 1, 2)  # Li 2020, Eq. 7: E = C_body_enu
        ref = p.reference_field_enu_nT
        R_w, V0 = init_rotation(m, C, ref)
        deriv, first, half = derivative_operator(m, self.tangents)
        m1, m2 = deriv(m)
        tm, nm, ok_m = normals_tangents(m1, m2)
        E1, E2 = deriv(E)  # the same linear filter on E: v' = E' V, v'' = E'' V
        scaleV = float(np.linalg.norm(V0))

        def virtual(V: F64) -> tuple[F64, F64, F64, F64, F64, F64]:
            v = np.einsum("nij,j->ni", E, V)  # Li 2020, Eqs. 8-9
            v1 = np.einsum("nij,j->ni", E1, V)
            v2 = np.einsum("nij,j->ni", E2, V)
            tv, nv, ok_v = normals_tangents(v1, v2)
            return v, v1, v2, tv, nv, ok_v

        # Li 2020, Eqs. 14-16: the rotation bringing the measured normals and tangents onto the
        # virtual ones (least squares over all pairs).
        _, _, _, tv0, nv0, okv0 = virtual(V0)
        ok0 = np.logical_and(ok_m, okv0)
        R0 = wahba(np.concatenate([tm, nm[ok0]]), np.concatenate([tv0, nv0[ok0]]))
        if _cost_simple(R0, m, E, V0) > _cost_simple(R_w, m, E, V0):
            R0 = R_w  # the closed form is only a start; keep the better of the two
        fixV = ref is not None
        # The normal term only where both normals are defined at the start (a fixed mask keeps
        # the objective smooth).
        okf = ok0.astype(float)[:, None]

        def unpack(x: F64) -> F64:
            return V0 if fixV else x[3:6] * scaleV

        def resid_RV(R: F64, V: F64) -> F64:
            v, _, _, tv, nv, _ = virtual(V)
            r_n = (nm @ R.T - nv) * okf  # Li 2020, Eq. 24, normal term
            r_t = tm @ R.T - tv  # Li 2020, Eq. 24, tangent term
            r_v = (m @ R.T - v) / scaleV  # Li 2020, Eq. 24, vector term
            return np.concatenate([r_n.ravel(), r_t.ravel(), r_v.ravel()])

        def jac_RV(R: F64, V: F64, dR: F64) -> F64:
            """Jacobian w.r.t. the rotation parameters (``dR`` = dR/dp_k, (K,3,3)) and V."""
            blocks_R = [
                np.einsum("nj,kij->nik", nm, dR) * okf[:, :, None],
                np.einsum("nj,kij->nik", tm, dR),
                np.einsum("nj,kij->nik", m, dR) / scaleV,
            ]
            JR = np.concatenate([b.reshape(-1, len(dR)) for b in blocks_R])
            if fixV:
                return JR
            _, v1, v2, _, _, _ = virtual(V)
            dv1 = E1 * scaleV  # d v' / d (V / scaleV)
            dv2 = E2 * scaleV
            cr = np.cross(v1, v2)
            dcr = -skew(v2) @ dv1 + skew(v1) @ dv2  # d(a x b) = -[b]x da + [a]x db
            dnv = _unit_jac(cr) @ dcr
            dtv = _unit_jac(v1) @ dv1
            JV = np.concatenate(
                [(-dnv * okf[:, :, None]).reshape(-1, 3), (-dtv).reshape(-1, 3), -E.reshape(-1, 3)]
            )
            return np.concatenate([JR, JV], 1)

        def resid(x: F64) -> F64:
            return resid_RV(cayley(x[:3]) @ R0, unpack(x))

        def jac(x: F64) -> F64:
            dR = cayley_derivatives(x[:3]) @ R0
            return jac_RV(cayley(x[:3]) @ R0, unpack(x), dR)

        x0 = np.zeros(3) if fixV else np.concatenate([np.zeros(3), V0 / scaleV])
        sol = least_squares(
            resid,
            x0,
            jac=jac,
            method="lm",
            x_scale="jac",
            xtol=1e-12,
            ftol=1e-12,
            gtol=1e-12,
            max_nfev=self.max_nfev,
        )
        R = cayley(sol.x[:3]) @ R0
        V = unpack(sol.x)
        # Covariance about the solution: Jacobian w.r.t. a body-frame rotation phi (left
        # perturbation exp(phi^) R, dR/dphi_k = [e_k]x R) and V, analytic.
        J = jac_RV(R, V, skew(np.eye(3)) @ R)
        r = resid_RV(R, V)
        H = J.T @ J
        blocks = {"rot": slice(0, 3)}
        if not fixV:
            blocks["V"] = slice(3, 6)
        an = analyse(H, blocks)
        cov = an.cov @ _score_covariance(J, r, len(tm), first, len(m), half) @ an.cov
        nul = an.block_null.get("rot", np.zeros((3, 0)))
        sig = sigma_with_null(cov[:3, :3], nul)
        axes = [canonical_axis(v) for v in nul.T]
        warnings = []
        if axes:
            warnings.append(rotation_words(axes, fixV))
        if p.terms:
            warnings.append(
                "li2020 estimates the rotation only; requested terms "
                + ", ".join(sorted(t.value for t in p.terms))
                + " were not estimated"
            )
        yhat = np.einsum("nij,j->ni", E, V) @ R
        return Calibration(
            R_body_mag=R,
            sigma_rotvec_deg=np.degrees(sig),
            B_enu_nT=V,
            estimator=self.name,
            residual_rms_nT=float(np.sqrt(np.mean((m - yhat) ** 2))),
            n_samples=p.n,
            unobservable_axes_body=tuple(axes),
            R_nominal_body_mag=p.R_nominal_body_mag,
            warnings=tuple(warnings),
        )


def _score_covariance(J: F64, r: F64, m: int, first: int, n: int, half: int) -> F64:
    """Newey-West estimate of the covariance of the score ``J.T r``, (P, P).

    ``J`` and ``r`` are stacked as in the objective: normal and tangent rows for derivative
    samples ``first .. first + m - 1`` (3 rows each), then vector rows for samples
    ``0 .. n - 1``. Contributions are summed per sample into a score series ``g_i``; residuals
    share noise within ``2 half + 1`` samples, so lags up to ``4 half`` are kept with
    Bartlett weights ``1 - l / (L + 1)``.
    """
    P = J.shape[1]
    contrib = J * r[:, None]
    g = np.zeros((n, P))
    idx_d = first + np.arange(m)
    np.add.at(g, idx_d, contrib[: 3 * m].reshape(m, 3, P).sum(1))
    np.add.at(g, idx_d, contrib[3 * m : 6 * m].reshape(m, 3, P).sum(1))
    g += contrib[6 * m :].reshape(n, 3, P).sum(1)
    g -= g.mean(0)  # zero at the optimum up to the truncation; centre for safety
    S = g.T @ g
    lags = min(4 * half, n - 1)
    for lag in range(1, lags + 1):
        G = g[lag:].T @ g[:-lag]
        S += (1.0 - lag / (lags + 1)) * (G + G.T)
    return S


def _cost_simple(R: F64, m: F64, E: F64, V: F64) -> float:
    return float(np.sum((m @ R.T - np.einsum("nij,j->ni", E, V)) ** 2))

"""Streaming calibration: the misalignment from fixed-size sufficient statistics.

More in docs/modules.md, ``stages.estimators.streaming``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import cast

import numpy as np
from numpy.typing import NDArray

from pipeline.core.errors import EstimationError
from pipeline.core.geometry import quat_to_matrix, skew, so3_exp
from pipeline.model.calibration import Calibration
from pipeline.model.forward import SOFT_IRON_BASIS, SOFT_IRON_BASIS_TRACE_FREE
from pipeline.model.solve import Linearised, minimise
from stages.estimators.base import RELATIVE_INFO_THRESHOLD, analyse, solve_many_truncated

F64 = NDArray[np.float64]

#: relative eigenvalue of the rotation information below which an axis is unobservable
UNOBSERVABLE_RATIO = 1e-8
ESTIMATOR_NAME = "ml-streaming"


# ------------------------------------------------------------------------------ the model
@dataclass(frozen=True)
class _State:
    R: F64  # R_body_mag
    B: F64  # B_enu_nT
    o: F64  # offset_nT (zeros when not estimated)


def _T(st: StreamStats, R: F64) -> F64:
    """``sum_i C_i @ R @ y_i`` (3,)."""
    return np.einsum("abc,bc->a", st.M, R)


def cost(st: StreamStats, R: F64, B: F64, o: F64) -> float:
    """Sum of squared residuals ``sum |y_i - o - R.T C_i.T B|^2``, nT^2, from the sums."""
    SRo = st.S @ R @ o
    c = (st.sum_yy - 2.0 * o @ st.sum_y + st.n * o @ o
         - 2.0 * B @ (_T(st, R) - SRo) + st.n * B @ B)
    return max(float(c), 0.0)


def normal_equations(st: StreamStats, s: _State) -> tuple[F64, F64]:
    """Gauss-Newton ``(J^T J, J^T r)`` over ``[phi (3), B (3), o (3)]`` at state ``s``.

    ``phi`` perturbs the rotation on the right, ``R <- R @ exp([phi]x)``, so the predicted
    reading ``m_i = R.T C_i.T B`` moves by ``m_i x phi`` and ``dr_i/dphi = -[m_i]x``.
    """
    R, B, o, n = s.R, s.B, s.o, st.n
    # sum_i C_i.T B B.T C_i = sum_ac B_a B_c W[a, :, c, :]
    CBBC = np.einsum("a,c,abcd->bd", B, B, st.W)
    sum_mm = R.T @ CBBC @ R  # sum_i m_i m_i.T
    sum_m = R.T @ st.S.T @ B  # sum_i m_i
    H = np.zeros((9, 9))
    H[:3, :3] = (B @ B) * n * np.eye(3) - sum_mm  # sum [m]x^T [m]x
    H[:3, 3:6] = -R.T @ st.S.T @ skew(B)  # sum [m_i]x R.T C_i.T
    H[:3, 6:] = -skew(sum_m)  # sum (-[m_i]x)^T (-I) = -[sum m_i]x
    H[3:6, 3:6] = n * np.eye(3)
    H[3:6, 6:] = st.S @ R  # sum C_i R
    H[6:, 6:] = n * np.eye(3)
    H = np.triu(H) + np.triu(H, 1).T
    # J^T r with r_i = y_i - o - m_i
    sum_m_cross_y = _sum_m_cross_y(st, R, B)
    g = np.empty(9)
    g[:3] = sum_m_cross_y - np.cross(sum_m, o)  # sum [m_i]x r_i = sum m_i x (y_i - o)
    g[3:6] = -(_T(st, R) - st.S @ R @ o - n * B)  # -sum C_i R r_i
    g[6:] = -(st.sum_y - n * o - sum_m)  # -sum r_i
    return H, g


def _eps() -> F64:
    e = np.zeros((3, 3, 3))
    e[0, 1, 2] = e[1, 2, 0] = e[2, 0, 1] = 1.0
    e[0, 2, 1] = e[2, 1, 0] = e[1, 0, 2] = -1.0
    return e


def _sum_m_cross_y(st: StreamStats, R: F64, B: F64) -> F64:
    """``sum_i m_i x y_i`` with ``m_i = R.T C_i.T B``: ``P[k, l] = sum_i m_ik y_il``."""
    P = np.einsum("ak,b,bal->kl", R, B, st.M)
    return np.einsum("jkl,kl->j", _eps(), P)


def _solve_linear(st: StreamStats, R: F64, B_fixed: F64 | None, with_offset: bool
                  ) -> tuple[F64, F64]:
    """Best ``B`` (unless fixed) and ``o`` (if estimated) for a given ``R`` (linear LS)."""
    n, T, SR = st.n, _T(st, R), st.S @ R
    if B_fixed is not None:
        B = B_fixed
        o = (st.sum_y - SR.T @ B) / n if with_offset else np.zeros(3)
        return B, o
    if not with_offset:
        return T / n, np.zeros(3)
    A = np.block([[n * np.eye(3), SR], [SR.T, n * np.eye(3)]])
    x = np.linalg.lstsq(A, np.concatenate([T, st.sum_y]), rcond=1e-12)[0]
    return x[:3], x[3:]


def _cube_rotations() -> list[F64]:
    out = []
    for perm in ((0, 1, 2), (1, 2, 0), (2, 0, 1), (1, 0, 2), (0, 2, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            P = np.zeros((3, 3))
            for i, j in enumerate(perm):
                P[i, j] = 1.0 - 2.0 * signs[i]
            if np.linalg.det(P) > 0:
                out.append(P)
    return out


@dataclass(frozen=True)
class StreamingFit:
    """Result of :func:`fit_stats`: the estimate, its covariance and fit quality.

    Attributes
    ----------
    R_body_mag : ndarray (3, 3)
    B_enu_nT : ndarray (3,)
    offset_nT : ndarray (3,) or None
    cov : ndarray (9, 9)
        Covariance of ``[phi (rad, mag frame), B (nT), o (nT)]``; rows of fixed or
        unestimated parameters are zero.
    residual_rms_nT : float
        RMS over every component of the residual, nT (as every estimator's: the residual
        vector's norm over sqrt 3; the verdict compares it with the per-axis noise).
    n_samples : int
    unobservable_axes_body : tuple of ndarray (3,)
    iterations : int
    D : ndarray (3, 3) or None
        Soft iron, when estimated; ``sigma_D`` its 1-sigma per element (``inf`` where an
        unobservable direction touches it), ``cov_D`` the covariance of its basis
        coefficients.
    time_offset_s : float or None
        ``tau`` relative to the stamps of the aligned samples, when estimated;
        ``sigma_time_offset_s`` its 1-sigma (``inf`` when unobservable).
    warnings : tuple of str

    """

    R_body_mag: F64
    B_enu_nT: F64
    offset_nT: F64 | None
    cov: F64
    residual_rms_nT: float
    n_samples: int
    unobservable_axes_body: tuple[F64, ...]
    iterations: int
    D: F64 | None = None
    sigma_D: F64 | None = None
    cov_D: F64 | None = None
    time_offset_s: float | None = None
    sigma_time_offset_s: float | None = None
    warnings: tuple[str, ...] = ()

    @property
    def sigma_rotvec_deg(self) -> F64:
        """One-sigma of the rotation vector, deg (infinite about unobservable axes)."""
        # phi is in the mag frame; rotate its covariance into body axes (R phi)
        C = self.R_body_mag @ self.cov[:3, :3] @ self.R_body_mag.T
        sig = np.degrees(np.sqrt(np.clip(np.diag(C), 0.0, None)))
        for ax in self.unobservable_axes_body:
            sig = np.where(np.abs(ax) > 1e-3, np.inf, sig)
        return sig

    def to_calibration(self) -> Calibration:
        """Return the fit as a :class:`Calibration` (``ml-streaming``)."""
        sig_o = None
        if self.offset_nT is not None:
            sig_o = np.sqrt(np.clip(np.diag(self.cov[6:, 6:]), 0.0, None))
        return Calibration(
            R_body_mag=self.R_body_mag,
            sigma_rotvec_deg=self.sigma_rotvec_deg,
            B_enu_nT=self.B_enu_nT,
            estimator=ESTIMATOR_NAME,
            residual_rms_nT=self.residual_rms_nT,
            n_samples=self.n_samples,
            unobservable_axes_body=self.unobservable_axes_body,
            offset_nT=self.offset_nT,
            sigma_offset_nT=sig_o,
            sigma_B_enu_nT=np.sqrt(np.clip(np.diag(self.cov[3:6, 3:6]), 0.0, None)),
            D=self.D,
            sigma_D=self.sigma_D,
            time_offset_s=self.time_offset_s,
            sigma_time_offset_s=self.sigma_time_offset_s,
            warnings=self.warnings,
        )


def fit_stats(
    st: StreamStats,
    *,
    estimate_offset: bool = False,
    estimate_soft_iron: bool = False,
    estimate_time_offset: bool = False,
    reference_field_enu_nT: F64 | None = None,
    R_nominal_body_mag: F64 | None = None,
    max_iter: int = 50,
    block_sandwich: bool = False,
) -> StreamingFit:
    """Gauss-Newton (Levenberg-damped, THE solver core) on the sufficient statistics alone.

    Parameters
    ----------
    st : StreamStats
        Sums over all samples (:class:`StreamAccumulator`).
    estimate_offset : bool
        Estimate the hard-iron offset ``o`` (mag frame, nT).
    estimate_soft_iron : bool
        Estimate the symmetric soft-iron matrix ``D`` (trace 3 when ``B`` is estimated).
    estimate_time_offset : bool
        Estimate ``tau`` (s, relative to the aligned samples' stamps) from the second-order
        expansion of the attitude (docs/modules.md); only the samples with both stencil
        neighbours are used then.
    reference_field_enu_nT : ndarray (3,), optional
        Known background field; estimated when ``None``.
    R_nominal_body_mag : ndarray (3, 3), optional
        Starting rotation; by default the best of the 24 axis-aligned rotations.
    max_iter : int
        Gauss-Newton iterations.
    block_sandwich : bool
        With a :class:`StreamStats` (per-time-block sums), give the rotation-only model the
        block sandwich covariance too (as the in-memory ML and the soft iron / time offset
        fits have): residuals correlated over seconds (attitude noise interpolated, field
        gradients) make the information's sigmas too small. ``False``: the information's.

    Raises
    ------
    EstimationError
        Too few samples.

    """
    if st.n < 10:
        raise EstimationError(f"only {st.n} aligned samples: too few to calibrate")
    B_fixed = None if reference_field_enu_nT is None else np.asarray(
        reference_field_enu_nT, dtype=float).reshape(3)
    if estimate_soft_iron or estimate_time_offset or (
            block_sandwich and isinstance(st, StreamStats) and len(st.block_Wa)):
        return _fit_terms(st, estimate_offset=estimate_offset,
                          estimate_soft_iron=estimate_soft_iron,
                          estimate_time_offset=estimate_time_offset, B_fixed=B_fixed,
                          R_nominal=R_nominal_body_mag, max_iter=max_iter)
    starts = [np.asarray(R_nominal_body_mag, float)] if R_nominal_body_mag is not None \
        else _cube_rotations()
    best: _State | None = None
    best_c = np.inf
    for R0 in starts:
        R = R0
        # a few alternations (SVD for R given B and o; Li 2020, Eq. 24 form) to get close
        for _ in range(3):
            B, o = _solve_linear(st, R, B_fixed, estimate_offset)
            K = np.einsum("a,abc->bc", B, st.M) - np.outer(st.S.T @ B, o)
            U, _s, Vt = np.linalg.svd(K)
            d = np.sign(np.linalg.det(U @ Vt)) or 1.0
            R = U @ np.diag([1.0, 1.0, d]) @ Vt
        B, o = _solve_linear(st, R, B_fixed, estimate_offset)
        c = cost(st, R, B, o)
        if c < best_c:
            best, best_c = _State(R, B, o), c
    assert best is not None
    free = np.array([True] * 3 + [B_fixed is None] * 3 + [estimate_offset] * 3)
    def linearise(x: _State, with_normal: bool) -> Linearised:
        cx = cost(st, x.R, x.B, x.o)
        if not with_normal:
            return Linearised(cx)
        H, g = normal_equations(st, x)
        # THE core's convention: g = J.T r with J = d(prediction)/dx = -d(residual)/dx
        return Linearised(cx, H[np.ix_(free, free)], -g[free])

    def update(x: _State, step: F64) -> _State:
        d = np.zeros(9)
        d[free] = step
        return _State(x.R @ so3_exp(d[:3]), x.B + d[3:6], x.o + d[6:])

    def solve_step(Hf: F64, gf: F64, lam: float, _scale: F64) -> F64:
        scale = np.sqrt(np.clip(np.diag(Hf), 1e-300, None))
        Hs = Hf / np.outer(scale, scale)
        return cast(F64, np.linalg.lstsq(Hs + lam * np.eye(len(gf)), gf / scale,
                                         rcond=1e-12)[0] / scale)

    def converged(before: Linearised, after: Linearised, step: F64) -> bool:
        return bool(before.cost - after.cost <= 1e-12 * max(before.cost, 1.0)
                    and np.max(np.abs(step[:n_rot])) < 1e-12)

    n_rot = 3  # the rotation leads the free parameters
    # THE solver core (pipeline.model.solve.minimise) on the sums alone
    sol = minimise(best, linearise, update, solve_step=solve_step, converged=converged,
                   max_iter=max_iter, rtol=0.0, lam0=1e-9, max_tries=20, lam_up=10.0,
                   lam_down=10.0, lam_min=1e-12)
    s, c, iterations = sol.state, sol.at.cost, sol.n_iter
    H, _g = normal_equations(st, s)
    p = int(free.sum())
    dof = max(3 * st.n - p, 1)
    sigma2 = c / dof
    Hf = H[np.ix_(free, free)]
    cov_f = sigma2 * np.linalg.pinv(Hf, rcond=1e-12, hermitian=True)
    cov = np.zeros((9, 9))
    cov[np.ix_(free, free)] = cov_f
    # unobservable rotation axes: small eigenvalues of the rotation information with the
    # nuisance parameters (B, o) marginalised (Schur complement)
    info = H[:3, :3]
    nuis = free.copy()
    nuis[:3] = False
    if nuis.any():
        Hrn = H[np.ix_(np.arange(3), np.flatnonzero(nuis))]
        Hnn = H[np.ix_(nuis, nuis)]
        info = info - Hrn @ np.linalg.pinv(Hnn, rcond=1e-12, hermitian=True) @ Hrn.T
    w, V = np.linalg.eigh(info)
    axes = tuple(s.R @ V[:, k] for k in range(3) if w[k] <= UNOBSERVABLE_RATIO * max(w[-1], 1e-300))
    if len(axes) == 1:
        # one rotation axis undetermined (single-axis motion, field estimated): of the equally
        # good rotations exp(theta [a]x) R, report the one nearest the nominal rotation
        s = _nearest_about_axis(st, s, axes[0], R_nominal_body_mag, B_fixed, estimate_offset)
    return StreamingFit(
        R_body_mag=s.R,
        B_enu_nT=s.B,
        offset_nT=s.o if estimate_offset else None,
        cov=cov,
        residual_rms_nT=float(np.sqrt(c / (3 * st.n))),
        n_samples=st.n,
        unobservable_axes_body=tuple(a / np.linalg.norm(a) for a in axes),
        iterations=iterations,
    )


def _nearest_about_axis(st: StreamStats, s: _State, axis_body: F64, R_nominal: F64 | None,
                       B_fixed: F64 | None, with_offset: bool) -> _State:
    """Turn ``s.R`` about ``axis_body`` to the angle nearest ``R_nominal`` (identity)."""
    Rn = np.eye(3) if R_nominal is None else np.asarray(R_nominal, float)
    a = axis_body / np.linalg.norm(axis_body)
    K = skew(a)
    A = Rn.T
    # tr(Rn.T exp(theta K) R) = c0 + sin(theta) c1 + (1 - cos(theta)) c2 (Rodrigues)
    c1 = np.trace(A @ K @ s.R)
    c2 = np.trace(A @ K @ K @ s.R)
    theta = np.arctan2(c1, -c2)  # maximiser of c1 sin(theta) - c2 cos(theta)
    R = so3_exp(theta * a) @ s.R
    B, o = _solve_linear(st, R, B_fixed, with_offset)
    # The cost from the sums cancels sum_yy against terms of the same size: its rounding is
    # ~1e-16 sum_yy, so "no worse" is judged with a margin of that scale (not an absolute one).
    if cost(st, R, B, o) > cost(st, s.R, s.B, s.o) * (1 + 1e-9) + 1e-13 * st.sum_yy:
        return s  # not an exact symmetry of this data: keep the optimum
    return _State(R, B, o)


# ------------------------------------------------------------------------------ soft iron, tau
#: length of the expanded attitude vector g = [1, vec G0, vec G1, vec G2] (docs/modules.md)
NG = 28
#: default baseline of the three-point attitude derivatives, s (docs/modules.md)
DERIVATIVE_BASELINE_S = 0.05
#: most time blocks kept for the block sandwich covariance (fixed memory): the block length
#: starts at :data:`stages.estimators.checks.BLOCK_S` and doubles when the recording outgrows
#: them (adjacent blocks are merged)
MAX_BLOCKS = 128
#: length of the rotation-model vector a = [1, vec C] of every sample
NA = 10


@dataclass(frozen=True)
class StreamStats:
    """Sums of :class:`StreamAccumulator`: everything :func:`fit_stats` needs, fixed size.

    The rotation model's sums over every sample (``n``, ``sum_y``, ``sum_yy``, ``S``, ``M``,
    ``W``) are the totals of its per-block sums ``block_Wa``, ``block_Ya``, ``block_yya``.

    Attributes
    ----------
    Wg : ndarray (28, 28)
        ``sum g_i g_i.T`` over the samples with both stencil neighbours (docs/modules.md);
        ``Wg[0, 0]`` is their count.
    Yg : ndarray (28, 3)
        ``sum g_i y_i.T``, nT.
    yy : float
        ``sum |y_i|^2`` over the same samples, nT^2.
    block_Wg, block_Yg, block_yy : ndarray (K, 28, 28), (K, 28, 3), (K,)
        The same sums per time block (at most :data:`MAX_BLOCKS`): the block sandwich
        covariance.
    block_Wa, block_Ya, block_yya : ndarray (K, 10, 10), (K, 10, 3), (K,)
        Per block, the rotation-model sums of every sample (``a = [1, vec C]``).
    baseline_s, block_s : float
        Baseline of the attitude derivatives; length of a time block.

    """

    Wg: F64
    Yg: F64
    yy: float
    block_Wg: F64
    block_Yg: F64
    block_yy: F64
    block_Wa: F64
    block_Ya: F64
    block_yya: F64
    baseline_s: float = DERIVATIVE_BASELINE_S
    block_s: float = 1.0

    @classmethod
    def of(cls, q_enu_body: F64, mag_nT: F64, t_ns: NDArray[np.int64]) -> StreamStats:
        """Return the rotation model's sums of aligned samples (one block of a stream)."""
        acc = StreamAccumulator(with_tau=False)
        acc.add(q_enu_body, mag_nT, t_ns)
        return acc.result()

    @cached_property
    def n(self) -> int:
        """Number of samples (all of them)."""
        return int(round(float(self.block_Wa[:, 0, 0].sum())))

    @cached_property
    def sum_y(self) -> F64:
        """Sum of the magnetometer readings (3,), nT, mag frame."""
        return cast(F64, self.block_Ya[:, 0, :].sum(axis=0))

    @cached_property
    def sum_yy(self) -> float:
        """Sum of their squared norms, nT^2."""
        return float(self.block_yya.sum())

    @cached_property
    def S(self) -> F64:  # noqa: N802 - the sum's name in the model
        """Sum of ``C_enu_body`` (3, 3)."""
        return cast(F64, self.block_Wa[:, 0, 1:].sum(axis=0).reshape(3, 3))

    @cached_property
    def M(self) -> F64:  # noqa: N802 - the sum's name in the model
        """``M[a, b, c] = sum C_enu_body[a, b] * y[c]`` (3, 3, 3), nT."""
        return cast(F64, self.block_Ya[:, 1:, :].sum(axis=0).reshape(3, 3, 3))

    @cached_property
    def W(self) -> F64:  # noqa: N802 - the sum's name in the model
        """``W[a, b, c, d] = sum C_enu_body[a, b] * C_enu_body[c, d]`` (3, 3, 3, 3)."""
        return cast(F64, self.block_Wa[:, 1:, 1:].sum(axis=0).reshape(3, 3, 3, 3))

    @property
    def n_tau(self) -> int:
        """Number of samples in the expanded sums (those with both stencil neighbours)."""
        return int(round(self.Wg[0, 0]))

    def __add__(self, other: StreamStats) -> StreamStats:
        """Return the sums of two disjoint stretches (e.g. the halves of a recording).

        Totals add; the time blocks of the two are kept side by side (the block sandwich
        only needs the blocks to be disjoint stretches, not of one length).
        """
        def cat(a: F64, b: F64) -> F64:
            return np.concatenate([a, b])

        return StreamStats(
            Wg=self.Wg + other.Wg, Yg=self.Yg + other.Yg,
            yy=self.yy + other.yy,
            block_Wg=cat(self.block_Wg, other.block_Wg),
            block_Yg=cat(self.block_Yg, other.block_Yg),
            block_yy=cat(self.block_yy, other.block_yy),
            block_Wa=cat(self.block_Wa, other.block_Wa),
            block_Ya=cat(self.block_Ya, other.block_Ya),
            block_yya=cat(self.block_yya, other.block_yya),
            baseline_s=self.baseline_s, block_s=max(self.block_s, other.block_s))


def _embed(Wa: F64, Ya: F64) -> tuple[F64, F64]:
    """Rotation-model sums ``[1, vec C]`` (..., 10, ·) as expanded sums (G1 = G2 = 0)."""
    Wg = np.zeros((*Wa.shape[:-2], NG, NG))
    Yg = np.zeros((*Ya.shape[:-2], NG, 3))
    Wg[..., :NA, :NA] = Wa
    Yg[..., :NA, :] = Ya
    return Wg, Yg


@dataclass(frozen=True)
class SampleSums:
    """The sums of every aligned sample of a long recording, reduced in one pass.

    What :func:`fit_stats` fits the rotation (and the terms asked for) from, without the
    samples themselves.

    Attributes
    ----------
    halves : tuple of two StreamStats, or None
        The rotation model's sums (per time block) of the recording's first and second
        halves of equal sample counts: their sum is the whole's, and their fits check its
        sigmas. None when ``terms`` holds the sums.
    split_s : float
        Where the halves meet, s from the first magnetometer sample.
    terms : StreamStats or None
        The expanded sums of every sample, for the soft iron and the time offset.

    """

    halves: tuple[StreamStats, StreamStats] | None = None
    split_s: float = 0.0
    terms: StreamStats | None = None


@dataclass(frozen=True)
class _Sums:
    """The sums one fit uses: totals and per time block (``None`` without blocks)."""

    Wg: F64
    Yg: F64
    yy: float
    n: int
    block_Wg: F64 | None = None
    block_Yg: F64 | None = None


def _expanded_sums(stats: StreamStats, with_tau: bool) -> _Sums:
    """Return the sums of the samples a fit uses (rotation sums embedded when tau is fixed)."""
    if with_tau:
        return _Sums(stats.Wg, stats.Yg, stats.yy, stats.n_tau, stats.block_Wg,
                     stats.block_Yg)
    Wg, Yg = _embed(stats.block_Wa.sum(axis=0), stats.block_Ya.sum(axis=0))
    bW, bY = _embed(stats.block_Wa, stats.block_Ya)
    return _Sums(Wg, Yg, stats.sum_yy, stats.n, bW, bY)


def _stencil_weights(a: F64, c: F64) -> tuple[F64, F64]:
    """Return the first and second derivative weights (N, 3) at 0 of the Lagrange parabola.

    Its nodes are at ``a < 0``, ``0`` and ``c > 0`` (s).
    """
    d1 = np.stack([-c / (a * (a - c)), -(a + c) / (a * c), -a / ((c - a) * c)], axis=1)
    d2 = np.stack([2.0 / (a * (a - c)), 2.0 / (a * c), 2.0 / ((c - a) * c)], axis=1)
    return d1, d2


class _Blocks:
    """Sums ``sum v v.T``, ``sum v y.T``, ``sum |y|^2`` per time block, at most MAX_BLOCKS."""

    def __init__(self, dim: int):
        self.W = np.zeros((MAX_BLOCKS, dim, dim))
        self.Y = np.zeros((MAX_BLOCKS, dim, 3))
        self.yy = np.zeros(MAX_BLOCKS)

    def merge_pairs(self) -> None:
        for a in (self.W, self.Y, self.yy):
            half = a[0::2] + a[1::2]
            a[:] = 0.0
            a[: MAX_BLOCKS // 2] = half

    def add(self, blk: NDArray[np.int64], v: F64, y: F64) -> None:
        """Add rows ``v``, ``y`` in blocks ``blk`` (non-decreasing)."""
        cuts = np.flatnonzero(np.diff(blk)) + 1
        for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, len(blk)], strict=True):
            b, vv, yv = int(blk[lo]), v[lo:hi], y[lo:hi]
            self.W[b] += vv.T @ vv
            self.Y[b] += vv.T @ yv
            self.yy[b] += float(np.einsum("ij,ij->", yv, yv))


class StreamAccumulator:
    """One pass, fixed memory: the sums of :class:`StreamStats` from ordered blocks.

    ``acc = StreamAccumulator(); acc.add(q_enu_body, mag_nT, t_ns) ...; stats = acc.result()``.
    Blocks must come in time order (stamps non-decreasing across and within blocks). The
    attitude derivatives of a sample are taken once its neighbour ``baseline_s`` later has
    arrived; the samples they still need are carried to the next block (docs/modules.md), so
    the sums do not depend on how the data are split. The sums are also kept per time block
    (at most :data:`MAX_BLOCKS`, from the first stamp; adjacent blocks merge when the
    recording outgrows them) for the block sandwich covariance.

    Parameters
    ----------
    baseline_s : float
        Least distance of the stencil neighbours, s.
    max_gap_s : float
        A larger step between consecutive samples ends a stretch: stencils do not cross it.
    block_s : float
        Initial length of the time blocks of the covariance, s.
    with_tau : bool
        Accumulate the expanded sums of the time offset (``False``: only the rotation
        model's sums, every sample and per time block, for the block sandwich).

    """

    def __init__(self, baseline_s: float = DERIVATIVE_BASELINE_S, max_gap_s: float = 0.1,
                 block_s: float = 1.0, with_tau: bool = True):
        if not (baseline_s > 0 and max_gap_s > 0 and block_s > 0):
            raise EstimationError("baseline_s, max_gap_s and block_s must be positive")
        self.baseline_s = float(baseline_s)
        self.with_tau = bool(with_tau)
        self._h = int(round(baseline_s * 1e9))
        self._gap = int(round(max_gap_s * 1e9))
        self._blk = max(int(round(block_s * 1e9)), 1)
        self._t0: int | None = None
        self._g = _Blocks(NG)
        self._a = _Blocks(NA)
        # carried samples: the first ``_done`` of them are already decided
        self._t = np.zeros(0, np.int64)
        self._q = np.zeros((0, 4))
        self._y = np.zeros((0, 3))
        self._done = 0

    def _block_of(self, t: NDArray[np.int64]) -> NDArray[np.int64]:
        assert self._t0 is not None
        while int(t[-1] - self._t0) // self._blk >= MAX_BLOCKS:
            self._g.merge_pairs()
            self._a.merge_pairs()
            self._blk *= 2
        return (t - self._t0) // self._blk

    def add(self, q_enu_body: F64, mag_nT: F64, t_ns: NDArray[np.int64]) -> None:
        """Add one block of aligned samples (attitude at the stamps, scalar-last)."""
        q = np.asarray(q_enu_body, dtype=float).reshape(-1, 4)
        y = np.asarray(mag_nT, dtype=float).reshape(-1, 3)
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        if not len(q) == len(y) == len(t):
            raise EstimationError(f"{len(q)} attitudes, {len(y)} readings, {len(t)} stamps")
        if len(t) == 0:
            return
        if np.any(np.diff(t) < 0) or (len(self._t) and t[0] < self._t[-1]):
            raise EstimationError("the stamps of the stream must not decrease")
        if self._t0 is None:
            self._t0 = int(t[0])
        C = quat_to_matrix(q).reshape(-1, 9)
        self._a.add(self._block_of(t), np.concatenate([np.ones((len(t), 1)), C], axis=1), y)
        if not self.with_tau:
            self._t = t[-1:]  # the stamps must still advance
            return
        T = np.concatenate([self._t, t])
        Q = np.concatenate([self._q, q])
        Y = np.concatenate([self._y, y])
        m = len(T)
        h = self._h
        pend = np.arange(self._done, m)
        decided = pend[T[pend] + h <= T[-1]]
        if len(decided):
            L = np.searchsorted(T, T[decided] - h, side="right") - 1
            R = np.searchsorted(T, T[decided] + h, side="left")
            gaps = np.concatenate([[0], np.cumsum(np.diff(T) > self._gap)])
            ok = (L >= 0) & (gaps[R] == gaps[np.maximum(L, 0)])
            j, L, R = decided[ok], L[ok], R[ok]
            if len(j):
                self._emit(T, Q, Y, j, L, R)
        p = self._done + len(decided)  # the first undecided sample (decided ones lead)
        t_ref = T[p] if p < m else T[-1]
        keep = max(int(np.searchsorted(T, t_ref - h, side="right")) - 1, 0)
        self._t, self._q, self._y = T[keep:], Q[keep:], Y[keep:]
        self._done = p - keep

    def _emit(self, T: NDArray[np.int64], Q: F64, Y: F64, j: NDArray[np.intp],
              L: NDArray[np.intp], R: NDArray[np.intp]) -> None:
        a = (T[L] - T[j]).astype(float) * 1e-9
        c = (T[R] - T[j]).astype(float) * 1e-9
        d1, d2 = _stencil_weights(a, c)
        CL, C0, CR = (quat_to_matrix(Q[k]).reshape(-1, 9) for k in (L, j, R))
        Cdot = d1[:, :1] * CL + d1[:, 1:2] * C0 + d1[:, 2:] * CR
        Cddot = d2[:, :1] * CL + d2[:, 1:2] * C0 + d2[:, 2:] * CR
        g = np.concatenate([np.ones((len(j), 1)), C0, -Cdot, 0.5 * Cddot], axis=1)
        self._g.add(self._block_of(T[j]), g, Y[j])

    def result(self) -> StreamStats:
        """Return the sums so far (samples still waiting for a later neighbour left out)."""
        used = np.flatnonzero((self._a.W[:, 0, 0] > 0) | (self._g.W[:, 0, 0] > 0))
        k = int(used[-1]) + 1 if len(used) else 0
        g, a = self._g, self._a
        return StreamStats(
            Wg=g.W.sum(axis=0), Yg=g.Y.sum(axis=0), yy=float(g.yy.sum()),
            block_Wg=g.W[:k].copy(), block_Yg=g.Y[:k].copy(), block_yy=g.yy[:k].copy(),
            block_Wa=a.W[:k].copy(), block_Ya=a.Y[:k].copy(), block_yya=a.yy[:k].copy(),
            baseline_s=self.baseline_s, block_s=self._blk * 1e-9,
        )


@dataclass(frozen=True)
class _Full:
    R: F64
    B: F64
    o: F64
    D: F64
    tau: float


def _soft_iron_basis(estimate_B: bool) -> F64:

    return SOFT_IRON_BASIS_TRACE_FREE if estimate_B else SOFT_IRON_BASIS


class _Design:
    """Prediction and Jacobian of the full model, linear in the expanded attitude ``g``."""

    def __init__(self, B_free: bool, with_o: bool, with_D: bool, with_tau: bool):
        self.basis = _soft_iron_basis(B_free)
        self.blocks: dict[str, slice] = {}
        n = 0
        for name, size, on in (("rot", 3, True), ("B", 3, B_free), ("offset", 3, with_o),
                               ("D", len(self.basis), with_D), ("tau", 1, with_tau)):
            if on:
                self.blocks[name] = slice(n, n + size)
                n += size
        self.n_params = n

    def predict(self, g: F64, s: _Full, with_jacobian: bool = True
                ) -> tuple[F64, F64 | None]:
        """``m (K, 3)`` and ``dm/dx (K, 3, P)`` for expanded attitudes ``g (K, 28)``."""
        K = len(g)
        G0, G1, G2 = (g[:, 1 + 9 * k: 10 + 9 * k].reshape(K, 3, 3) for k in range(3))
        P = G0 + s.tau * G1 + s.tau**2 * G2
        u = np.einsum("kab,a->kb", P, s.B)  # P.T B
        v = u @ s.R  # R.T P.T B per row
        m = v @ s.D.T + g[:, :1] * s.o
        if not with_jacobian:
            return m, None
        J = np.zeros((K, 3, self.n_params))
        b = self.blocks
        J[:, :, b["rot"]] = np.einsum("ab,kbc->kac", s.D, np.stack([skew(x) for x in v]))
        if "B" in b:
            J[:, :, b["B"]] = np.einsum("ab,cb,kdc->kad", s.D, s.R, P)
        if "offset" in b:
            J[:, :, b["offset"]] = g[:, 0, None, None] * np.eye(3)
        if "D" in b:
            J[:, :, b["D"]] = np.einsum("eab,kb->kae", self.basis, v)
        if "tau" in b:
            w = np.einsum("kab,a->kb", G1 + 2.0 * s.tau * G2, s.B)
            J[:, :, b["tau"].start] = (w @ s.R) @ s.D.T
        return m, J

    def step(self, s: _Full, dx: F64) -> _Full:
        b = self.blocks
        R = s.R @ so3_exp(dx[b["rot"]])
        B = s.B + dx[b["B"]] if "B" in b else s.B
        o = s.o + dx[b["offset"]] if "offset" in b else s.o
        D = s.D + np.einsum("k,kij->ij", dx[b["D"]], self.basis) if "D" in b else s.D
        tau = s.tau + float(dx[b["tau"]][0]) if "tau" in b else s.tau
        return _Full(R, B, o, D, tau)


_EYE_G = np.eye(NG)


def full_cost(Wg: F64, Yg: F64, yy: float, design: _Design, s: _Full) -> float:
    """Sum of squared residuals of the full model from the expanded sums, nT^2."""
    k, _ = design.predict(_EYE_G, s, with_jacobian=False)
    return float(yy - 2.0 * np.sum(k * Yg) + np.einsum("gh,ga,ha->", Wg, k, k))


def full_normal_equations(Wg: F64, Yg: F64, design: _Design, s: _Full
                          ) -> tuple[F64, F64]:
    """``(J.T J, J.T r)`` of the full model from the sums (J = d prediction / dx)."""
    k, K = design.predict(_EYE_G, s)
    assert K is not None
    WK = np.einsum("gh,hap->gap", Wg, K)  # (28, 3, P)
    H = np.einsum("gap,gaq->pq", K, WK)
    g = np.einsum("gap,ga->p", K, Yg) - np.einsum("gap,ga->p", WK, k)
    return 0.5 * (H + H.T), g


def _fit_full(Wg: F64, Yg: F64, yy: float, design: _Design, s0: _Full,
              max_iter: int) -> tuple[_Full, float, int]:
    """Run THE solver core on the expanded sums from ``s0``."""
    floor = 1e-13 * max(yy, 1.0)  # rounding of the cost from the sums

    def linearise(x: _Full, with_normal: bool) -> Linearised:
        c = full_cost(Wg, Yg, yy, design, x)
        if not with_normal:
            return Linearised(c)
        H, g = full_normal_equations(Wg, Yg, design, x)
        return Linearised(c, H, g)

    def solve_step(H: F64, g: F64, lam: float, _scale: F64) -> F64:
        scale = np.sqrt(np.clip(np.diag(H), 1e-300, None))
        Hs = H / np.outer(scale, scale)
        return cast(F64, solve_many_truncated(Hs + lam * np.diag(np.diag(Hs)),
                                              (g / scale)[:, None],
                                              RELATIVE_INFO_THRESHOLD)[:, 0] / scale)

    def converged(before: Linearised, after: Linearised, dx: F64) -> bool:
        H = cast(F64, before.H)
        return bool(float(dx @ H @ dx) <= 1e-12 * max(before.cost, 0.0) + 1e-3 * floor)

    sol = minimise(s0, linearise, design.step, solve_step=solve_step, converged=converged,
                   max_iter=max_iter, rtol=0.0, lam0=1e-9, max_tries=20, lam_up=10.0,
                   lam_down=10.0, lam_min=1e-12, accept_atol=floor)
    return sol.state, max(float(sol.at.cost), 0.0), sol.n_iter


def _block_sandwich(bW: F64, bY: F64, design: _Design, s: _Full, H_pinv: F64,
                    cov_white: F64) -> F64:
    """Block (batch-means) sandwich covariance from the per-block sums, never below white.

    The score of a time block at ``s``, ``J_b.T r_b = sum_g K_g.T Yg_bg - sum_gh Wg_bgh K_g.T
    k_h``, is exact from its sums; ``H^+ (sum_b s_b s_b.T) H^+`` then holds whatever the
    noise's correlation within a block and its dependence on the attitude (the attitude
    noise moves the reading across the field, not isotropically), as the in-memory ML's
    :func:`stages.estimators.checks.sandwich_cov`.
    """
    k, K = design.predict(_EYE_G, s)
    assert K is not None
    scores = (np.einsum("gap,bga->bp", K, bY)
              - np.einsum("bgh,gap,ha->bp", bW, K, k))
    cov = H_pinv @ (scores.T @ scores) @ H_pinv
    cov = 0.5 * (cov + cov.T)
    dw = np.sqrt(np.maximum(np.diag(cov_white), 0.0))
    ds = np.sqrt(np.maximum(np.diag(cov), 0.0))
    f = np.where(ds > 0, np.maximum(dw / np.where(ds > 0, ds, 1.0), 1.0), 1.0)
    return cast(F64, cov * f[:, None] * f[None, :])


def _fit_terms(stats: StreamStats, *, estimate_offset: bool,
               estimate_soft_iron: bool, estimate_time_offset: bool, B_fixed: F64 | None,
               R_nominal: F64 | None, max_iter: int) -> StreamingFit:
    """Soft iron and / or time offset: staged Gauss-Newton on the expanded sums."""
    first = fit_stats(stats, estimate_offset=estimate_offset, reference_field_enu_nT=B_fixed,
                      R_nominal_body_mag=R_nominal, max_iter=max_iter)
    sums = _expanded_sums(stats, estimate_time_offset)
    Wg, Yg, yy, n = sums.Wg, sums.Yg, sums.yy, sums.n
    if n < 10:
        raise EstimationError(f"only {n} samples with attitude neighbours: too few to "
                              "estimate the time offset")
    o = first.offset_nT if first.offset_nT is not None else np.zeros(3)
    D = np.eye(3)
    if estimate_soft_iron and B_fixed is not None:
        # the scale of D is carried by the known |B|: start at the measured ratio
        yo = (yy - 2.0 * o @ Yg[0] + n * o @ o) / n
        D = D * np.sqrt(max(yo, 0.0)) / np.linalg.norm(B_fixed)
    s = _Full(first.R_body_mag, first.B_enu_nT, o, D, 0.0)
    B_free = B_fixed is None
    it = first.iterations
    stages: list[tuple[bool, bool]] = []
    if estimate_soft_iron and estimate_time_offset:
        stages.append((True, False))  # D at tau = 0 first: tau's Jacobian needs a close model
    stages.append((estimate_soft_iron, estimate_time_offset))
    for with_D, with_tau in stages:
        design = _Design(B_free, estimate_offset, with_D, with_tau)
        s, c, k = _fit_full(Wg, Yg, yy, design, s, max_iter)
        it += k
    H, _g = full_normal_equations(Wg, Yg, design, s)
    dof = max(3 * n - design.n_params, 1)
    an = analyse(H, design.blocks)
    cov_all = an.cov * (c / dof)
    if sums.block_Wg is not None and sums.block_Yg is not None:
        cov_all = _block_sandwich(sums.block_Wg, sums.block_Yg, design, s, an.cov, cov_all)
    b = design.blocks
    cov = np.zeros((9, 9))
    idx = [np.r_[b["rot"]]]
    pos = [np.r_[0:3]]
    if "B" in b:
        idx.append(np.r_[b["B"]])
        pos.append(np.r_[3:6])
    if "offset" in b:
        idx.append(np.r_[b["offset"]])
        pos.append(np.r_[6:9])
    ii, pp = np.concatenate(idx), np.concatenate(pos)
    cov[np.ix_(pp, pp)] = cov_all[np.ix_(ii, ii)]
    rot_null = an.block_null.get("rot", np.zeros((3, 0)))
    axes = tuple(s.R @ v / np.linalg.norm(v) for v in rot_null.T)
    warnings: list[str] = []
    sig_D = None
    if "D" in b:
        coef = design.basis.reshape(len(design.basis), 9).T  # (9, k)
        cd = cov_all[b["D"], b["D"]]
        sig_D = np.sqrt(np.maximum(np.einsum("ek,kl,el->e", coef, cd, coef), 0.0)).reshape(3, 3)
        nul = an.block_null.get("D", np.zeros((len(design.basis), 0)))
        if nul.size:
            touched = np.abs(coef @ nul) > 1e-3
            sig_D = np.where(touched.any(axis=1).reshape(3, 3), np.inf, sig_D)
            warnings.append("part of the soft-iron matrix D is not observable from this motion "
                            "(kept at its initial value): rotate about two or three different "
                            "axes")
        if B_free:
            warnings.append("without a reference field the overall scale of D cannot be told "
                            "from |B|: D is normalised to trace 3")
    sig_tau = None
    if "tau" in b:
        sig_tau = float(np.sqrt(max(cov_all[b["tau"], b["tau"]][0, 0], 0.0)))
        if an.block_null.get("tau", np.zeros((1, 0))).size:
            sig_tau = float("inf")
            warnings.append("the time offset is not observable (kept at its initial value): "
                            "it trades against the rotation about the turning axis when the "
                            "rate is constant; vary the rotation rate or rotate about a second "
                            "axis")
    cov_D = cov_all[b["D"], b["D"]] if "D" in b else None
    return StreamingFit(
        R_body_mag=s.R,
        B_enu_nT=s.B,
        offset_nT=s.o if estimate_offset else None,
        cov=cov,
        residual_rms_nT=float(np.sqrt(c / (3 * n))),
        n_samples=n,
        unobservable_axes_body=axes,
        iterations=it,
        D=s.D if "D" in b else None,
        sigma_D=sig_D,
        cov_D=cov_D,
        time_offset_s=s.tau if "tau" in b else None,
        sigma_time_offset_s=sig_tau,
        warnings=tuple(warnings),
    )

"""What every estimator shares: options, the problem it solves, and the uncertainty analysis.

The measurement model is the one of CONVENTIONS::

    y_mag(t) = D @ R_body_mag.T @ C_enu_body(t - tau).T @ B_enu + o + noise

An estimator is anything with ``fit(problem) -> Calibration`` (:class:`Estimator`). What the
options name (``EstimatorKind``, ``EstimateTerm``, ``RobustLoss``) is the framework's, in
:mod:`pipeline.core.vocabulary`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from pipeline.core.errors import EstimationError
from pipeline.core.geometry import quat_to_matrix, skew
from pipeline.core.recording import AttitudeSeries
from pipeline.core.vocabulary import RobustLoss
from pipeline.model.attitude import AttitudeInterpolator
from pipeline.model.calibration import Calibration

F64 = NDArray[np.float64]

#: An eigen-direction of the information matrix keeps less than this fraction of its
#: information once the other parameters are marginalised out (generalised eigenvalue of the
#: marginal against the unmarginalised block, 0..1, scale-free): its 1-sigma is then more than
#: 1000x what it would be if the others were known, and it is reported as unobservable. Attitude
#: noise of 0.015 deg on a single-axis sweep leaves ratios near 1e-7, real wobble of >= 0.1 deg
#: gives >= 1e-5.
RELATIVE_INFO_THRESHOLD = 1e-6


@dataclass(frozen=True)
class NoiseModel:
    """Sensor noise figures (1-sigma) used to weight the residuals.

    Attributes
    ----------
    sigma_mag_nT : float
        White noise of each magnetometer component, nT.
    sigma_heading_rad : float
        Attitude error about the ENU up axis, rad.
    sigma_pitch_rad, sigma_roll_rad : float
        Attitude errors about body x (pitch) and body y (roll), rad.

    """

    sigma_mag_nT: float = 0.1
    sigma_heading_rad: float = 0.0
    sigma_pitch_rad: float = 0.0
    sigma_roll_rad: float = 0.0

    @classmethod
    def li2020(cls) -> NoiseModel:
        """Return the paper's sensor figures: 0.1 nT; heading 0.06 deg, pitch and roll 0.015 deg."""
        return cls(0.1, np.radians(0.06), np.radians(0.015), np.radians(0.015))

    def attitude_cov_body(self, C_enu_body: F64) -> F64:
        """Covariance of the small attitude error expressed in the body frame, (N, 3, 3), rad^2.

        The error model of the generator (``pipeline.app.simulate``, and
        :func:`stages.estimators.synthetic.draw`): the reported attitude is
        ``C_meas = exp([dh e_up]x) @ C_enu_body @ exp([(dp, dr, 0)]x)``, i.e. a heading error
        ``dh`` about ENU up (``C.T @ e_up`` in body) and pitch and roll errors ``dp``, ``dr``
        about body x and body y (Li 2020: pitch about x, roll about y), all independent. Then
        ``C_meas = C_enu_body @ exp([delta]x)`` with the body-frame error
        ``delta = dh C.T e_up + dp e_x + dr e_y``, whose covariance this returns.
        """
        up_b = C_enu_body[:, 2, :]  # row 2 of C_enu_body = C.T @ e_up
        out = self.sigma_heading_rad**2 * up_b[:, :, None] * up_b[:, None, :]
        out = out + np.diag([self.sigma_pitch_rad**2, self.sigma_roll_rad**2, 0.0])
        return out


@dataclass(frozen=True)
class EstimationProblem:
    """One estimation problem: aligned samples plus everything the caller asked for.

    Attributes
    ----------
    t_ns : ndarray int64 (N,)
        Magnetometer stamps.
    mag_nT : ndarray (N, 3)
        Magnetometer, frame mag.
    q_enu_body : ndarray (N, 4)
        Attitude at ``t - time_offset0_s``.
    time_offset0_s : float
        The ``tau`` the attitude was interpolated with.
    attitude : AttitudeSeries or None
        The raw attitude series (to re-interpolate at ``t - tau`` when ``tau`` is estimated).
    terms : frozenset of EstimateTerm
    reference_field_enu_nT : ndarray (3,) or None
        A known background field; with it ``B`` is fixed.
    R_nominal_body_mag : ndarray (3, 3) or None
    robust : RobustLoss
    noise : NoiseModel or None
        ``None``: isotropic unknown noise, the covariance is scaled by the residual variance.

    """

    t_ns: NDArray[np.int64]
    mag_nT: F64
    q_enu_body: F64
    time_offset0_s: float = 0.0
    attitude: AttitudeSeries | None = None
    terms: frozenset = frozenset()
    reference_field_enu_nT: F64 | None = None
    R_nominal_body_mag: F64 | None = None
    robust: RobustLoss = RobustLoss.NONE
    noise: NoiseModel | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(self.t_ns) < 10:
            raise EstimationError(
                f"only {len(self.t_ns)} magnetometer samples with an attitude",
                hint="a calibration needs a recording with motion and at least a few seconds "
                "of overlapping magnetometer and attitude data",
            )
        if not np.all(np.isfinite(self.mag_nT)) or not np.all(np.isfinite(self.q_enu_body)):
            raise EstimationError("magnetometer or attitude samples contain NaN or inf")

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(len(self.t_ns))

    @property
    def C_enu_body(self) -> F64:
        """Attitude matrices, (N, 3, 3)."""
        return quat_to_matrix(self.q_enu_body)


@runtime_checkable
class Estimator(Protocol):
    """The plug-in point: anything that turns an :class:`EstimationProblem` into a calibration."""

    def fit(self, problem: EstimationProblem) -> Calibration:
        """Estimate the calibration."""
        ...


# ------------------------------------------------------------------------------- helpers
def interpolate_q(attitude: AttitudeSeries, t_ns: NDArray[np.int64], offset_s: float) -> F64:
    """Interpolate the attitude at ``t - offset_s`` (clamped at the ends), shape (N, 4).

    THE interpolator (:class:`pipeline.model.attitude.AttitudeInterpolator`), every gap
    bridged: used while iterating on ``tau`` over samples already known to have an attitude.
    """
    it = AttitudeInterpolator.of(attitude, max_gap_s=np.inf, clamp=True)
    return it.at(t_ns, offset_s).q_enu_body


def wahba(a: F64, b: F64, w: F64 | None = None) -> F64:
    """Rotation ``R`` minimising ``sum w_i |b_i - R a_i|^2`` (Kabsch / SVD), shape (3, 3)."""
    w = np.ones(len(a)) if w is None else w
    H = (b * w[:, None]).T @ a
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt)) or 1.0
    return U @ np.diag([1.0, 1.0, d]) @ Vt


def cube_rotations() -> F64:
    """Return the 24 proper rotations that permute and flip axes, (24, 3, 3)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            M = np.zeros((3, 3))
            for r, c in enumerate(perm):
                M[r, c] = signs[r]
            if np.linalg.det(M) > 0:
                out.append(M)
    return np.array(out)


def init_rotation(
    mag_nT: F64,
    C_enu_body: F64,
    B_ref: F64 | None,
    candidates: F64 | None = None,
    iterations: int = 8,
) -> tuple[F64, F64]:
    """Closed-form start for ``R_body_mag`` and ``B_enu`` that converges from any mounting.

    With a reference field: Wahba between ``y_i`` and ``C_i.T @ B_ref`` (one SVD). Without:
    for each candidate start (the 24 axis permutations and, when given, the nominal mounting)
    ``B = mean(C R y)``; the candidate with the smallest spread of the restored field wins, then
    a few alternations ``R = Wahba(y, C.T B)``, ``B = mean(C R y)``. The mean of ``C y`` from
    identity is a poor guess under a large misalignment; the candidate search avoids that.

    Returns
    -------
    R_body_mag : ndarray (3, 3)
    B_enu_nT : ndarray (3,)

    """
    y = mag_nT
    if B_ref is not None:
        b_body = np.einsum("nji,j->ni", C_enu_body, B_ref)
        return wahba(y, b_body), np.asarray(B_ref, float)
    cands = cube_rotations() if candidates is None else candidates
    # All candidates at once: restored fields e (K, N, 3), their spread about the mean.
    n = len(y)
    # e_k[n, i] = sum_jl C[n, i, j] y[n, l] R_k[j, l]: one matrix product over (j, l).
    T = (C_enu_body[:, :, :, None] * y[:, None, None, :]).reshape(n * 3, 9)
    e = (T @ cands.reshape(len(cands), 9).T).reshape(n, 3, len(cands)).transpose(2, 0, 1)
    Bk = e.mean(1)
    cost = np.mean(np.sum((e - Bk[:, None, :]) ** 2, 2), 1)
    best = int(np.argmin(cost))
    R, B = cands[best], Bk[best]
    for _ in range(iterations):
        b_body = np.einsum("nji,j->ni", C_enu_body, B)
        R = wahba(y, b_body)
        B = np.einsum("nij,nj->ni", C_enu_body, y @ R.T).mean(0)
    return R, B


def irls_weights(r_norm: F64, loss: RobustLoss, scale: float | None = None) -> F64:
    """IRLS weights for the per-sample whitened residual norms.

    Huber (k = 1.345) and Cauchy (k = 2.385) on ``r / s`` where ``s`` is the given scale or a
    robust one (1.4826 x median absolute norm, per component, i.e. divided by sqrt(3)).
    """
    if loss is RobustLoss.NONE:
        return np.ones_like(r_norm)
    s = scale if scale is not None else 1.4826 * float(np.median(r_norm)) / np.sqrt(3.0) * 1.2
    s = max(s, 1e-12)
    u = r_norm / s
    if loss is RobustLoss.HUBER:
        k = 1.345 * np.sqrt(3.0)
        return np.where(u <= k, 1.0, k / np.maximum(u, 1e-300))
    k = 2.385 * np.sqrt(3.0)
    return 1.0 / (1.0 + (u / k) ** 2)


@dataclass(frozen=True)
class Analysis:
    """Covariance and observability of a least-squares fit.

    Attributes
    ----------
    cov : ndarray (P, P)
        Parameter covariance (pseudo-inverse; zero along unobservable directions).
    null_dirs : ndarray (P, K)
        Unobservable directions of the full parameter vector (scaled back to parameters).
    block_null : dict of str -> ndarray (nb, k)
        Per block, the unobservable directions in that block's coordinates.
    block_ratio : dict of str -> ndarray (nb,)
        Per block, the generalised eigenvalues (fraction of information kept), ascending.

    """

    cov: F64
    null_dirs: F64
    block_null: dict
    block_ratio: dict


def solve_truncated(H: F64, g: F64, threshold: float = RELATIVE_INFO_THRESHOLD) -> F64:
    """``pinv(H) @ g`` with Jacobi scaling and eigenvalues below ``threshold`` x max dropped.

    Steps then never move along directions the data cannot determine: those parameters stay
    at their initial (prior) value instead of drifting on noise.
    """
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / d[:, None] / d[None, :]
    w, V = np.linalg.eigh(Hs)
    keep = w > threshold * max(w[-1], 1e-300)
    inv = (V[:, keep] / w[keep]) @ V[:, keep].T
    return (inv @ (g / d)) / d


def _eigh_generalised(A: F64, B: F64) -> tuple[F64, F64]:
    """Solve ``A v = lambda B v`` (A symmetric, B symmetric positive definite), ascending.

    Through the Cholesky factor ``B = L L.T``: ``L^-1 A L^-T y = lambda y``, ``v = L^-T y``.
    numpy only (scipy.linalg's import alone costs a calibration a quarter of a second).
    """
    L = np.linalg.cholesky(B)
    Li = np.linalg.inv(L)
    A2 = Li @ A @ Li.T
    lam, y = np.linalg.eigh(0.5 * (A2 + A2.T))
    return lam, Li.T @ y


def analyse(
    H: F64, blocks: dict[str, slice], threshold: float = RELATIVE_INFO_THRESHOLD
) -> Analysis:
    """Covariance (``H`` is the whitened information ``J.T J``) and observability per block.

    For each block ``b`` the marginal information ``M_b = H_bb - H_bo H_oo^+ H_ob`` is compared
    with ``H_bb`` through the generalised eigenproblem ``M_b v = lambda H_bb v``: lambda is the
    fraction of a direction's information that survives not knowing the other parameters.
    """
    P = H.shape[0]
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / d[:, None] / d[None, :]
    w, V = np.linalg.eigh(Hs)
    keep = w > threshold * max(w[-1], 1e-300)
    cov = ((V[:, keep] / w[keep]) @ V[:, keep].T) / d[:, None] / d[None, :]
    null = V[:, ~keep] / d[:, None]
    block_null: dict = {}
    block_ratio: dict = {}
    idx = np.arange(P)
    for name, sl in blocks.items():
        b = idx[sl]
        if b.size == 0:
            continue
        nb = len(b)
        lam_all, vec, live, zero_info = _block_eig(H, b, threshold)
        nul_list = [np.eye(nb)[:, i] for i in np.flatnonzero(zero_info)]
        for j in np.flatnonzero(lam_all[live] < threshold):
            full = np.zeros(nb)
            full[live] = vec[:, j]
            nul_list.append(full)
        block_ratio[name] = np.sort(lam_all)
        # Directions with no information at all (H v = 0 inside the block) make the
        # generalised problem 0 = lambda * 0; take them from the null space of the full H.
        Vs = V[:, ~keep]
        for j in range(Vs.shape[1]):  # type: ignore[assignment]  # j: an index, as above
            part = Vs[b, j]
            if np.linalg.norm(part) > 0.1:
                nul_list.append(part / d[b])
        nul = np.zeros((nb, 0))
        if nul_list:
            A = np.stack([v / np.linalg.norm(v) for v in nul_list], 1)
            U, sv, _ = np.linalg.svd(A, full_matrices=False)
            nul = U[:, sv > 1e-6 * sv[0]]
        block_null[name] = nul
    return Analysis(cov, null, block_null, block_ratio)


def _block_eig(H: F64, b: np.ndarray, threshold: float) -> tuple[F64, F64, np.ndarray,
                                                                 np.ndarray]:
    """Solve the generalised eigenproblem ``M_b v = lambda H_bb v`` of block ``b`` (analyse).

    Returns ``lambda`` per coordinate of the block (zero where it has no information at
    all), the unit eigenvectors of the informed coordinates, their indices and the mask of
    the uninformed ones.
    """
    idx = np.arange(H.shape[0])
    o = np.setdiff1d(idx, b)
    Hbb = H[np.ix_(b, b)]
    if o.size:
        Hoo = H[np.ix_(o, o)]
        Hob = H[np.ix_(o, b)]
        Ho_inv = solve_many_truncated(Hoo, Hob, threshold)
        M = Hbb - Hob.T @ Ho_inv
    else:
        M = Hbb
    M = 0.5 * (M + M.T)
    hd = np.diag(Hbb)
    zero_info = hd <= 1e-20 * max(float(np.max(np.diag(H))), 1e-300)
    lam_all = np.zeros(len(b))
    live = np.flatnonzero(~zero_info)
    vec = np.zeros((0, 0))
    if live.size:
        db = np.sqrt(hd[live])
        Bn = Hbb[np.ix_(live, live)] / db[:, None] / db[None, :]
        Mn = M[np.ix_(live, live)] / db[:, None] / db[None, :]
        lam, vec = _eigh_generalised(Mn, Bn + 1e-12 * np.eye(live.size))
        vec = vec / db[:, None]
        vec = vec / np.linalg.norm(vec, axis=0, keepdims=True)
        lam_all[live] = lam
    return lam_all, vec, live, zero_info


def information_ratio(H: F64, block: slice, threshold: float = RELATIVE_INFO_THRESHOLD) -> F64:
    """``analyse(H, {name: block}).block_ratio[name]`` without the covariance and null space.

    The same numbers (the same computation), for callers that need only how much of a
    block's information survives the other parameters (one factorization of ``H`` less).
    """
    return np.sort(_block_eig(H, np.arange(H.shape[0])[block], threshold)[0])


def solve_many_truncated(H: F64, G: F64, threshold: float) -> F64:
    """``pinv(H) @ G`` (columns of G) with the truncation of :func:`solve_truncated`."""
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / d[:, None] / d[None, :]
    w, V = np.linalg.eigh(Hs)
    keep = w > threshold * max(w[-1], 1e-300)
    inv = (V[:, keep] / w[keep]) @ V[:, keep].T
    return (inv @ (G / d[:, None])) / d[:, None]


def sigma_with_null(cov_block: F64, null: F64, tol: float = 1e-3) -> F64:
    """1-sigma per coordinate; ``inf`` where an unobservable direction has a component."""
    s = np.sqrt(np.maximum(np.diag(cov_block), 0.0))
    if null.size:
        touched = np.any(np.abs(null) > tol, axis=1)
        s = np.where(touched, np.inf, s)
    return s


def canonical_axis(v: F64) -> F64:
    """Return a unit axis with a deterministic sign (largest component positive)."""
    v = np.asarray(v, float)
    v = v / np.linalg.norm(v)
    return v if v[np.argmax(np.abs(v))] > 0 else -v


def rotation_words(axes: list[F64], has_reference: bool) -> str:
    """Word the warning for unobservable rotation axes, saying what would fix it."""
    ax = "; ".join("[" + ", ".join(f"{c:+.3f}" for c in a) + "]" for a in axes)
    if len(axes) >= 3:
        return (
            "the rotation is not determined by these data (no usable motion): record rotations "
            "about at least two different axes"
        )
    fix = (
        "rotate about a second, different axis"
        if has_reference
        else "rotate about a second, different axis or give a reference field "
        "(--reference-field or --igrf)"
    )
    return (
        f"the rotation about body axis {ax} is not observable from this motion (it was kept at "
        f"its initial value and its sigma is reported as infinite): {fix}"
    )


def skew_rows(b: F64) -> F64:
    """``[b_i]x`` for each row, (N, 3, 3)."""
    return skew(b)

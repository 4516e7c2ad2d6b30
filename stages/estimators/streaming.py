"""Streaming calibration: the misalignment from fixed-size sufficient statistics.

For a recording too large for memory, the magnetometer and the attitude are read a chunk at
a time (:func:`pipeline.io.mcap_read.iter_recording_chunks`), brought onto common stamps
(:func:`iter_aligned_chunks`) and reduced to a fixed set of sums (:class:`SufficientStats`,
122 numbers whatever the length of the recording). The model is the rotation part of the ML
model of :mod:`stages.estimators.ml` with isotropic magnetometer noise (CONVENTIONS,
``D = I``, ``tau = 0``)::

    y_i = R_body_mag.T @ C_enu_body_i.T @ B_enu + o + e_i,    e_i ~ N(0, sigma^2 I)

(Li 2020, Eq. 1, with the hard-iron offset ``o`` of CONVENTIONS). Because ``C_i`` and ``R``
are orthogonal, ``|r_i|^2 = |C_i R (y_i - o) - B|^2``, so the cost, its gradient and the
Gauss-Newton normal equations ``J^T J``, ``J^T r`` at *any* state are linear in

- ``n``, ``sum_y = sum y_i``, ``sum_yy = sum |y_i|^2``,
- ``S = sum C_i`` (3x3), ``M[a, b, c] = sum C_i[a, b] y_i[c]`` (3x3x3),
- ``W[a, b, c, d] = sum C_i[a, b] C_i[c, d]`` (3x3x3x3).

One pass over the data accumulates them (chunks are merged by addition, so chunks may also
be reduced in parallel); Gauss-Newton then iterates on the sums alone, without touching the
data again. The solution is the least-squares (= ML under isotropic Gaussian magnetometer
noise) estimate; the in-memory ML estimator additionally weights each sample by the
attitude noise, which this reduction leaves out.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import cast

import numpy as np
from numpy.typing import NDArray

from pipeline.core.errors import EstimationError
from pipeline.core.geometry import quat_to_matrix, skew, so3_exp
from pipeline.model.calibration import Calibration
from pipeline.model.solve import Linearised, minimise

F64 = NDArray[np.float64]

#: relative eigenvalue of the rotation information below which an axis is unobservable
UNOBSERVABLE_RATIO = 1e-8
ESTIMATOR_NAME = "ml-streaming"


def _zeros(*shape: int) -> F64:
    return np.zeros(shape)


@dataclass(frozen=True)
class SufficientStats:
    """Sums over samples that determine the least-squares cost at every state.

    Attributes
    ----------
    n : int
        Number of samples.
    sum_y : ndarray (3,)
        Sum of the magnetometer readings, nT, mag frame.
    sum_yy : float
        Sum of their squared norms, nT^2.
    S : ndarray (3, 3)
        Sum of ``C_enu_body``.
    M : ndarray (3, 3, 3)
        ``M[a, b, c] = sum C_enu_body[a, b] * y[c]``, nT.
    W : ndarray (3, 3, 3, 3)
        ``W[a, b, c, d] = sum C_enu_body[a, b] * C_enu_body[c, d]``.
    t_first_ns, t_last_ns : int
        First and last stamp seen (for reporting only).

    """

    n: int = 0
    sum_y: F64 = field(default_factory=lambda: _zeros(3))
    sum_yy: float = 0.0
    S: F64 = field(default_factory=lambda: _zeros(3, 3))
    M: F64 = field(default_factory=lambda: _zeros(3, 3, 3))
    W: F64 = field(default_factory=lambda: _zeros(3, 3, 3, 3))
    t_first_ns: int | None = None
    t_last_ns: int | None = None

    @classmethod
    def from_samples(
        cls, q_enu_body: F64, mag_nT: F64, t_ns: NDArray[np.int64] | None = None
    ) -> SufficientStats:
        """Reduce one chunk of aligned samples.

        Parameters
        ----------
        q_enu_body : ndarray (N, 4)
            Attitude at the magnetometer stamps, scalar-last.
        mag_nT : ndarray (N, 3)
            Magnetometer readings, nT, mag frame.
        t_ns : ndarray (N,) of int64, optional
            Stamps, only to remember the span.

        """
        q = np.asarray(q_enu_body, dtype=float).reshape(-1, 4)
        y = np.asarray(mag_nT, dtype=float).reshape(-1, 3)
        if len(q) != len(y):
            raise EstimationError(f"{len(q)} attitudes for {len(y)} magnetometer samples")
        C = quat_to_matrix(q).reshape(-1, 9)  # (N, 9): C_enu_body row-major
        span: tuple[int, int] | tuple[None, None] = (None, None)
        if t_ns is not None and len(t_ns):
            span = (int(np.min(t_ns)), int(np.max(t_ns)))
        return cls(
            n=len(y),
            sum_y=y.sum(axis=0),
            sum_yy=float(np.einsum("ij,ij->", y, y)),
            S=C.sum(axis=0).reshape(3, 3),
            # (9, N) @ (N, 3) and (9, N) @ (N, 9): BLAS, no (N, 27) or (N, 81) temporaries
            M=(C.T @ y).reshape(3, 3, 3),
            W=(C.T @ C).reshape(3, 3, 3, 3),
            t_first_ns=span[0],
            t_last_ns=span[1],
        )

    def __add__(self, other: SufficientStats) -> SufficientStats:
        """Merge the sums of two disjoint sets of samples."""
        firsts = [t for t in (self.t_first_ns, other.t_first_ns) if t is not None]
        lasts = [t for t in (self.t_last_ns, other.t_last_ns) if t is not None]
        return SufficientStats(
            n=self.n + other.n,
            sum_y=self.sum_y + other.sum_y,
            sum_yy=self.sum_yy + other.sum_yy,
            S=self.S + other.S,
            M=self.M + other.M,
            W=self.W + other.W,
            t_first_ns=min(firsts) if firsts else None,
            t_last_ns=max(lasts) if lasts else None,
        )


def accumulate(chunks: Iterable[tuple[F64, F64] | tuple[F64, F64, NDArray[np.int64]]]
               ) -> SufficientStats:
    """Sum :meth:`SufficientStats.from_samples` over ``(q_enu_body, mag_nT[, t_ns])`` chunks."""
    total = SufficientStats()
    for chunk in chunks:
        total = total + SufficientStats.from_samples(*chunk)
    return total


# ------------------------------------------------------------------------------ the model
@dataclass(frozen=True)
class _State:
    R: F64  # R_body_mag
    B: F64  # B_enu_nT
    o: F64  # offset_nT (zeros when not estimated)


def _T(st: SufficientStats, R: F64) -> F64:
    """``sum_i C_i @ R @ y_i`` (3,)."""
    return np.einsum("abc,bc->a", st.M, R)


def cost(st: SufficientStats, R: F64, B: F64, o: F64) -> float:
    """Sum of squared residuals ``sum |y_i - o - R.T C_i.T B|^2``, nT^2, from the sums."""
    SRo = st.S @ R @ o
    c = (st.sum_yy - 2.0 * o @ st.sum_y + st.n * o @ o
         - 2.0 * B @ (_T(st, R) - SRo) + st.n * B @ B)
    return max(float(c), 0.0)


def normal_equations(st: SufficientStats, s: _State) -> tuple[F64, F64]:
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


def _sum_m_cross_y(st: SufficientStats, R: F64, B: F64) -> F64:
    """``sum_i m_i x y_i`` with ``m_i = R.T C_i.T B``: ``P[k, l] = sum_i m_ik y_il``."""
    P = np.einsum("ak,b,bal->kl", R, B, st.M)
    return np.einsum("jkl,kl->j", _eps(), P)


def _solve_linear(st: SufficientStats, R: F64, B_fixed: F64 | None, with_offset: bool
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
        RMS of the residual vector norms.
    n_samples : int
    unobservable_axes_body : tuple of ndarray (3,)
    iterations : int

    """

    R_body_mag: F64
    B_enu_nT: F64
    offset_nT: F64 | None
    cov: F64
    residual_rms_nT: float
    n_samples: int
    unobservable_axes_body: tuple[F64, ...]
    iterations: int

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
        )


def fit_stats(
    st: SufficientStats,
    *,
    estimate_offset: bool = False,
    reference_field_enu_nT: F64 | None = None,
    R_nominal_body_mag: F64 | None = None,
    max_iter: int = 50,
) -> StreamingFit:
    """Gauss-Newton (Levenberg-damped, THE solver core) on the sufficient statistics alone.

    Parameters
    ----------
    st : SufficientStats
        Sums over all samples.
    estimate_offset : bool
        Estimate the hard-iron offset ``o`` (mag frame, nT).
    reference_field_enu_nT : ndarray (3,), optional
        Known background field; estimated when ``None``.
    R_nominal_body_mag : ndarray (3, 3), optional
        Starting rotation; by default the best of the 24 axis-aligned rotations.
    max_iter : int
        Gauss-Newton iterations.

    Raises
    ------
    EstimationError
        Too few samples.

    """
    if st.n < 10:
        raise EstimationError(f"only {st.n} aligned samples: too few to calibrate")
    B_fixed = None if reference_field_enu_nT is None else np.asarray(
        reference_field_enu_nT, dtype=float).reshape(3)
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
        residual_rms_nT=float(np.sqrt(c / st.n)),
        n_samples=st.n,
        unobservable_axes_body=tuple(a / np.linalg.norm(a) for a in axes),
        iterations=iterations,
    )


def _nearest_about_axis(st: SufficientStats, s: _State, axis_body: F64, R_nominal: F64 | None,
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


# ------------------------------------------------------------------------------ chunked I/O
def iter_aligned_chunks(
    chunks: Iterable, *, max_gap_s: float = 0.1
) -> Iterator[tuple[F64, F64, NDArray[np.int64]]]:
    """Bring chunks of a recording onto the magnetometer stamps, chunk by chunk.

    Parameters
    ----------
    chunks : iterable of objects with ``mag`` (VectorSeries) and ``attitude``
        (AttitudeSeries or None), such as :func:`pipeline.io.mcap_read.iter_recording_chunks`.
        Within a chunk samples need not be sorted; across chunks stamps must advance.
    max_gap_s : float
        Attitude gap bridged by THE interpolator (:func:`stages.resample.interpolate_attitude`).

    Yields
    ------
    (q_enu_body (N, 4), mag_nT (N, 3), t_ns (N,))
        Magnetometer samples with a usable attitude. A magnetometer sample later than the
        last attitude sample seen so far waits for the next chunk; the last attitude sample
        of a chunk is kept to bracket the first magnetometer samples of the next.

    """
    from pipeline.core.recording import AttitudeSeries
    from pipeline.model.attitude import interpolate_attitude

    att_t = np.zeros(0, np.int64)
    att_q = np.zeros((0, 4))
    mag_t = np.zeros(0, np.int64)
    mag_v = np.zeros((0, 3))
    for ch in chunks:
        if ch.attitude is not None and len(ch.attitude):
            att_t = np.concatenate([att_t, ch.attitude.t_ns])
            att_q = np.concatenate([att_q, ch.attitude.q_enu_body])
            o = np.argsort(att_t, kind="stable")
            att_t, att_q = att_t[o], att_q[o]
        mag_t = np.concatenate([mag_t, ch.mag.t_ns])
        mag_v = np.concatenate([mag_v, ch.mag.values])
        if len(att_t) < 2:
            continue
        ready = mag_t <= att_t[-1]
        if ready.any():
            t_r = mag_t[ready]
            q, ok = interpolate_attitude(AttitudeSeries(att_t, att_q), t_r, max_gap_s=max_gap_s)
            if ok.any():
                yield q[ok], mag_v[ready][ok], t_r[ok]
            mag_t, mag_v = mag_t[~ready], mag_v[~ready]
        # keep the attitude samples that can still bracket the waiting magnetometer samples
        keep_from = len(att_t) - 1
        if len(mag_t):
            keep_from = min(keep_from, max(int(np.searchsorted(att_t, mag_t.min())) - 1, 0))
        att_t, att_q = att_t[keep_from:], att_q[keep_from:]
    # magnetometer samples after the last attitude sample have no attitude: dropped


def calibrate_streaming(
    path: str,
    *,
    estimate_offset: bool = False,
    reference_field_enu_nT: F64 | None = None,
    max_messages: int = 200_000,
    max_gap_s: float = 0.1,
    mag_topic: str | None = None,
    attitude_topic: str | None = None,
) -> Calibration:
    """Calibrate a recording of any length in bounded memory (one pass over the file).

    Parameters
    ----------
    path : str
        The MCAP recording.
    estimate_offset : bool
        Estimate the hard-iron offset.
    reference_field_enu_nT : ndarray (3,), optional
        Known background field.
    max_messages : int
        Messages decoded per chunk (memory bound: about 100 bytes per message).
    max_gap_s : float
        Attitude gap bridged by interpolation.
    mag_topic, attitude_topic : str, optional
        Channels, as for :func:`pipeline.io.mcap_read.read_recording`.

    """
    from pipeline.io.mcap_read import iter_recording_chunks

    chunks = iter_recording_chunks(path, max_messages=max_messages, mag_topic=mag_topic,
                                   attitude_topic=attitude_topic)
    st = accumulate(iter_aligned_chunks(chunks, max_gap_s=max_gap_s))
    return fit_stats(st, estimate_offset=estimate_offset,
                     reference_field_enu_nT=reference_field_enu_nT).to_calibration()

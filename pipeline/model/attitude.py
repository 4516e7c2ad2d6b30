"""THE attitude interpolator: a C1 cubic on SO(3) between the attitude samples, with the gap rule.

More in docs/modules.md, ``pipeline.model.attitude``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import cast

import numpy as np
from numpy.typing import NDArray

from pipeline.core.geometry import (
    norm_last,
    quat_conj,
    quat_mul,
    quat_normalize,
    quat_to_matrix,
    quat_to_rotvec,
    rotvec_to_quat,
)
from pipeline.model.attitude_kernels import cubic_at

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B8 = NDArray[np.bool_]

#: lower bound of the automatic gap threshold, s
MIN_AUTO_GAP_S = 0.05
#: automatic gap threshold in median attitude intervals
AUTO_GAP_INTERVALS = 5.0


def increments(q_enu_body: F64) -> F64:
    """Rotation vectors ``Log(q_k^* q_{k+1})`` (rad, body frame, short way round), (M-1, 3)."""
    q = np.asarray(q_enu_body, dtype=float)
    dq = quat_mul(quat_conj(q[:-1]), q[1:])
    return quat_to_rotvec(np.where(dq[:, 3:4] < 0, -dq, dq))


def estimate_cubic_weight(t_ns: I64, q_enu_body: F64) -> float:
    """``lam`` of (A7) from the track's second differences at lags 1 and 2 (0..1).

    Only runs of evenly spaced samples (each interval within 10 % of the median) count, so
    gaps and the gap rule do not change it.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    if len(t) < 12:
        return 0.0
    return _cubic_weight(increments(q_enu_body), np.diff(t).astype(float))


def _cubic_weight(phi: F64, dt: F64) -> float:
    """:func:`estimate_cubic_weight` from the increments ``phi`` (M-1, 3) and spacings ``dt``."""
    if len(phi) < 11:
        return 0.0
    med = float(np.median(dt))
    if med <= 0:
        return 0.0
    even = np.abs(dt - med) <= 0.1 * med
    # lag 1: phi_k - phi_{k-1}; lag 2: (phi_{k+2} + phi_{k+3}) - (phi_k + phi_{k+1})
    ok1 = even[1:] & even[:-1]
    d1 = (phi[1:] - phi[:-1])[ok1]
    ok2 = even[:-3] & even[1:-2] & even[2:-1] & even[3:]
    d2 = ((phi[2:-1] + phi[3:]) - (phi[:-3] + phi[1:-2]))[ok2]
    if len(d1) < 10 or len(d2) < 10:
        return 0.0
    n1, n2 = np.sum(d1 * d1, axis=1), np.sum(d2 * d2, axis=1)
    e1, e2 = float(np.mean(n1)), float(np.mean(n2))
    # the curvature only where it stands out of the noise of its own estimate (3 sigma)
    se = float(np.sqrt(np.var(n1) / len(n1) + np.var(n2) / len(n2))) / 15.0
    M = max((e2 - e1) / 15.0 - 3.0 * se, 0.0)
    s2 = max((e1 - M) / 6.0, 0.0) / len(d1)  # the noise's share of a parameter's error
    den = M / 120.0 + s2 / 70.0
    if den <= 0:
        return 0.0
    return float(np.clip((M / 120.0 - s2 / 15.0) / den, 0.0, 1.0))


def mean_interpolation_noise_factor(cubic_weight: float = 1.0) -> float:
    """Mean over ``s`` of :func:`interpolation_noise_factor`: ``2/3 + 2 lam/15 + lam^2/70``."""
    lam = float(cubic_weight)
    return 2.0 / 3.0 + 2.0 * lam / 15.0 + lam * lam / 70.0


def _cross(a: F64, b: F64) -> F64:
    """Row-wise ``a x b`` of (N, 3) arrays (np.cross without its per-call overhead)."""
    ax, ay, az = a[:, 0], a[:, 1], a[:, 2]
    bx, by, bz = b[:, 0], b[:, 1], b[:, 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=1)


def right_jacobian_apply(r: F64, v: F64) -> F64:
    """``Jr(r) v`` of SO(3) row by row, (N, 3), for rotation vectors ``r`` (N, 3).

    ``Jr(r) = I - a [r]x + b [r]x^2`` (Sola 2018, Eq. 143) applied without forming the
    matrices: ``[r]x v = r x v``.
    """
    th = norm_last(r)[:, None]
    small = th < 1e-6
    t = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0 - th**2 / 120.0, (t - np.sin(t)) / t**3)
    rv = _cross(r, v)
    return v - a * rv + b * _cross(r, rv)


def right_jacobian_inv_apply(r: F64, v: F64) -> F64:
    """``Jr(r)^-1 v`` of SO(3) row by row, (N, 3) (Sola 2018, Eq. 144)."""
    th = norm_last(r)[:, None]
    small = th < 1e-4
    t = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12.0 + th**2 / 720.0,
                 1.0 / t**2 - (1.0 + np.cos(t)) / (2.0 * t * np.sin(t)))
    rv = _cross(r, v)
    return v + 0.5 * rv + c * _cross(r, rv)


def auto_max_gap_s(t_ns: I64) -> float:
    """Default gap threshold: ``max(0.05 s, 5 x median attitude interval)``, s.

    Parameters
    ----------
    t_ns : ndarray of int64, shape (M,)
        Attitude stamps, ns (need not be sorted).

    """
    t = np.asarray(t_ns)
    d = np.diff(t)
    if not bool(np.all(d > 0)):  # sorted without duplicates (what ingest gives) skips the sort
        t = np.unique(t)
        d = np.diff(t)
    if len(t) < 2:
        return MIN_AUTO_GAP_S
    return max(MIN_AUTO_GAP_S, AUTO_GAP_INTERVALS * float(np.median(d)) * 1e-9)


@dataclass(frozen=True)
class Interpolated:
    """The attitude at query times.

    Attributes
    ----------
    q_enu_body : ndarray, shape (N, 4)
        Unit quaternions, scalar-last; NaN where not ``valid``.
    valid : ndarray of bool, shape (N,)
        False outside the attitude span or inside a gap longer than ``max_gap_s``.
    omega_body_rad_s : ndarray, shape (N, 3)
        Angular velocity of the interpolated attitude, body frame, rad/s (exact derivative
        of the cubic, (A6)); NaN where not ``valid``.
    position : ndarray, shape (N,)
        Where each query falls between its two bracketing samples, 0..1 (``s`` above).

    """

    q_enu_body: F64
    valid: B8
    position: F64
    #: computes ``omega_body_rad_s`` on first use (most queries need the attitude only)
    _omega: Callable[[], F64] = field(repr=False, compare=False)
    #: ``C.T`` (N, 3, 3) where the compiled pass gave it (None: :attr:`Ct` computes it)
    _Ct: F64 | None = field(default=None, repr=False, compare=False)

    @cached_property
    def Ct(self) -> F64:
        """``C_enu_body.T`` (N, 3, 3), the transposed rotation matrices; NaN where not valid."""
        return self._Ct if self._Ct is not None else quat_to_matrix(self.q_enu_body,
                                                                   transposed=True)

    @cached_property
    def omega_body_rad_s(self) -> F64:
        """Angular velocity, body frame, rad/s, (N, 3) (A6); NaN where not ``valid``."""
        return self._omega()


class AttitudeInterpolator:
    """The C1 cubic of ``q_enu_body`` samples (docs/modules.md), built once per series.

    Parameters
    ----------
    t_ns : ndarray of int64, shape (M,)
        Attitude stamps, ns. Need not be sorted; duplicated stamps keep their first sample.
    q_enu_body : ndarray, shape (M, 4)
        Unit quaternions (Hamilton, scalar-last) rotating body vectors into ENU.
    max_gap_s : float or None
        Longest interval between two samples bridged, s; ``None``: :func:`auto_max_gap_s`.
        ``inf`` bridges every gap.
    clamp : bool
        Hold the first / last sample outside the span (and count those queries valid)
        instead of marking them invalid.
    cubic_weight : float or None
        ``lam`` of (A7); ``None``: :func:`estimate_cubic_weight` from the samples.
    step_s : float or None
        The series' sample spacing (:attr:`step_s`); ``None``: the median of these samples'.

    """

    def __init__(self, t_ns: I64, q_enu_body: F64, max_gap_s: float | None = None,
                 clamp: bool = False, cubic_weight: float | None = None,
                 step_s: float | None = None):
        self._step_s = None if step_s is None else float(step_s)
        ta = np.asarray(t_ns, dtype=np.int64)
        qa = np.asarray(q_enu_body, dtype=float).reshape(-1, 4)
        if len(ta) and np.any(np.diff(ta) <= 0):
            order = np.argsort(ta, kind="stable")
            ta, qa = ta[order], qa[order]
            keep = np.concatenate([[True], np.diff(ta) > 0])
            ta, qa = ta[keep], qa[keep]
        self.t_ns = ta
        self.q_enu_body = qa
        self.max_gap_s = auto_max_gap_s(ta) if max_gap_s is None else float(max_gap_s)
        self.clamp = clamp
        # stamps in s from the first attitude sample: float precision (epoch ns do not fit
        # a float64 exactly) and sub-ns offsets
        self._tr = (ta - ta[0]).astype(float) * 1e-9 if len(ta) else np.zeros(0)
        if len(ta) >= 2:
            self._phi = increments(qa)  # (M-1, 3) rad, body frame, (A3)
            self._dt = np.diff(self._tr)
            self.cubic_weight = (_cubic_weight(self._phi, self._dt) if cubic_weight is None
                                 else float(cubic_weight))
            self._a, self._b = self._tangents()
        else:
            self._phi = np.zeros((0, 3))
            self._dt = np.zeros(0)
            self._a = self._b = np.zeros((0, 3))
            self.cubic_weight = 0.0

    def _tangents(self) -> tuple[F64, F64]:
        """Hermite tangents ``a_i``, ``b_i`` (M-1, 3) of every segment, (A4)-(A5)."""
        dt = self._dt
        ok = dt <= self.max_gap_s + 1e-12  # a segment the gap rule bridges
        rate = self._phi / np.where(dt > 0, dt, 1.0)[:, None]  # (M-1, 3) mean rate
        m = len(self.t_ns)
        w = np.zeros((m, 3))
        # one-sided at the ends and beside a gap, three-point inside (A5)
        left = np.zeros(m, dtype=bool)
        right = np.zeros(m, dtype=bool)
        left[1:] = ok  # node k has a usable segment k-1
        right[:-1] = ok  # node k has a usable segment k
        both = left & right
        k = np.flatnonzero(both)
        d0, d1 = dt[k - 1], dt[k]
        w[k] = (d0[:, None] * rate[k] + d1[:, None] * rate[k - 1]) / (d0 + d1)[:, None]
        only_r = right & ~left
        w[only_r] = rate[np.flatnonzero(only_r)]
        only_l = left & ~right
        w[only_l] = rate[np.flatnonzero(only_l) - 1]
        a = dt[:, None] * w[:-1]
        b = dt[:, None] * right_jacobian_inv_apply(self._phi, w[1:])
        lam = self.cubic_weight  # (A7): lam = 0 is SLERP
        return lam * a + (1.0 - lam) * self._phi, lam * b + (1.0 - lam) * self._phi

    @classmethod
    def of(cls, attitude, max_gap_s: float | None = None, clamp: bool = False
           ) -> AttitudeInterpolator:
        """Build from a :class:`pipeline.core.recording.AttitudeSeries`."""
        return cls(attitude.t_ns, attitude.q_enu_body, max_gap_s=max_gap_s, clamp=clamp)

    def noise_factor(self, position: F64) -> F64:
        """:func:`interpolation_noise_factor` at this interpolator's ``lam``, (N,)."""
        return interpolation_noise_factor(position, self.cubic_weight)

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def step_s(self) -> float:
        """Median sample spacing, s (0.01 with fewer than two samples).

        An interpolator over a piece of a long series is given the whole series' (the eddy
        regressor's difference step is a multiple of it).
        """
        if self._step_s is not None:
            return self._step_s
        return float(np.median(self._dt)) if len(self._dt) else 0.01

    def _locate(self, tq: F64, clamp: bool) -> tuple[I64, F64, B8, B8]:
        """Segment ``j``, position ``s`` in it, ``valid`` (gap rule) and ``held`` of queries."""
        tr = self._tr
        held = np.zeros(len(tq), dtype=bool)
        if clamp:
            held = (tq < tr[0]) | (tq > tr[-1])  # held end sample: no rotation
            tq = np.clip(tq, tr[0], tr[-1])
        i = np.searchsorted(tr, tq, side="right") - 1  # tr[i] <= tq < tr[i + 1]
        i = np.where(tq == tr[-1], len(tr) - 2, i)
        inside = (i >= 0) & (i < len(tr) - 1)
        j = np.clip(i, 0, len(tr) - 2)
        dt = np.take(self._dt, j)
        t_lo, t_hi = np.take(tr, j), np.take(tr, j + 1)
        on_sample = (tq == t_lo) | (tq == t_hi)
        valid = inside & ((dt <= self.max_gap_s + 1e-12) | on_sample)
        s = np.clip((tq - t_lo) / np.where(dt > 0, dt, 1.0), 0.0, 1.0)
        return j, s, valid, held

    def position_rel_s(self, tq_s: F64, *, clamp: bool | None = None) -> F64:
        """Where queries (s from the first sample) fall between two samples, 0..1, (N,).

        The ``position`` of :meth:`at_rel_s` without interpolating the attitude (0 where not
        valid).
        """
        clamp = self.clamp if clamp is None else clamp
        tq = np.asarray(tq_s, dtype=float)
        if len(self._tr) < 2 or len(tq) == 0:
            return np.zeros(len(tq))
        _, s, valid, _ = self._locate(tq, clamp)
        return np.where(valid, s, 0.0)

    def at_rel_s(self, tq_s: F64, *, clamp: bool | None = None, compiled: bool = False
                 ) -> Interpolated:
        """Return the attitude at ``tq_s``, seconds from the first attitude sample.

        ``clamp`` overrides the interpolator's own setting for this query. ``compiled``: the
        same curve by one compiled pass over the queries
        (:mod:`pipeline.model.attitude_kernels`), which also gives ``C.T``
        (:attr:`Interpolated.Ct`); for a caller that has numba loaded anyway.
        """
        clamp = self.clamp if clamp is None else clamp
        tq = np.asarray(tq_s, dtype=float)
        tr, qa = self._tr, self.q_enu_body
        n = len(tq)
        if compiled and len(tr) >= 2 and n > 0:
            return self._at_compiled(tq, clamp)
        q_out = np.full((n, 4), np.nan)
        pos = np.zeros(n)
        if len(tr) == 0 or n == 0:
            return Interpolated(q_out, np.zeros(n, dtype=bool), pos, lambda: np.full((n, 3),
                                                                                     np.nan))
        if len(tr) == 1:
            inside = np.ones(n, dtype=bool) if clamp else tq == tr[0]
            q_out[inside] = quat_normalize(qa[0])

            def still() -> F64:
                w = np.full((n, 3), np.nan)
                w[inside] = 0.0
                return w

            return Interpolated(q_out, inside, pos, still)
        j, s, valid, held = self._locate(tq, clamp)
        all_valid = bool(valid.all())
        jv = j if all_valid else j[valid]
        sv = (s if all_valid else s[valid])[:, None]
        rv = self._rotvec(jv, sv)
        qv = quat_mul(np.take(qa, jv, axis=0), rotvec_to_quat(rv))  # (A1)
        qv /= norm_last(qv, keepdims=True)
        if all_valid:
            q_out = qv
            pos = s.copy()
        else:
            q_out[valid] = qv
            pos[valid] = s[valid]
        return Interpolated(q_out, valid, pos, self._omega(jv, sv, rv, valid, held))

    def _at_compiled(self, tq: F64, clamp: bool) -> Interpolated:
        """:meth:`at_rel_s` by :func:`pipeline.model.attitude_kernels.cubic_at`."""
        q, Ct, pos, valid, held, j, rv = cubic_at(
            self._tr, self._dt, self._a, self._phi, self._b, self.q_enu_body, tq,
            self.max_gap_s, clamp)
        if not valid.all():
            j, rv = j[valid], rv[valid]
        sv = pos[valid][:, None]
        return Interpolated(q, valid, pos, self._omega(j, sv, rv, valid, held), Ct)

    def _omega(self, jv: I64, sv: F64, rv: F64, valid: B8, held: B8) -> Callable[[], F64]:
        """(A6): the exact derivative of the cubic at the valid queries, computed when asked.

        ``jv``, ``sv`` (n, 1), ``rv`` (n, 3): the valid queries' segments, positions and
        rotation vectors (the closure keeps those, not the curve's terms).
        """
        n = len(valid)

        def omega() -> F64:
            s2 = sv * sv
            a, phi, b = (np.take(x, jv, axis=0) for x in (self._a, self._phi, self._b))
            dr = (3 * s2 - 4 * sv + 1) * a + (6 * sv - 6 * s2) * phi + (3 * s2 - 2 * sv) * b
            dt = np.take(self._dt, jv)
            w = right_jacobian_apply(rv, dr) / np.where(dt > 0, dt, 1.0)[:, None]
            w_out = np.full((n, 3), np.nan)
            w_out[valid] = w
            w_out[valid & held] = 0.0
            return w_out

        return omega

    def _rotvec(self, jv: I64, sv: F64) -> F64:
        """(A2): the cubic's rotation vector in segments ``jv`` at positions ``sv`` (N, 1).

        ``np.take``: several times faster than indexing with an array for these gathers.
        """
        s2 = sv * sv
        s3 = s2 * sv
        a, phi, b = (np.take(x, jv, axis=0) for x in (self._a, self._phi, self._b))
        return cast(F64, (s3 - 2 * s2 + sv) * a + (3 * s2 - 2 * s3) * phi + (s3 - s2) * b)

    def at(self, t_ns: I64, time_offset_s: float = 0.0, *,
           clamp: bool | None = None) -> Interpolated:
        """Return the attitude at ``t - time_offset_s`` for stamps ``t_ns`` (ns since the epoch).

        ``time_offset_s`` is ``tau`` of CONVENTIONS: the sample stamped ``t`` was sensed at
        ``t - tau``. ``clamp`` overrides the interpolator's own setting for this query.
        """
        t_q = np.asarray(t_ns, dtype=np.int64)
        t0 = self.t_ns[0] if len(self.t_ns) else np.int64(0)
        tq = (t_q - t0).astype(float) * 1e-9 - float(time_offset_s)
        return self.at_rel_s(tq, clamp=clamp)


def interpolation_noise_factor(position: F64, cubic_weight: float = 1.0) -> F64:
    """Variance of interpolated white attitude noise relative to one sample's, (N,).

    To first order, with evenly spaced samples, the cubic (A1)-(A5) weighs the samples
    ``i - 1 .. i + 2`` with the Catmull-Rom weights ``(-s^3 + 2 s^2 - s) / 2``,
    ``(3 s^3 - 5 s^2 + 2) / 2``, ``(-3 s^3 + 4 s^2 + s) / 2``, ``(s^3 - s^2) / 2`` and SLERP
    with ``(0, 1 - s, s, 0)``; the blend (A7) with ``lam * CR + (1 - lam) * SLERP``.
    Independent errors of variance ``sigma^2`` reach the interpolated attitude with the
    variance ``sum(w^2) sigma^2``: 1 on a sample; on average over ``s`` 2/3 (SLERP) to 57/70
    (the cubic), :func:`mean_interpolation_noise_factor`.
    """
    s = np.asarray(position, dtype=float)
    lam = float(cubic_weight)
    s2, s3 = s * s, s * s * s
    cr = ((-s3 + 2 * s2 - s) / 2, (3 * s3 - 5 * s2 + 2) / 2, (-3 * s3 + 4 * s2 + s) / 2,
          (s3 - s2) / 2)
    sl = (0.0 * s, 1.0 - s, s, 0.0 * s)
    return sum((b + lam * (a - b)) ** 2 for a, b in zip(cr, sl, strict=True))


def interpolation_error_shape(position: F64) -> F64:
    """Shape of the interpolation error's variance between two samples, (N,), mean 8/15.

    The error of an interpolating curve vanishes on the samples and peaks midway; its
    variance goes as ``(s (1 - s))^2``, scaled here to 1 at ``s = 1/2``.
    """
    s = np.asarray(position, dtype=float)
    return 16.0 * (s * (1.0 - s)) ** 2


#: mean over ``s`` of :func:`interpolation_error_shape`
MEAN_INTERPOLATION_ERROR_SHAPE = 8.0 / 15.0


def _midway_error2(it: AttitudeInterpolator, m: int) -> F64:
    """Return the squared angles (rad^2) of the curve through every ``m``-th sample.

    Taken at the samples midway (the same ``lam``), against those samples.
    """
    t, q = it.t_ns, it.q_enu_body
    base = AttitudeInterpolator(t[0::m], q[0::m], max_gap_s=it.max_gap_s * m,
                                cubic_weight=it.cubic_weight)
    h = m // 2
    mid_t, mid_q = t[h::m], q[h::m]
    got = base.at(mid_t)
    ok = got.valid
    dq = quat_mul(quat_conj(mid_q[ok]), got.q_enu_body[ok])
    e2 = np.sum(quat_to_rotvec(np.where(dq[:, 3:4] < 0, -dq, dq)) ** 2, axis=1)
    return e2[e2 <= 100.0 * max(float(np.median(e2)), 1e-30)] if len(e2) else e2  # gaps


def interpolation_error_rad(it: AttitudeInterpolator) -> float:
    """RMS angle (rad) of the interpolator's own error midway between samples, from the track.

    The curve through every second sample is compared with the samples midway, and so is
    the curve through every fourth: the mean squared differences are ``E_2 = N + 2^(2p) e^2``
    and ``E_4 = N + 2^(4p) e^2``, ``N`` the attitude noise's share (the same at both spacings,
    so it need not be known), ``e`` the error midway at the track's own spacing and ``p`` its
    order (4 for the cubic's midway error on evenly spaced samples, 2 for SLERP, blended by
    ``lam``). ``e^2 = (E_4 - E_2) / (2^(4p) - 2^(2p))``, counted beyond three standard errors
    of the difference. Gaps and glitches (errors over 100 times the median) are left out.
    """
    if len(it) < 40:
        return 0.0
    e2, e4 = _midway_error2(it, 2), _midway_error2(it, 4)
    if len(e2) < 10 or len(e4) < 10:
        return 0.0
    p = 2.0 + 2.0 * it.cubic_weight
    se = float(np.sqrt(np.var(e2) / len(e2) + np.var(e4) / len(e4)))
    d = float(np.mean(e4) - np.mean(e2)) - 3.0 * se
    if d <= 0:
        return 0.0
    return float(np.sqrt(d / (2.0 ** (4 * p) - 2.0 ** (2 * p))))


def attitude_noise_rad(q_enu_body: F64) -> float:
    """Robust estimate of the white attitude noise of a sampled track (RMS angle, rad).

    The smaller of two estimates, each of which a motion can only inflate:

    - from the second differences of the sign-aligned quaternions: a small error ``delta``
      (rad, any axes) moves the vector part by ``delta / 2``, so for white noise
      ``E |d2|^2 = 6/4 E |delta|^2``; second differences over ten times their median (motion
      spikes) are left out. At attitude rates of 50 Hz and more a motion of a few Hz barely
      contributes;
    - from the top quarter of the spectrum of the rotation increments (0.75 to 1 times the
      Nyquist frequency): white noise differenced has the periodogram ``2 v (1 - cos w)``
      per component there, while a hand-held or vehicle motion stays well below it. This
      one holds at slow attitude rates, where the motion fills the second differences.
    """
    q = np.array(q_enu_body, dtype=float)
    if len(q) < 30:
        return 0.0
    sgn = np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0)
    q[1:] *= np.cumprod(sgn)[:, None]
    d2 = q[2:] - 2.0 * q[1:-1] + q[:-2]
    e2 = np.sum(d2[:, :3] ** 2, axis=1)
    med = float(np.median(e2))
    if med <= 0:
        return 0.0
    second = float(np.sqrt(np.mean(e2[e2 <= 10.0 * med]) / 1.5))
    phi = increments(q)
    phi = phi - phi.mean(axis=0)
    m = len(phi)
    P = np.abs(np.fft.rfft(phi, axis=0)) ** 2 / m  # (m // 2 + 1, 3)
    w = 2.0 * np.pi * np.arange(P.shape[0]) / m
    band = w >= 0.75 * np.pi
    if band.sum() < 5:
        return second
    v = float(np.mean(np.sum(P[band], axis=1) / (2.0 * (1.0 - np.cos(w[band])))))
    return min(second, float(np.sqrt(max(v, 0.0))))


def interpolate_attitude(
    attitude,
    t_ns: I64,
    *,
    time_offset_s: float = 0.0,
    max_gap_s: float = 0.1,
) -> tuple[F64, B8]:
    """Interpolate the attitude (:class:`AttitudeInterpolator`) at ``t - time_offset_s``.

    Parameters
    ----------
    attitude : AttitudeSeries
        Need not be sorted; duplicated stamps keep their first sample.
    t_ns : ndarray of int64, shape (N,)
        Query stamps (magnetometer), ns.
    time_offset_s : float
        ``tau`` of CONVENTIONS: the attitude is taken at ``t - tau``.
    max_gap_s : float
        Bracketing attitude samples further apart than this are not interpolated between.

    Returns
    -------
    q_enu_body : ndarray, shape (N, 4)
        Unit quaternions, scalar-last (NaN where not valid).
    valid : ndarray of bool, shape (N,)
        False outside the attitude span or inside a gap.

    """
    it = AttitudeInterpolator.of(attitude, max_gap_s=max_gap_s)
    r = it.at(t_ns, time_offset_s)
    return r.q_enu_body, r.valid

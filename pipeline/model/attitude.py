"""THE attitude interpolator: SLERP between the attitude samples, with the gap rule.

Every user of an attitude between its samples goes through :class:`AttitudeInterpolator`
(resampling onto the magnetometer stamps, the estimators while they iterate on ``tau``, the
diagnosis fit, restoring and the forward model), so that the same recording and model give
the same prediction everywhere.

Between two attitude samples ``q_i`` (at ``t_i``) and ``q_{i+1}`` (at ``t_{i+1}``)::

    q(t) = q_i (x) Exp(s phi_i / 2),   s = (t - t_i) / (t_{i+1} - t_i),
    phi_i = Log(q_i^* (x) q_{i+1})          (rotation vector, short way round)

(SLERP written with the right-``Exp`` of the Lie-group note: Sola, Deray & Atchuthan, "A
micro Lie theory for state estimation in robotics", 2018, Sect. III, right plus
``q (+) phi = q (x) Exp(phi)``). In matrices ``C_enu_body(t) = C_i Exp([s phi_i]x)``, so the
derivative of the interpolated attitude is exact and piecewise constant::

    d/dt C_enu_body(t) = C_enu_body(t) [omega_body]x,   omega_body = phi_i / (t_{i+1} - t_i)

(rad/s, body frame), which is what the time-offset Jacobian of :mod:`pipeline.model.forward`
uses.

Gap rule: two consecutive attitude samples further apart than ``max_gap_s`` are not
interpolated between; a query inside such a gap, or outside the span of the samples, is not
valid (a query that falls exactly on a sample is valid even beside a gap).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry import quat_conj, quat_mul, quat_normalize, quat_slerp, quat_to_rotvec

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B8 = NDArray[np.bool_]

#: lower bound of the automatic gap threshold, s
MIN_AUTO_GAP_S = 0.05
#: automatic gap threshold in median attitude intervals
AUTO_GAP_INTERVALS = 5.0


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
        of the SLERP: constant between two samples); NaN where not ``valid``.
    position : ndarray, shape (N,)
        Where each query falls between its two bracketing samples, 0..1 (``s`` above).

    """

    q_enu_body: F64
    valid: B8
    omega_body_rad_s: F64
    position: F64


class AttitudeInterpolator:
    """SLERP of ``q_enu_body`` samples (module docstring), built once per attitude series.

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

    """

    def __init__(self, t_ns: I64, q_enu_body: F64, max_gap_s: float | None = None,
                 clamp: bool = False):
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
            dq = quat_mul(quat_conj(qa[:-1]), qa[1:])
            dq = np.where(dq[:, 3:4] < 0, -dq, dq)  # short way round, as quat_slerp
            self._phi = quat_to_rotvec(dq)  # (M-1, 3) rad, body frame
            self._dt = np.diff(self._tr)
        else:
            self._phi = np.zeros((0, 3))
            self._dt = np.zeros(0)

    @classmethod
    def of(cls, attitude, max_gap_s: float | None = None, clamp: bool = False
           ) -> AttitudeInterpolator:
        """Build from a :class:`pipeline.recording.AttitudeSeries`."""
        return cls(attitude.t_ns, attitude.q_enu_body, max_gap_s=max_gap_s, clamp=clamp)

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def step_s(self) -> float:
        """Median sample spacing, s (0.01 with fewer than two samples)."""
        return float(np.median(self._dt)) if len(self._dt) else 0.01

    def at_rel_s(self, tq_s: F64, *, clamp: bool | None = None) -> Interpolated:
        """Return the attitude at ``tq_s``, seconds from the first attitude sample.

        ``clamp`` overrides the interpolator's own setting for this query.
        """
        clamp = self.clamp if clamp is None else clamp
        tq = np.asarray(tq_s, dtype=float)
        tr, qa = self._tr, self.q_enu_body
        n = len(tq)
        q_out = np.full((n, 4), np.nan)
        w_out = np.full((n, 3), np.nan)
        pos = np.zeros(n)
        if len(tr) == 0 or n == 0:
            return Interpolated(q_out, np.zeros(n, dtype=bool), w_out, pos)
        if len(tr) == 1:
            inside = np.ones(n, dtype=bool) if clamp else tq == tr[0]
            q_out[inside] = quat_normalize(qa[0])
            w_out[inside] = 0.0
            return Interpolated(q_out, inside, w_out, pos)
        held = np.zeros(n, dtype=bool)
        if clamp:
            held = (tq < tr[0]) | (tq > tr[-1])  # held end sample: no rotation
            tq = np.clip(tq, tr[0], tr[-1])
        i = np.searchsorted(tr, tq, side="right") - 1  # tr[i] <= tq < tr[i + 1]
        i = np.where(tq == tr[-1], len(tr) - 2, i)
        inside = (i >= 0) & (i < len(tr) - 1)
        j = np.clip(i, 0, len(tr) - 2)
        dt = self._dt[j]
        on_sample = (tq == tr[j]) | (tq == tr[j + 1])
        valid = inside & ((dt <= self.max_gap_s + 1e-12) | on_sample)
        s = np.clip((tq - tr[j]) / np.where(dt > 0, dt, 1.0), 0.0, 1.0)
        jv = j[valid]
        q_out[valid] = quat_slerp(qa[jv], qa[jv + 1], s[valid])
        w_out[valid] = self._phi[jv] / np.where(dt[valid] > 0, dt[valid], 1.0)[:, None]
        w_out[valid & held] = 0.0
        pos[valid] = s[valid]
        return Interpolated(q_out, valid, w_out, pos)

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


def interpolation_noise_factor(position: F64) -> F64:
    """Variance of SLERP-interpolated white attitude noise relative to one sample's, (N,).

    Between two samples with independent errors of variance ``sigma^2`` the interpolated
    error at ``s`` is ``(1 - s) e_i + s e_{i+1}`` (to first order), of variance
    ``((1 - s)^2 + s^2) sigma^2``: 1 on a sample, 1/2 midway, 2/3 on average over ``s``.
    """
    s = np.asarray(position, dtype=float)
    return (1.0 - s) ** 2 + s**2


def attitude_noise_rad(q_enu_body: F64) -> float:
    """Robust estimate of the white attitude noise of a sampled track (RMS angle, rad).

    From the second differences of the sign-aligned quaternions (the motion of a few Hz at
    most barely contributes at attitude rates of 50 Hz and more): a small error ``delta``
    (rad, any axes) moves the vector part by ``delta / 2``, so for white noise
    ``E |d2|^2 = 6/4 E |delta|^2``; second differences over ten times their median (motion
    spikes) are left out.
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
    return float(np.sqrt(np.mean(e2[e2 <= 10.0 * med]) / 1.5))


def interpolate_attitude(
    attitude,
    t_ns: I64,
    *,
    time_offset_s: float = 0.0,
    max_gap_s: float = 0.1,
) -> tuple[F64, B8]:
    """SLERP of ``q_enu_body`` at ``t - time_offset_s``, with the gap rule.

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

"""THE measurement model: prediction, Jacobian and restore (inverse), written once.

More in docs/modules.md, ``pipeline.model.forward``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from numpy.typing import NDArray

from pipeline.core.geometry import (
    each_times_rows,
    left_times,
    norm_last,
    quat_rotate,
    quat_to_matrix,
    rot_z,
    rows_times,
    so3_exp,
)
from pipeline.model.attitude import AttitudeInterpolator, Interpolated
from pipeline.model.dipole_kernels import DIPOLE_NT, MIN_SOURCE_DISTANCE_M, add_dipole_field

if TYPE_CHECKING:
    from pipeline.core.recording import AttitudeSeries, PositionSeries

    # the effect modules import this one (their bases and formulas): the parts' type only
    from pipeline.model.effects.base import RestorePart

F64 = NDArray[np.float64]

#: The time offset model (the attitude re-interpolated at ``t - tau``, (J5)) is checked for
#: lags up to this (s) at rotation rates up to 5 rad/s (``tests/test_model.py``); estimators
#: fit ``tau`` on the samples at least this far inside the attitude's span.
MAX_TIME_OFFSET_S = 0.1
#: Order of the Legendre polynomials of ``field_drift`` (P1..P4; the constant is ``B_enu``).
DRIFT_DEGREE = 4
#: Order of the Legendre polynomials of ``heading_drift`` (P1..P2; a constant heading error
#: is a fixed turn of ``B_enu`` about Up, absorbed by the field).
HEADING_DEGREE = 2
#: Half-width of the central difference of the eddy-current regressor, in attitude intervals.
RATE_STEP_INTERVALS = 3.0
#: Parameter names of :func:`jacobian`'s columns.
PARAM_NAMES = ("rot_x", "rot_y", "rot_z", "B_e", "B_n", "B_u", "o_x", "o_y", "o_z",
               "D_xx", "D_yy", "D_zz", "D_xy", "D_xz", "D_yz", "tau")

#: symmetric basis of D: three diagonal then three off-diagonal elements
SOFT_IRON_BASIS = np.zeros((6, 3, 3))
for _k, (_i, _j) in enumerate([(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]):
    SOFT_IRON_BASIS[_k, _i, _j] = SOFT_IRON_BASIS[_k, _j, _i] = 1.0
#: its trace-free part: without a reference field the scale of D trades exactly against |B|,
#: so D is kept at trace 3 (mean gain 1) and |B| carries the scale
SOFT_IRON_BASIS_TRACE_FREE = np.concatenate(
    [np.array([np.diag([1.0, -1.0, 0.0]), np.diag([0.0, 1.0, -1.0])]) / np.sqrt(2.0),
     SOFT_IRON_BASIS[3:]])


def skew_rows(v: F64) -> F64:
    """``[v]x`` for each row of ``v`` (N, 3) -> (N, 3, 3)."""
    z = np.zeros(len(v))
    x, y, w = v[:, 0], v[:, 1], v[:, 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1),
                     np.stack([-y, x, z], -1)], -2)


def drift_basis(t_s: F64, span_s: float) -> F64:
    """Legendre P1..P4 of the time scaled to [-1, 1] over ``[0, span_s]``, (N, 4)."""
    x = 2.0 * np.asarray(t_s, dtype=float) / max(span_s, 1e-9) - 1.0
    return cast(F64, np.polynomial.legendre.legvander(x, DRIFT_DEGREE)[:, 1:])


def heading_basis(t_s: F64, span_s: float) -> F64:
    """Legendre P1..P2 of the time scaled to [-1, 1] over ``[0, span_s]``, (N, 2)."""
    x = 2.0 * np.asarray(t_s, dtype=float) / max(span_s, 1e-9) - 1.0
    return cast(F64, np.polynomial.legendre.legvander(x, HEADING_DEGREE)[:, 1:])


def rotate_about_up(v_enu: F64, h_rad: F64) -> F64:
    """Rows of ``v_enu`` (N, 3) turned about Up by ``h_rad`` (N,): ``Rz(h) v`` (ENU yaw)."""
    c, s = np.cos(h_rad), np.sin(h_rad)
    v = np.asarray(v_enu, dtype=float)
    out = v.copy()
    out[:, 0] = c * v[:, 0] - s * v[:, 1]
    out[:, 1] = s * v[:, 0] + c * v[:, 1]
    return out


def hat_basis(t_s: F64, knots_s: F64) -> F64:
    """Linear B-splines on ``knots_s``, zero outside ``[knots[0], knots[-1])``, (N, K)."""
    t = np.asarray(t_s, dtype=float)[:, None]
    k = np.asarray(knots_s, dtype=float)
    h = np.diff(k)
    left = np.concatenate([[np.inf], h])
    right = np.concatenate([h, [np.inf]])
    d = t - k[None, :]
    phi = np.clip(np.where(d < 0, 1.0 + d / left, 1.0 - d / right), 0.0, 1.0)
    return phi * ((t >= k[0]) & (t < k[-1]))


def ramp_modes(ramp_s: tuple[float, float], mode_step_s: float) -> int:
    """Return the number of sine modes of one transition of a ``hard_iron_step``.

    One mode per ``mode_step_s`` of the transition: the field of a magnet carried onto or
    off the platform changes shape within a fraction of a second (``1/r^3``), which a
    straight ramp cannot follow.
    """
    return max(1, int(np.ceil((float(ramp_s[1]) - float(ramp_s[0])) / mode_step_s - 1e-9)))


def ramp_profile(t_s: F64, window_s: tuple[float, float], ramps_s: Any,
                 mode_step_s: float) -> tuple[F64, F64]:
    """Plateau profile and transition basis of one ``hard_iron_step`` event, mag frame.

    The offset of an event in ``window_s = [a, b)`` is ``o s(t) + sum_j phi_j(t) c_j``:
    ``s`` is 1 on the plateau, 0 outside the window, and runs linearly from 0 at the outer
    end of each transition (a ramp that starts at ``a`` or ends at ``b``) to 1 at its inner
    end; ``phi_j = sin(k pi u)``, ``u`` running from 0 to 1 across a transition, are the
    Laplace eigenfunctions of that interval with both ends held (the offset is 0 before
    the magnet moves and ``o`` once it rests), whose coefficients ``c_j`` (3 each, mag
    frame) bend the ramp into the field the magnet made while it moved.

    Returns
    -------
    s : ndarray (N,)
        The plateau profile, dimensionless.
    phi : ndarray (N, M)
        The modes of all transitions, in order (:func:`ramp_modes` each).

    """
    t = np.asarray(t_s, dtype=float)
    a, b = float(window_s[0]), float(window_s[1])
    s = ((t >= a) & (t < b)).astype(float)
    cols = []
    for r0, r1 in ramps_s or ():
        r0, r1 = float(r0), float(r1)
        inside = (t >= r0) & (t < r1)
        u = (t[inside] - r0) / (r1 - r0)
        onset = abs(r0 - a) <= abs(r1 - b)
        s[inside] = u if onset else 1.0 - u
        k = np.arange(1, ramp_modes((r0, r1), mode_step_s) + 1)
        phi = np.zeros((t.size, k.size))
        phi[inside] = np.sin(np.pi * u[:, None] * k[None, :])
        cols.append(phi)
    return s, (np.concatenate(cols, axis=1) if cols else np.zeros((t.size, 0)))


def windows_span(windows_s: Any) -> tuple[float, float]:
    """Return ``(t0, t1)``, s: from the first window's start to the last one's end."""
    return (min(float(a) for a, _ in windows_s), max(float(b) for _, b in windows_s))


def window_rows(t_s: F64, t0: float, t1: float) -> slice | np.ndarray:
    """Return the samples with stamps in ``[t0, t1)``: a slice of ascending stamps, else a mask.

    A term that acts in a window is computed on those rows alone (zero elsewhere).
    """
    t = np.asarray(t_s, dtype=float)
    if not ascending(t):
        return (t >= t0) & (t < t1)
    a, b = np.searchsorted(t, [t0, t1])
    return slice(int(a), int(b))


def ascending(t_s: F64) -> bool:
    """Tell whether stamps are in order (equal neighbours allowed): searchsorted applies."""
    t = np.asarray(t_s, dtype=float)
    return bool(t.size < 2 or not np.any(t[1:] < t[:-1]))


def in_windows(t_s: F64, windows_s: Any) -> np.ndarray:
    """Half-open window membership, (N,) bool."""
    t = np.asarray(t_s, dtype=float)
    out = np.zeros(t.shape, dtype=bool)
    for a, b in windows_s or ():
        out |= (t >= float(a)) & (t < float(b))
    return out


@dataclass(frozen=True)
class Reading:
    """(M2)-(M5) at given attitude matrices, with the intermediate quantities.

    Attributes
    ----------
    y_nT : ndarray (N, 3)
        (M5): ``y0 + sum(offsets) + E_s ydot0``.
    y0_nT : ndarray (N, 3)
        (M4): ``D m``.
    b_body_nT, m_nT : ndarray (N, 3)
        (M2) ``C.T B'`` and (M3) ``R.T b``.
    bdot_nT_s, mdot_nT_s, ydot0_nT_s : ndarray (N, 3)
        ``C'.T B'``, ``R.T bdot`` and ``D mdot`` (the eddy regressor of (M5)); zeros without
        ``C'.T``.

    """

    y_nT: F64
    y0_nT: F64
    b_body_nT: F64
    m_nT: F64
    bdot_nT_s: F64
    mdot_nT_s: F64
    ydot0_nT_s: F64


def reading(Ct: F64, field_nT: F64, R_body_mag: F64, D: F64 | None = None,
            offsets_nT: tuple[F64, ...] | list[F64] = (), E_s: F64 | None = None,
            Cdot_t: F64 | None = None) -> Reading:
    """(M2)-(M5) from the pieces: THE place the prediction is computed.

    Both :func:`evaluate` (a :class:`ForwardModel`) and the diagnosis
    (:func:`stages.diagnose.model.evaluate`, which caches ``C.T`` over a fit and adds its own
    terms to the field) call it.

    Parameters
    ----------
    Ct : ndarray (N, 3, 3)
        ``C_enu_body(t - tau).T``, the attitude at the sensing time.
    field_nT : ndarray (N, 3) or (3,)
        The field the attitude source sees, ``B'(t)`` of (M1)-(M1h), ENU (the diagnosis'
        ``axis_tilt`` turns it further); (3,): constant (``B_enu`` alone, the estimators).
    R_body_mag : ndarray (3, 3)
        ``R`` of (M3).
    D : ndarray (3, 3) or None
        Identity when None.
    offsets_nT : sequence of ndarray (3,) or (N, 3)
        The additive mag-frame terms of (M5) (``o``, ``o_step 1[t in windows]``), added in order.
    E_s : ndarray (3, 3) or None
        ``eddy_current``; None: no eddy term.
    Cdot_t : ndarray (N, 3, 3) or None
        ``d/dt C.T`` at ``t - tau`` (:func:`rate_matrices`); None: ``ydot0 = 0``.

    """
    R = np.asarray(R_body_mag)
    b = _field_in(Ct, field_nT)  # (M2)
    m = b @ R  # (M3): rows R.T @ b
    y0 = m if D is None else m @ np.asarray(D).T  # (M4)
    if Cdot_t is not None:
        bdot = _field_in(Cdot_t, field_nT)
        mdot = bdot @ R
        ydot0 = mdot if D is None else mdot @ np.asarray(D).T
    else:
        bdot = mdot = ydot0 = np.zeros_like(b)
    y = y0.copy()
    for o in offsets_nT:  # (M5)
        y += o
    if E_s is not None:
        y += ydot0 @ np.asarray(E_s).T
    return Reading(y, y0, b, m, bdot, mdot, ydot0)


def _field_in(M: F64, field_nT: F64) -> F64:
    """Rows ``M_i @ B_i``; a constant field (3,) as three fused column sums (no batched matmul)."""
    f = np.asarray(field_nT)
    if f.ndim == 1:
        return cast(F64, M[:, :, 0] * f[0] + M[:, :, 1] * f[1] + M[:, :, 2] * f[2])
    return rows_times(M, f)


def field_jacobian(Ct: F64, R_body_mag: F64, D: F64 | None = None, E_s: F64 | None = None,
                   Cdot_t: F64 | None = None) -> F64:
    """(J2): ``dy/dB' = D R.T C.T + E_s D R.T C'.T`` (N, 3, 3), per sample."""
    DRt = np.asarray(R_body_mag).T if D is None else np.asarray(D) @ np.asarray(R_body_mag).T
    G = left_times(DRt, Ct)
    if E_s is not None and Cdot_t is not None:
        G += left_times(np.asarray(E_s) @ DRt, Cdot_t)
    return G


def time_offset_jacobian(omega_body_rad_s: F64, b_body_nT: F64, bddot_nT_s2: F64 | None,
                         R_body_mag: F64, D: F64 | None = None, E_s: F64 | None = None) -> F64:
    """(J5): ``dy/dtau = D R.T (omega_body x b) - E_s D R.T C''.T B'`` (N, 3), per s.

    ``bddot_nT_s2`` is ``C''.T B'`` (:func:`rate_matrices`; unused without ``E_s``).
    """
    DRt = np.asarray(R_body_mag).T if D is None else np.asarray(D) @ np.asarray(R_body_mag).T
    J = np.cross(omega_body_rad_s, b_body_nT) @ DRt.T
    if E_s is None or bddot_nT_s2 is None:
        return cast(F64, J)
    return cast(F64, J - (bddot_nT_s2 @ DRt.T) @ np.asarray(E_s).T)


def soft_iron_jacobian(basis: F64, m_nT: F64, mdot_nT_s: F64, E_s: F64 | None = None) -> F64:
    """(J4): ``dy/dd_k = S_k m + E_s S_k mdot`` (N, 3, K), ``S_k`` of ``basis`` (K, 3, 3).

    ``D`` perturbed along ``basis``: :data:`PARAM_NAMES` use the six symmetric unit matrices,
    the diagnosis' ``soft_iron`` the five traceless ones.
    """
    J = each_times_rows(basis, m_nT)
    if E_s is not None:
        J = J + each_times_rows(np.matmul(np.asarray(E_s), basis), mdot_nT_s)
    return J


def source_offset_enu(c_m: F64, psi_rad: float, p_m: F64,
                      lever_enu_m: F64 | None = None) -> F64:
    """``r`` (N, 3), m, ENU: from a ``local_source`` at ``c_m`` to the sensor.

    ``r = Rz(psi) (p - c) + C l``: positions ``p_m`` (N, 3) and ``c_m`` in the position
    frame, turned to ENU by its bearing ``psi``; ``lever_enu_m`` the lever arm ``C l`` in
    ENU (N, 3) when the model has one.
    """
    r = (np.asarray(p_m, dtype=float) - np.asarray(c_m, dtype=float)) @ rot_z(psi_rad).T
    return r if lever_enu_m is None else r + lever_enu_m


def dipole_matrix(r_enu_m: F64) -> F64:
    """``B = P(r) m``: the point dipole's field per unit moment, (N, 3, 3), nT / (A m^2).

    ``P = 100 (3 u u^T - I) / r^3`` with ``r`` the vector from the source to the sensor, m.
    """
    r = np.asarray(r_enu_m, dtype=float)
    d = np.maximum(norm_last(r), MIN_SOURCE_DISTANCE_M)
    s = DIPOLE_NT / d**3
    u = (r / d[:, None]).T  # (3, N): each component a contiguous row
    return _symmetric(lambda i, j: 3.0 * s * u[i] * u[j] - (s if i == j else 0.0), len(d))


def dipole_field(r_enu_m: F64, m_Am2: F64) -> F64:
    """``B = 100 (3 (m.u) u - m) / r^3`` (N, 3), nT: ``dipole_matrix(r) @ m``, no matrices.

    One pass over the samples, compiled (:func:`pipeline.model.dipole_kernels.add_dipole_field`).
    """
    r = np.asarray(r_enu_m, dtype=float).reshape(-1, 3)
    out = np.zeros((len(r), 3))
    add_dipole_field(r, np.asarray(m_Am2, dtype=float), out)
    return out


def dipole_gradient(r_enu_m: F64, m_Am2: F64) -> F64:
    """``dB/dr`` (N, 3, 3), nT/m, of the point dipole ``m`` at ``r`` (symmetric: curl-free).

    From ``B = k (3 (m.r) r / r^5 - m / r^3)``::

        dB_i/dr_j = k (3 (m_j r_i + m_i r_j + (m.r) d_ij) / r^5 - 15 (m.r) r_i r_j / r^7)

    that is ``a (r_i m_j + m_i r_j + (m.r) d_ij) - c r_i r_j`` with ``a = 3 k / r^5`` and
    ``c = 15 k (m.r) / r^7`` per sample.
    """
    r = np.asarray(r_enu_m, dtype=float)
    m = np.asarray(m_Am2, dtype=float)
    d = np.maximum(norm_last(r), MIN_SOURCE_DISTANCE_M)
    mr = r @ m
    d2 = d * d
    a = 3.0 * DIPOLE_NT / (d2 * d2 * d)
    c = 5.0 * a * mr / d2
    rt = r.T.copy()  # (3, N)

    def entry(i: int, j: int) -> F64:
        e = a * (rt[i] * m[j] + m[i] * rt[j]) - c * rt[i] * rt[j]
        return e + a * mr if i == j else e

    return _symmetric(entry, len(d))


def _symmetric(entry: Callable[[int, int], F64], n: int) -> F64:
    """(N, 3, 3) from its six distinct entries ``entry(i, j)`` (N,), ``i <= j``.

    The per-sample 3 x 3 products of broadcasting run along axes of length 3, which numpy
    loops over slowly; each entry as a whole column of samples is one pass.
    """
    out = np.empty((n, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            out[:, i, j] = entry(i, j)
            if j != i:
                out[:, j, i] = out[:, i, j]
    return out


@dataclass(frozen=True)
class ForwardModel:
    """Every term of (M1)-(M5) with its value; absent terms are ``None`` / empty.

    The sensor's constants are fields; the terms that are a field in ENU, a turn of it or an
    offset changing in time are ``parts``, each built by its effect's module from its
    CONVENTIONS params (:meth:`pipeline.model.calibration.Calibration.forward_model`).

    Attributes
    ----------
    R_body_mag : ndarray (3, 3)
    B_enu_nT : ndarray (3,)
    D : ndarray (3, 3) or None
        Symmetric positive-definite (identity when None).
    offset_nT : ndarray (3,) or None
        ``o``, mag frame.
    time_offset_s : float
        ``tau``, s (CONVENTIONS sign).
    E_s : ndarray (3, 3) or None
        ``eddy_current``, s.
    lever_arm_body_m : ndarray (3,) or None
        ``lever_arm``: the magnetometer at ``p + C_enu_body l`` (CONVENTIONS), for the
        spatial terms.
    parts : tuple of RestorePart
        The fitted terms of ``F(t)`` (M1), the heading drift (M1h) and the offset steps
        (M5), in the order (M1) sums them
        (:class:`pipeline.model.effects.base.RestorePart`).
    unmodelled : tuple of str
        Effects the calibration names whose fitted curve it does not carry.

    """

    R_body_mag: F64
    B_enu_nT: F64
    D: F64 | None = None
    offset_nT: F64 | None = None
    time_offset_s: float = 0.0
    E_s: F64 | None = None
    lever_arm_body_m: F64 | None = None
    parts: tuple[RestorePart, ...] = ()
    unmodelled: tuple[str, ...] = field(default=())

    # ------------------------------------------------------------------ pieces
    @property
    def D_or_I(self) -> F64:
        """``D`` (identity when not estimated)."""
        return np.eye(3) if self.D is None else self.D

    @property
    def needs_positions(self) -> bool:
        """A term's field depends on the sensor's position."""
        return any(p.needs_positions for p in self.parts)

    def external_field_nT(self, t_s: F64, p_m: F64 | None = None,
                          lever_enu_m: F64 | None = None) -> F64:
        """``F(t)`` of (M1), ENU, (N, 3); ``t_s`` from the first magnetometer sample.

        ``lever_enu_m``: the lever arm in ENU at each sample, ``C_enu_body l`` (N, 3), m.
        ``p_m``: positions (N, 3), m, for the spatial terms (NaN rows or None: no
        contribution).
        """
        t = np.asarray(t_s, dtype=float)
        F = np.zeros((len(t), 3))
        lev = None if lever_enu_m is None else np.nan_to_num(np.asarray(lever_enu_m, float))
        p, placed = None, np.ones((len(t), 1), dtype=bool)
        if p_m is not None:
            p = np.asarray(p_m, dtype=float)
            placed = np.isfinite(p).all(axis=1)[:, None]
            p = np.nan_to_num(p)  # the rows without a position are masked below
        for part in self.parts:
            f = part.field_enu(t, p, lev)
            if f is not None:
                F += np.where(placed, f, 0.0) if part.needs_positions else f
        return F

    def heading_rad(self, t_s: F64) -> F64 | None:
        """``h(t)`` of (M1h), rad, (N,); None without ``heading_drift``."""
        return next((h for part in self.parts if (h := part.heading_rad(t_s)) is not None),
                    None)

    def step_offset_nT(self, t_s: F64) -> F64:
        """``o_step 1[t in windows]`` of (M5), with its transitions, mag frame, (N, 3)."""
        t = np.asarray(t_s, dtype=float)
        out = np.zeros((len(t), 3))
        for part in self.parts:
            o = part.offset_nT(t)
            if o is not None:
                out += o
        return out


@dataclass(frozen=True)
class ForwardEvaluation:
    """The model at the magnetometer stamps.

    Attributes
    ----------
    y_nT : ndarray (N, 3)
        Predicted reading (M5), mag frame; NaN where not ``valid``.
    valid : ndarray of bool (N,)
        An attitude was available at ``t - tau`` (gap rule).
    q_enu_body : ndarray (N, 4)
        Attitude at ``t - tau`` (NaN where not valid).
    omega_body_rad_s : ndarray (N, 3)
        Angular velocity of the interpolated attitude at ``t - tau``, body frame.
    field_enu_nT : ndarray (N, 3)
        The field the attitude source sees, ``Rz(h) (B_enu + F(t))`` (M1)-(M1h).
    heading_rad : ndarray (N,) or None
        ``h(t)`` (M1h); None without ``heading_drift``.
    b_body_nT, m_nT, ydot0_nT_s : ndarray (N, 3)
        (M2), (M3) and the eddy regressor (zeros without ``eddy_current``).
    sensor_nT : ndarray (N, 3)
        ``o + o_step + E_s ydot0``: the additive mag-frame terms of (M5).
    interp_position : ndarray (N,)
        Where ``t - tau`` falls between its two attitude samples, 0..1.

    """

    y_nT: F64
    valid: np.ndarray
    q_enu_body: F64
    field_enu_nT: F64
    b_body_nT: F64
    m_nT: F64
    ydot0_nT_s: F64
    sensor_nT: F64
    interp_position: F64
    #: the attitude query (its angular velocity is computed on first use)
    _at: Interpolated = field(repr=False, compare=False)
    heading_rad: F64 | None = None

    @cached_property
    def omega_body_rad_s(self) -> F64:
        """Angular velocity at ``t - tau``, body frame, rad/s, (N, 3); 0 where not valid."""
        return np.where(self.valid[:, None], self._at.omega_body_rad_s, 0.0)


def _interp(attitude: AttitudeSeries | AttitudeInterpolator, max_gap_s: float | None
            ) -> AttitudeInterpolator:
    if isinstance(attitude, AttitudeInterpolator):
        return attitude
    return AttitudeInterpolator.of(attitude, max_gap_s=max_gap_s)


def _Ct(q: F64) -> F64:

    return np.swapaxes(quat_to_matrix(q), -1, -2)


def evaluate(
    model: ForwardModel,
    t_ns: NDArray[np.int64],
    attitude: AttitudeSeries | AttitudeInterpolator,
    *,
    t0_ns: int | None = None,
    max_gap_s: float | None = None,
    position: PositionSeries | None = None,
) -> ForwardEvaluation:
    """Evaluate (M1)-(M5) at the magnetometer stamps ``t_ns`` (int64 ns, sorted).

    ``t0_ns``: the first magnetometer stamp of the recording (effect windows count from it;
    default ``t_ns[0]``). ``max_gap_s``: attitude gap rule (default the automatic one).
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    n = len(t_ns)
    it = _interp(attitude, max_gap_s)
    t0 = int(t_ns[0]) if (t0_ns is None and n) else int(t0_ns or 0)
    t_s = (t_ns - t0).astype(float) * 1e-9
    tau = model.time_offset_s
    at = it.at(t_ns, tau)
    valid = at.valid
    ident = np.array([0.0, 0.0, 0.0, 1.0])
    q = np.where(valid[:, None], at.q_enu_body, ident)
    p_m = None
    if model.needs_positions and position is not None:
        p_m = position.at(t_ns)
    Ct = _Ct(q)
    lever = None
    if model.lever_arm_body_m is not None and p_m is not None:
        lever = np.swapaxes(Ct, -1, -2) @ model.lever_arm_body_m  # C l, ENU
    Bt = model.B_enu_nT[None, :] + model.external_field_nT(t_s, p_m, lever)
    h_rad = model.heading_rad(t_s)
    if h_rad is not None:
        Bt = rotate_about_up(Bt, h_rad)  # (M1h)
    Cdot = None
    if model.E_s is not None:
        Cdot = rate_matrices(it, t_ns, tau)[0]
    offsets = [model.step_offset_nT(t_s)]
    if model.offset_nT is not None:
        offsets.append(model.offset_nT)
    rd = reading(Ct, Bt, model.R_body_mag, model.D, offsets, model.E_s, Cdot)  # (M2)-(M5)
    b, m, y = rd.b_body_nT, rd.m_nT, rd.y_nT
    ydot0 = rd.ydot0_nT_s
    ydot0[~valid] = 0.0
    sensor = offsets[0] if len(offsets) == 1 else offsets[0] + offsets[1]
    if model.E_s is not None:
        sensor = sensor + ydot0 @ model.E_s.T
    nanv = ~valid
    y[nanv] = np.nan
    return ForwardEvaluation(y, valid, at.q_enu_body, Bt, b, m, ydot0, sensor, at.position, at,
                             h_rad)


def rate_matrices(it: AttitudeInterpolator, t_ns: NDArray[np.int64], tau: float
                  ) -> tuple[F64, F64]:
    """``C'.T`` and ``C''.T`` (N, 3, 3) at ``t - tau`` by central differences.

    Half-width :data:`RATE_STEP_INTERVALS` attitude intervals (the eddy regressor of (M5)
    then shares no attitude sample with the reading's own interpolation); ``C'.T B'`` is
    ``bdot`` of :func:`reading`, ``C''.T B'`` enters (J5).
    """
    h = max(RATE_STEP_INTERVALS * it.step_s, 1e-3)
    ident = np.array([0.0, 0.0, 0.0, 1.0])
    # clamped: the neighbours of a valid sample may fall just outside the span
    qs = [it.at(t_ns, tau + d, clamp=True).q_enu_body for d in (-h, 0.0, h)]  # s+h, s, s-h
    Cp, C0, Cm = (_Ct(np.where(np.all(np.isfinite(x), axis=1)[:, None], x, ident)) for x in qs)
    Cdot = (Cp - Cm) / (2.0 * h)
    Cddot = (Cp - 2.0 * C0 + Cm) / (h * h)
    return Cdot, Cddot


def predict(model: ForwardModel, t_ns: NDArray[np.int64],
            attitude: AttitudeSeries | AttitudeInterpolator, **kw: Any) -> F64:
    """Predicted readings (M5), mag frame, nT, (N, 3); NaN without an attitude."""
    return evaluate(model, t_ns, attitude, **kw).y_nT


@dataclass(frozen=True)
class Restoration:
    """Restored samples (M6) and the final model's residual.

    Attributes
    ----------
    t_ns : ndarray int64 (N,)
    calibrated_mag_nT : ndarray (N, 3)
        ``inv(D) (y - o - o_step - E_s ydot0)``, mag frame.
    enu_nT : ndarray (N, 3)
        (M6), ENU; NaN where not ``valid``.
    residual_nT : ndarray (N, 3)
        Measured minus predicted by (M1)-(M5), every term included; NaN where not valid.
    predicted_nT : ndarray (N, 3)
    q_enu_body : ndarray (N, 4)
        Attitude at ``t - tau`` (NaN where not valid).
    valid : ndarray bool (N,)

    """

    t_ns: NDArray[np.int64]
    calibrated_mag_nT: F64
    enu_nT: F64
    residual_nT: F64
    predicted_nT: F64
    q_enu_body: F64
    valid: np.ndarray


def restore(model: ForwardModel, mag_nT: F64, t_ns: NDArray[np.int64],
            attitude: AttitudeSeries | AttitudeInterpolator, **kw: Any) -> Restoration:
    """Invert the model (M6) and compute the residual of (M1)-(M5); keywords as :func:`evaluate`."""
    y = np.asarray(mag_nT, dtype=float)
    ev = evaluate(model, t_ns, attitude, **kw)
    c = y - ev.sensor_nT
    if model.D is not None:
        c = cast(F64, np.linalg.solve(model.D, c.T).T)
    q = np.where(ev.valid[:, None], ev.q_enu_body, np.array([0.0, 0.0, 0.0, 1.0]))
    enu = quat_rotate(q, c @ model.R_body_mag.T)
    if ev.heading_rad is not None:
        enu = rotate_about_up(enu, -ev.heading_rad)  # (M6): the heading error taken out
    enu[~ev.valid] = np.nan
    resid = y - ev.y_nT
    return Restoration(np.asarray(t_ns, dtype=np.int64), c, enu, resid, ev.y_nT,
                       ev.q_enu_body, ev.valid)


def jacobian(model: ForwardModel, t_ns: NDArray[np.int64],
             attitude: AttitudeSeries | AttitudeInterpolator, **kw: Any) -> F64:
    """``dy/dparams`` (N, 3, 16) in the order of :data:`PARAM_NAMES`, (J1)-(J5).

    Rows without an attitude are zero. The rotation column block is the right perturbation
    ``R <- R Exp(d)``; ``D`` is perturbed by its six symmetric entries; ``tau`` in s.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    it = _interp(attitude, kw.get("max_gap_s"))
    ev = evaluate(model, t_ns, it, **kw)
    n = len(t_ns)
    D = model.D_or_I
    R = model.R_body_mag
    valid = ev.valid
    ident = np.array([0.0, 0.0, 0.0, 1.0])
    Ct = _Ct(np.where(valid[:, None], ev.q_enu_body, ident))
    E = model.E_s
    m = ev.m_nT
    J = np.zeros((n, 3, len(PARAM_NAMES)))
    if E is not None:
        Cdot, Cddot = rate_matrices(it, t_ns, model.time_offset_s)
    else:
        Cdot = Cddot = np.zeros((n, 3, 3))
    B = ev.field_enu_nT
    mdot = rows_times(Cdot, B) @ R
    J[:, :, 0:3] = D @ skew_rows(m)  # (J1)
    if E is not None:
        J[:, :, 0:3] += E @ D @ skew_rows(mdot)
    J[:, :, 3:6] = field_jacobian(Ct, R, D, E, Cdot)  # (J2)
    if ev.heading_rad is not None:  # (J2) through (M1h): d B'/d B_enu = Rz(h)
        c, s_ = np.cos(ev.heading_rad), np.sin(ev.heading_rad)
        Rz = np.zeros((n, 3, 3))
        Rz[:, 0, 0] = Rz[:, 1, 1] = c
        Rz[:, 0, 1], Rz[:, 1, 0] = -s_, s_
        Rz[:, 2, 2] = 1.0
        J[:, :, 3:6] = np.matmul(J[:, :, 3:6], Rz)
    J[:, :, 6:9] = np.eye(3)  # (J3)
    J[:, :, 9:15] = soft_iron_jacobian(SOFT_IRON_BASIS, m, mdot, E)  # (J4)
    J[:, :, 15] = time_offset_jacobian(ev.omega_body_rad_s, ev.b_body_nT, rows_times(Cddot, B),
                                       R, D, E)  # (J5)
    J[~valid] = 0.0
    return J


def perturbed(model: ForwardModel, dx: F64) -> ForwardModel:
    """Apply a perturbation in the order of :data:`PARAM_NAMES` (right perturbation on R)."""
    dx = np.asarray(dx, dtype=float)
    D = model.D_or_I + np.tensordot(dx[9:15], SOFT_IRON_BASIS, axes=1)
    o = (np.zeros(3) if model.offset_nT is None else model.offset_nT) + dx[6:9]
    return replace(model, R_body_mag=model.R_body_mag @ so3_exp(dx[0:3]),
                   B_enu_nT=model.B_enu_nT + dx[3:6], D=D, offset_nT=o,
                   time_offset_s=model.time_offset_s + float(dx[15]))

"""Rotation decomposition (Tang et al. 2016): swing-twist, fitted rotation axes, octonions.

More in docs/modules.md, ``pipeline.model.tang``.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from pipeline.core.geometry import (
    quat_conj,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_to_rotvec,
    rotvec_to_quat,
)

F64 = NDArray[np.float64]


class TwistSide(enum.Enum):
    """Where the twist stands in the product.

    ``RIGHT``: ``q = swing * twist`` (twist applied first; for ``q_enu_body`` the axis is in
    the body frame). ``LEFT``: ``q = twist * swing`` (twist applied last; axis in the frame the
    quaternion maps into, ENU for ``q_enu_body``). The twist is the same in both; the swing
    differs.
    """

    RIGHT = "right"
    LEFT = "left"


def _unit(v: ArrayLike) -> F64:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def swing_twist(
    q: ArrayLike, axis: ArrayLike, side: TwistSide = TwistSide.RIGHT
) -> tuple[F64, F64]:
    """Split rotations into a twist about ``axis`` and a swing about a perpendicular axis.

    Parameters
    ----------
    q : array_like, shape (..., 4)
        Unit quaternions, scalar-last.
    axis : array_like, shape (3,) or (..., 3)
        Twist axis (normalised here).
    side : TwistSide
        ``RIGHT``: ``q = swing * twist``; ``LEFT``: ``q = twist * swing``.

    Returns
    -------
    swing, twist : ndarray, shape (..., 4)
        ``twist`` rotates about ``axis``; ``swing``'s rotation axis is perpendicular to it.
        Where the twist is undefined (a swing of exactly 180 deg) the twist is the identity.

    """
    q = np.asarray(q, dtype=float)
    n = _unit(axis)
    proj = np.sum(q[..., :3] * n, axis=-1, keepdims=True)
    tw = np.concatenate([proj * n * np.ones_like(q[..., :3]), q[..., 3:4]], axis=-1)
    norm = np.linalg.norm(tw, axis=-1, keepdims=True)
    degenerate = norm < 1e-12
    ident = np.zeros_like(tw)
    ident[..., 3] = 1.0
    tw = np.where(degenerate, ident, tw / np.where(degenerate, 1.0, norm))
    if side is TwistSide.RIGHT:
        sw = quat_mul(q, quat_conj(tw))
    else:
        sw = quat_mul(quat_conj(tw), q)
    return sw, tw


def twist_angle(q: ArrayLike, axis: ArrayLike) -> F64:
    """Signed twist angle (rad, in (-pi, pi]) of rotations ``q`` about ``axis``, shape (...)."""
    q = np.asarray(q, dtype=float)
    n = _unit(axis)
    proj = np.sum(q[..., :3] * n, axis=-1)
    w = q[..., 3]
    # a swing of exactly 180 deg leaves no twist (the same convention as swing_twist)
    degenerate = np.hypot(proj, w) < 1e-12
    return np.where(degenerate, 0.0, wrap_angle(2.0 * np.arctan2(proj, w)))


def rotation_angle(q: ArrayLike) -> F64:
    """Rotation angle (rad, in [0, pi]) of unit quaternions, shape (...)."""
    q = np.asarray(q, dtype=float)
    return 2.0 * np.arctan2(np.linalg.norm(q[..., :3], axis=-1), np.abs(q[..., 3]))


def axis_angle_quat(axis: ArrayLike, angle_rad: ArrayLike) -> F64:
    """Quaternions rotating by ``angle_rad`` (...) about ``axis`` (3,) or (..., 3)."""
    n = _unit(axis)
    a = np.asarray(angle_rad, dtype=float)[..., None]
    return np.concatenate([np.sin(a / 2) * n * np.ones(a.shape[:-1] + (3,)), np.cos(a / 2)], -1)


def min_rotation_quat(a: ArrayLike, b: ArrayLike) -> F64:
    """Return the smallest rotation (4,) taking unit vector ``a`` to ``b`` (no twist about them)."""
    a = _unit(a)
    b = _unit(b)
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-12:  # opposite: any perpendicular axis, 180 deg
        p = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(p) < 1e-6:
            p = np.cross(a, [0.0, 1.0, 0.0])
        return np.concatenate([_unit(p), [0.0]])
    q = np.concatenate([np.cross(a, b), [1.0 + c]])
    return q / np.linalg.norm(q)


# ----------------------------------------------------------------------------- Tang's equations


def tang_delta_gamma(omega_rad: ArrayLike, alpha_rad: ArrayLike) -> tuple[F64, F64]:
    """Tang 2016, Eq. (33): the full angles ``2 delta`` and ``2 gamma`` (rad).

    Parameters
    ----------
    omega_rad : array_like
        Rotation ``Omega = 2 theta`` about the tilted axis.
    alpha_rad : array_like
        Tilt of the axis from the nominal one (broadcast with ``omega_rad``).

    Returns
    -------
    two_delta, two_gamma : ndarray
        Rotation about the nominal axis and about the perpendicular axis in the tilt plane.

    """
    s = np.sin(0.5 * np.asarray(omega_rad, dtype=float))
    a = np.asarray(alpha_rad, dtype=float)
    two_delta = 2.0 * np.arcsin(s * np.cos(a))  # Tang 2016, Eq. 33
    two_gamma = 2.0 * np.arcsin(s * np.sin(a))  # Tang 2016, Eq. 33
    return two_delta, two_gamma


def tang_eta(omega_rad: ArrayLike, alpha_rad: ArrayLike) -> F64:
    """Tang 2016, Eq. (34): azimuth error ``eta = Omega - 2 asin(sin(Omega/2) cos alpha)`` (rad)."""
    om = np.asarray(omega_rad, dtype=float)
    return om - 2.0 * np.arcsin(np.sin(0.5 * om) * np.cos(alpha_rad))  # Tang 2016, Eq. 34


def tilted_rotation(omega_rad: ArrayLike, alpha_rad: ArrayLike) -> F64:
    """Exact geometry: rotation by ``Omega`` about z tilted by ``alpha`` towards x, (..., 4)."""
    om, al = np.broadcast_arrays(np.asarray(omega_rad, float), np.asarray(alpha_rad, float))
    axis = np.stack([np.sin(al), np.zeros_like(al), np.cos(al)], axis=-1)
    return axis_angle_quat(axis, om)


def exact_eta(omega_rad: ArrayLike, alpha_rad: ArrayLike) -> F64:
    """Azimuth error from exact geometry: ``Omega`` minus the twist about the nominal axis (rad).

    The rotation by ``Omega`` about the tilted axis is decomposed (swing-twist) into a rotation
    about the nominal axis z and a swing; the twist is what the azimuth reading shows.
    """
    q = tilted_rotation(omega_rad, alpha_rad)
    om = np.broadcast_to(np.asarray(omega_rad, float), q.shape[:-1])
    return wrap_angle(om - twist_angle(q, [0.0, 0.0, 1.0]))


def wrap_angle(a: ArrayLike) -> F64:
    """Angles wrapped to (-pi, pi] (rad)."""
    return np.angle(np.exp(1j * np.asarray(a, dtype=float)))


def tang_minor_spin(omega_rad: ArrayLike, alpha_rad: ArrayLike) -> F64:
    """Return the term Tang's product neglects, as a rotation angle (rad): ``2 asin|sin d sin g|``.

    ``(cos d + sin d k)(cos g + sin g i)`` contains ``sin d sin g (k i) = sin d sin g j``, a spin
    about the axis perpendicular to both; Eqs. (33)-(34) drop it.
    """
    two_d, two_g = tang_delta_gamma(omega_rad, alpha_rad)
    return 2.0 * np.arcsin(np.abs(np.sin(0.5 * two_d) * np.sin(0.5 * two_g)))


def tang_residual_rotation(omega_rad: ArrayLike, alpha_rad: ArrayLike) -> F64:
    """Angle (rad) of ``(q_delta q_gamma)^-1 q``: how far Tang's product is from the true rotation.

    ``q_delta q_gamma`` is renormalised (it has norm above 1 because of the minor spin).
    """
    two_d, two_g = tang_delta_gamma(omega_rad, alpha_rad)
    qd = axis_angle_quat([0.0, 0.0, 1.0], two_d)
    qg = axis_angle_quat([1.0, 0.0, 0.0], two_g)
    prod = quat_normalize(quat_mul(qd, qg))
    q = tilted_rotation(omega_rad, alpha_rad)
    return rotation_angle(quat_mul(quat_conj(prod), q))


@dataclass(frozen=True)
class MinorSpinBound:
    """Size of what Tang's Eqs. (33)-(34) neglect over a grid (all degrees)."""

    omega_max_deg: float
    alpha_max_deg: float
    max_minor_spin_deg: float
    max_eta_eq34_minus_exact_deg: float
    max_residual_rotation_deg: float


def minor_spin_bound(
    omega_max_deg: float = 40.0, alpha_max_deg: float = 20.0, n: int = 161
) -> MinorSpinBound:
    """Largest minor spin and Eq. (34) error for ``|Omega| <= omega_max, |alpha| <= alpha_max``."""
    om = np.radians(np.linspace(-omega_max_deg, omega_max_deg, n))
    al = np.radians(np.linspace(-alpha_max_deg, alpha_max_deg, n))
    om_g, al_g = np.meshgrid(om, al)
    return MinorSpinBound(
        omega_max_deg,
        alpha_max_deg,
        float(np.degrees(np.max(tang_minor_spin(om_g, al_g)))),
        float(np.degrees(np.max(np.abs(tang_eta(om_g, al_g) - exact_eta(om_g, al_g))))),
        float(np.degrees(np.max(tang_residual_rotation(om_g, al_g)))),
    )


def fit_alpha_from_eta(
    omega_rad: ArrayLike, eta_rad: ArrayLike, *, exact: bool = False
) -> tuple[float, float]:
    """Inverse of Eq. (34): the tilt ``|alpha|`` (rad) that best explains observed ``eta(Omega)``.

    Least squares over ``alpha`` in [0, pi/2] (``eta`` is even in ``alpha``, so its sign and the
    tilt's direction are not observable from azimuth errors alone).

    Parameters
    ----------
    omega_rad, eta_rad : array_like, shape (N,)
        Commanded rotations and observed azimuth errors.
    exact : bool
        Fit the exact-geometry curve (:func:`exact_eta`) instead of Eq. (34).

    Returns
    -------
    alpha_rad, sigma_rad : float
        Estimate and its 1-sigma from the residual scatter (``inf`` with fewer than 2 points
        or no sensitivity, e.g. all ``Omega`` = 0).

    """
    om = np.asarray(omega_rad, dtype=float).ravel()
    eta = np.asarray(eta_rad, dtype=float).ravel()
    model = exact_eta if exact else tang_eta

    def res(p: F64) -> F64:
        return model(om, p[0]) - eta

    # start from the closed form cos(alpha) = sin((Omega - eta)/2) / sin(Omega/2) (Eq. 34)
    s = np.sin(0.5 * om)
    ok = np.abs(s) > 1e-3
    c0 = np.median(np.sin(0.5 * (om[ok] - eta[ok])) / s[ok]) if np.any(ok) else 1.0
    a0 = float(np.arccos(np.clip(c0, 0.0, 1.0)))
    a0 = min(max(a0, 1e-4), np.pi / 2 - 1e-4)
    sol = least_squares(
        res, [a0], bounds=([0.0], [np.pi / 2]), x_scale=[0.01], xtol=1e-14, ftol=1e-15, gtol=1e-15
    )
    J = sol.jac[:, 0]
    dof = om.size - 1
    info = float(J @ J)
    if dof < 1 or info <= 0:
        return float(sol.x[0]), float("inf")
    s2 = float(sol.fun @ sol.fun) / dof
    return float(sol.x[0]), float(np.sqrt(s2 / info)) if s2 > 0 else 0.0


HEADING_STATS_KEYS = (
    "mean_deg",
    "var_deg2",
    "max_deg",
    "min_deg",
    "std_deg",
    "rms_deg",
    "max_abs_deg",
    "peak_to_peak_deg",
)


def heading_error_stats(eta_rad: ArrayLike) -> dict[str, float]:
    """Tang 2016, Table 2: statistics of a heading (azimuth) error series, in degrees.

    Table 2 gives the mean, variance, maximum and minimum of the heading error before and after
    compensation; the standard deviation, RMS, largest magnitude and peak-to-peak are added
    for the metrics files.

    Parameters
    ----------
    eta_rad : array_like, shape (N,)
        Heading errors, rad (already wrapped to (-pi, pi]; non-finite values are left out).

    Returns
    -------
    dict
        ``mean_deg``, ``var_deg2``, ``max_deg``, ``min_deg``, ``std_deg``, ``rms_deg``,
        ``max_abs_deg``, ``peak_to_peak_deg`` (NaN for an empty series) and ``n`` (int).

    """
    e = np.degrees(np.asarray(eta_rad, dtype=float).ravel())
    e = e[np.isfinite(e)]
    if e.size == 0:
        out: dict[str, float] = dict.fromkeys(HEADING_STATS_KEYS, float("nan"))
        out["n"] = 0
        return out
    return {
        "mean_deg": float(np.mean(e)),
        "var_deg2": float(np.var(e)),
        "max_deg": float(np.max(e)),
        "min_deg": float(np.min(e)),
        "std_deg": float(np.std(e)),
        "rms_deg": float(np.sqrt(np.mean(e**2))),
        "max_abs_deg": float(np.max(np.abs(e))),
        "peak_to_peak_deg": float(np.ptp(e)),
        "n": int(e.size),
    }


# ----------------------------------------------------------------------------- octonions


def octonion(a: ArrayLike, b: ArrayLike) -> F64:
    """Build the octonion ``a + b e`` from two scalar-last quaternions, shape (..., 8)."""
    a, b = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float))
    return np.concatenate([a, b], axis=-1)


def octonion_mul(x: ArrayLike, y: ArrayLike) -> F64:
    """Cayley-Dickson product ``(a, b)(c, d) = (ac - d* b, d a + b c*)``, shape (..., 8).

    Non-associative but alternative; ``|xy| = |x||y|``. Restricted to ``b = d = 0`` it is the
    Hamilton product, so the quaternion part composes rotations.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    a, b = x[..., :4], x[..., 4:]
    c, d = y[..., :4], y[..., 4:]
    first = quat_mul(a, c) - quat_mul(quat_conj(d), b)
    second = quat_mul(d, a) + quat_mul(b, quat_conj(c))
    return np.concatenate([first, second], axis=-1)


def octonion_conj(x: ArrayLike) -> F64:
    """Conjugate ``(a, b)* = (a*, -b)``."""
    x = np.asarray(x, dtype=float)
    return np.concatenate([quat_conj(x[..., :4]), -x[..., 4:]], axis=-1)


def octonion_norm(x: ArrayLike) -> F64:
    """Euclidean norm of octonions, shape (...)."""
    return np.linalg.norm(np.asarray(x, dtype=float), axis=-1)


# ----------------------------------------------------------------------------- stretches


@dataclass(frozen=True)
class RotationFit:
    """What a stretch of attitude does, as rotation about one fitted axis.

    Attributes
    ----------
    axis_body, axis_enu : ndarray (3,)
        Unit rotation axis (principal direction of the angular rate), signed so that the net
        twist is positive.
    twist_deg : float
        Net rotation about the axis over the stretch (integrated rate, may exceed 360).
    twist_range_deg : float
        Max minus min of the accumulated twist.
    mean_rate_deg_s : float
        Mean rotation rate about the axis.
    rate_cv : float
        Coefficient of variation of that rate (std / |mean|): near 0 for a constant rate,
        where a time offset is unobservable (it equals a fixed rotation about the axis).
    swing_rms_deg : float
        RMS of the swing of ``q_0^-1 q_k`` about the fitted body axis (wobble).
    axis_spread : float
        Second eigenvalue over the first of the rate scatter (0 for a single axis).
    coverage : float
        Fraction of the direction grid visited (see :func:`direction_coverage`).

    """

    axis_body: F64
    axis_enu: F64
    twist_deg: float
    twist_range_deg: float
    mean_rate_deg_s: float
    rate_cv: float
    swing_rms_deg: float
    axis_spread: float
    coverage: float


def angular_rate(t_ns: ArrayLike, q_enu_body: ArrayLike) -> tuple[F64, F64, F64]:
    """Angular rate from consecutive attitudes (rad/s), one row per interval.

    Parameters
    ----------
    t_ns : array_like of int64, shape (N,)
        Attitude stamps, ns.
    q_enu_body : array_like, shape (N, 4)
        Attitudes, scalar-last.

    Returns
    -------
    w_body, w_enu : ndarray, shape (N-1, 3)
        ``log(q_k^-1 q_k+1) / dt`` (body frame) and ``log(q_k+1 q_k^-1) / dt`` (ENU).
    dt_s : ndarray, shape (N-1,)

    """
    t = np.asarray(t_ns, dtype=np.int64)
    q = np.asarray(q_enu_body, dtype=float)
    dt = np.diff(t).astype(float) * 1e-9
    dts = np.where(dt > 0, dt, np.inf)
    w_body = quat_to_rotvec(quat_mul(quat_conj(q[:-1]), q[1:])) / dts[:, None]
    w_enu = quat_rotate(q[:-1], w_body)  # same rotation seen in ENU (first order in dt)
    return w_body, w_enu, dt


# Near-equal-area grid of directions on the sphere (Fibonacci lattice), for coverage.
def fibonacci_sphere(n: int) -> F64:
    """``n`` near-uniform unit vectors (Fibonacci lattice), shape (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5**0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


COVERAGE_CELLS = 100  # ~20 deg cells: a full single-axis circle visits about 0.15-0.2 of them
_GRID = fibonacci_sphere(COVERAGE_CELLS)


def direction_coverage(dirs: ArrayLike, n_cells: int = COVERAGE_CELLS) -> float:
    """Fraction of a near-equal-area spherical grid visited by directions ``dirs`` (N, 3).

    Each direction is assigned to its nearest grid point (Fibonacci lattice of ``n_cells``
    points, cells of about 20 deg for 100); the result is the fraction of cells hit. A static
    stretch gives ``1/n_cells``, a full rotation about one axis a great or small circle (about
    0.15-0.2 for a field far from the axis), tumbling in all directions approaches 1. We chose
    this over the eigenvalues of the direction scatter because a circle and a full sphere can
    have similar scatter eigenvalues while only the sphere determines a soft-iron matrix.
    """
    d = np.asarray(dirs, dtype=float).reshape(-1, 3)
    d = d[np.all(np.isfinite(d), axis=1)]
    if d.shape[0] == 0:
        return 0.0
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    grid = _GRID if n_cells == COVERAGE_CELLS else fibonacci_sphere(n_cells)
    # decimate very long inputs: neighbouring samples fall in the same cell anyway
    step = max(1, d.shape[0] // 20000)
    cell = np.argmax(d[::step] @ grid.T, axis=1)
    return float(np.unique(cell).size / grid.shape[0])


NET_AXIS_FRACTION = 0.25  # net rotation / path length above which the net direction is the axis


def fit_rotation(
    t_ns: ArrayLike,
    q_enu_body: ArrayLike,
    *,
    field_dirs_body: ArrayLike | None = None,
    w_body: ArrayLike | None = None,
    w_enu: ArrayLike | None = None,
) -> RotationFit:
    """Fit one rotation axis to a stretch of attitude and describe the motion.

    The axis is the principal eigenvector of the scatter ``sum w w^T dt`` of the angular rate
    (robust to rotations beyond 180 deg, unlike the rotation vectors of ``q_0^-1 q_k``), or the
    direction of the net rotation ``sum w dt`` when that is at least ``NET_AXIS_FRACTION`` of
    the rotation path ``sum |w| dt`` (a net turn with a large back-and-forth wobble).

    Parameters
    ----------
    t_ns : array_like of int64, shape (N,), N >= 2
        Attitude stamps, ns.
    q_enu_body : array_like, shape (N, 4)
        Attitudes, scalar-last.
    field_dirs_body : array_like, shape (N, 3), optional
        Field directions seen by the sensor (e.g. the magnetometer readings) for the coverage;
        without it the direction of ENU north-and-down (``[0, 0.5, -0.866]``) rotated into
        the body frame is used.
    w_body, w_enu : array_like, shape (N-1, 3), optional
        Precomputed (e.g. smoothed) angular rates, rad/s.

    Returns
    -------
    RotationFit

    """
    t = np.asarray(t_ns, dtype=np.int64)
    q = np.asarray(q_enu_body, dtype=float)
    if t.shape[0] < 2:
        raise ValueError("need at least two attitude samples to fit a rotation")
    if w_body is not None and w_enu is not None:
        wb = np.asarray(w_body, dtype=float)
        we = np.asarray(w_enu, dtype=float)
        dt = np.diff(t).astype(float) * 1e-9
    else:
        wb, we, dt = angular_rate(t, q)
    ok = np.isfinite(dt) & (dt > 0) & np.all(np.isfinite(wb), axis=1)
    dtk = np.where(ok, dt, 0.0)
    wbk = np.where(ok[:, None], wb, 0.0)
    wek = np.where(ok[:, None], we, 0.0)
    S = (wbk * dtk[:, None]).T @ wbk
    evals, evecs = np.linalg.eigh(S)
    axis_b = evecs[:, -1]
    spread = float(evals[-2] / evals[-1]) if evals[-1] > 0 else 1.0
    Se = (wek * dtk[:, None]).T @ wek
    axis_e = np.linalg.eigh(Se)[1][:, -1]
    # When a net rotation dominates (hand-held turning with a large oscillating wobble about
    # another axis), its direction is the axis the twist is about, not the wobble's.
    path = float(np.sum(np.linalg.norm(wbk, axis=1) * dtk))
    net_b = np.sum(wbk * dtk[:, None], axis=0)
    net_e = np.sum(wek * dtk[:, None], axis=0)
    if path > 0 and np.linalg.norm(net_b) >= NET_AXIS_FRACTION * path:
        axis_b = net_b / np.linalg.norm(net_b)
        axis_e = net_e / max(np.linalg.norm(net_e), 1e-300)
    rate = wbk @ axis_b
    net = float(np.sum(rate * dtk))
    if net < 0:
        axis_b, rate, net = -axis_b, -rate, -net
    if float(np.sum((wek @ axis_e) * dtk)) < 0:
        axis_e = -axis_e
    cum = np.concatenate([[0.0], np.cumsum(rate * dtk)])
    T = float(np.sum(dtk))
    mean_rate = net / T if T > 0 else 0.0
    if T > 0 and abs(mean_rate) > 0:
        var = float(np.sum(dtk * (rate - mean_rate) ** 2) / T)
        cv = float(np.sqrt(var) / abs(mean_rate))
    else:
        cv = float("inf")
    # q_0^-1 q_k: rotation in the body frame since the start (evenly thinned on long stretches:
    # an RMS does not need every sample)
    rel = quat_mul(quat_conj(q[:1]), q[:: max(1, q.shape[0] // 50000)])
    sw, _ = swing_twist(rel, axis_b, TwistSide.RIGHT)
    swing_rms = float(np.degrees(np.sqrt(np.mean(rotation_angle(sw) ** 2))))
    if field_dirs_body is None:
        f_enu = np.array([0.0, 0.5, -np.sqrt(0.75)])
        field_dirs_body = quat_rotate(quat_conj(q), np.broadcast_to(f_enu, (q.shape[0], 3)))
    return RotationFit(
        axis_body=axis_b,
        axis_enu=axis_e,
        twist_deg=float(np.degrees(net)),
        twist_range_deg=float(np.degrees(cum.max() - cum.min())),
        mean_rate_deg_s=float(np.degrees(mean_rate)),
        rate_cv=cv,
        swing_rms_deg=swing_rms,
        axis_spread=spread,
        coverage=direction_coverage(field_dirs_body),
    )


__all__ = [
    "TwistSide",
    "swing_twist",
    "twist_angle",
    "rotation_angle",
    "axis_angle_quat",
    "min_rotation_quat",
    "tang_delta_gamma",
    "tang_eta",
    "wrap_angle",
    "tilted_rotation",
    "exact_eta",
    "tang_minor_spin",
    "tang_residual_rotation",
    "MinorSpinBound",
    "minor_spin_bound",
    "fit_alpha_from_eta",
    "HEADING_STATS_KEYS",
    "heading_error_stats",
    "octonion",
    "octonion_mul",
    "octonion_conj",
    "octonion_norm",
    "RotationFit",
    "angular_rate",
    "fibonacci_sphere",
    "direction_coverage",
    "fit_rotation",
    "rotvec_to_quat",
]

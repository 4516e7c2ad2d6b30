"""Turntable attitude source, its axis tilt (``axis_tilt``) and the heading error it causes.

More in docs/modules.md, ``stages.turntable``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from pipeline.core.errors import ChannelError, EstimationError
from pipeline.core.geometry import (
    quat_conj,
    quat_mul,
    quat_rotate,
    quat_to_matrix,
    rotvec_to_quat,
    so3_exp,
)
from pipeline.core.recording import AlignedSeries, AttitudeSeries, Recording, Role
from pipeline.model.forward import reading
from pipeline.model.tang import (
    axis_angle_quat,
    heading_error_stats,
    min_rotation_quat,
    twist_angle,
    wrap_angle,
)
from stages.context import Context

F64 = NDArray[np.float64]


def _unit(v: ArrayLike) -> F64:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def tilt_basis(nominal_axis_enu: ArrayLike = (0.0, 0.0, 1.0)) -> tuple[F64, F64]:
    """Two horizontal-ish unit vectors (east-like, north-like) perpendicular to the axis.

    For the nominal axis up they are ENU east and north; otherwise east and north projected
    onto the plane perpendicular to the axis (north falls back to a perpendicular of east).
    """
    n = _unit(nominal_axis_enu)
    e = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(e) < 1e-6:
        e = np.array([0.0, 1.0, 0.0]) - n[1] * n
    e = _unit(e)
    return e, np.cross(n, e)


def tilt_quat(
    tilt_deg: float, azimuth_deg: float, nominal_axis_enu: ArrayLike = (0.0, 0.0, 1.0)
) -> F64:
    """Pure tilt ``T`` (shape (4,)) taking the nominal ENU axis onto the true one.

    ``azimuth_deg`` is the direction the true axis leans to, clockwise from north.
    """
    t = np.radians(tilt_deg)
    az = np.radians(azimuth_deg)
    return _tilt_quat_vec(np.array([t * np.sin(az), t * np.cos(az)]), nominal_axis_enu)


def _tilt_quat_vec(tau_rad: F64, nominal_axis_enu: ArrayLike = (0.0, 0.0, 1.0)) -> F64:
    """Tilt from the lean vector ``tau = tilt * (sin az, cos az)`` (rad) in the tilt basis."""
    n = _unit(nominal_axis_enu)
    e1, e2 = tilt_basis(n)
    lean = tau_rad[0] * e1 + tau_rad[1] * e2
    return rotvec_to_quat(np.cross(n, lean))  # rotating n by |lean| towards lean


def turntable_quat(
    angle_rad: ArrayLike,
    nominal_axis_body: ArrayLike = (0.0, 0.0, 1.0),
    nominal_axis_enu: ArrayLike = (0.0, 0.0, 1.0),
    tilt: F64 | None = None,
) -> F64:
    """Attitude ``q_enu_body`` (N, 4) of a turntable at angles ``angle_rad`` (N,).

    ``q = T * q_align * exp(angle a_body / 2)``; ``tilt`` is ``T`` (identity when None).
    """
    q_align = min_rotation_quat(nominal_axis_body, nominal_axis_enu)
    q = quat_mul(q_align, axis_angle_quat(nominal_axis_body, np.asarray(angle_rad, float)))
    if tilt is not None:
        q = quat_mul(tilt, q)
    return q


@dataclass(frozen=True)
class TurntableAttitude:
    """Fill ``Recording.attitude`` from the turntable angle channel.

    Parameters
    ----------
    nominal_axis_body : 3-tuple
        The turntable axis in the body frame.
    nominal_axis_enu : 3-tuple
        The turntable axis in ENU (up for a level table).
    tilt_deg, azimuth_deg : float
        A known (e.g. fitted by :func:`fit_axis_tilt`) tilt of the true axis; the attitude is
        then compensated: ``q = T q_nom``. Azimuth clockwise from north, degrees.

    """

    nominal_axis_body: tuple[float, float, float] = (0.0, 0.0, 1.0)
    nominal_axis_enu: tuple[float, float, float] = (0.0, 0.0, 1.0)
    tilt_deg: float = 0.0
    azimuth_deg: float = 0.0

    requires: ClassVar[frozenset[str]] = frozenset({"recording"})
    provides: ClassVar[frozenset[str]] = frozenset({"recording"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` with a recording whose ``attitude`` comes from the turntable."""
        return ctx.replace(recording=self.apply(ctx.recording))

    def apply(self, rec: Recording | None) -> Recording:
        """Return the recording with ``attitude`` built from its turntable channel."""
        if rec is None or rec.turntable is None or len(rec.turntable) == 0:
            raise ChannelError(
                "no turntable angle channel to build the attitude from",
                role="attitude",
                path=None if rec is None else rec.path,
                hint="record the turntable angle (std_msgs/msg/Float64 in degrees or "
                "magalign.Turntable) or give an attitude channel",
            )
        tilt = None
        if self.tilt_deg != 0.0:
            tilt = tilt_quat(self.tilt_deg, self.azimuth_deg, self.nominal_axis_enu)
        q = turntable_quat(
            rec.turntable.angle_rad, self.nominal_axis_body, self.nominal_axis_enu, tilt
        )
        topic = next((c.topic for c in rec.channels if c.role is Role.TURNTABLE), None)
        return dataclasses.replace(
            rec,
            attitude=AttitudeSeries(rec.turntable.t_ns, q),
            attitude_topic=rec.attitude_topic or topic,
        )


# ----------------------------------------------------------------------------- heading error


@dataclass(frozen=True)
class HeadingStats:
    """Tang 2016, Table 2 statistics of a heading (azimuth) error series, degrees."""

    mean_deg: float
    var_deg2: float
    max_deg: float
    min_deg: float
    n: int
    extra: tuple[tuple[str, float], ...] = ()

    def to_dict(self) -> dict[str, float]:
        """JSON-ready dict (the keys of :func:`pipeline.model.tang.heading_error_stats`)."""
        return {
            "mean_deg": self.mean_deg,
            "var_deg2": self.var_deg2,
            "max_deg": self.max_deg,
            "min_deg": self.min_deg,
            **dict(self.extra),
            "n": self.n,
        }


def heading_stats(eta_rad: ArrayLike) -> HeadingStats:
    """Mean, variance, maximum and minimum of a heading error (rad in, degrees out).

    A typed view of :func:`pipeline.model.tang.heading_error_stats` (Tang 2016, Table 2).
    """
    d = heading_error_stats(eta_rad)
    main = ("mean_deg", "var_deg2", "max_deg", "min_deg", "n")
    extra = tuple((k, v) for k, v in d.items() if k not in main)
    return HeadingStats(
        d["mean_deg"], d["var_deg2"], d["max_deg"], d["min_deg"], int(d["n"]), extra
    )


def heading_error(
    q_enu_body: ArrayLike, q_ref_enu_body: ArrayLike, axis_enu: ArrayLike = (0.0, 0.0, 1.0)
) -> F64:
    """Heading error (rad, (N,)) of an attitude series against a reference series.

    Twist about ``axis_enu`` of the rotation since the first sample, ``q_k q_0^-1``, minus the
    same for the reference (Tang's azimuth error when ``q`` is the nominal turntable attitude
    and the reference the true one).
    """
    q = np.asarray(q_enu_body, dtype=float)
    r = np.asarray(q_ref_enu_body, dtype=float)
    tq = twist_angle(quat_mul(q, quat_conj(q[:1])), axis_enu)
    tr = twist_angle(quat_mul(r, quat_conj(r[:1])), axis_enu)
    return wrap_angle(tq - tr)


# ----------------------------------------------------------------------------- tilt fit


@dataclass(frozen=True)
class TiltResult:
    """Fitted turntable axis tilt with the misalignment (docs/modules.md).

    Attributes
    ----------
    tilt_deg, azimuth_deg : float
        Tilt of the true axis and the direction it leans to (clockwise from north).
    sigma_tilt_deg, sigma_azimuth_deg : float
        1-sigma; ``inf`` when the data do not determine them.
    lean_enu_deg : ndarray (2,)
        The lean vector ``tilt * (sin az, cos az)`` in the tilt basis (east, north for a level
        table), degrees; ``sigma_lean_deg`` its 1-sigma per component.
    unobservable_lean_dirs : tuple of ndarray (2,)
        Directions of the lean vector the data cannot determine.
    observable_lean_dirs : tuple of ndarray (2,)
        Directions it does determine, with ``sigma_observable_deg`` the 1-sigma of the lean
        along each (e.g. the lean towards the horizontal field when only the field is known).
        With one observable direction the lean along it carries a second-order bias from the
        unobserved lean, ``~ t_across^2 / 2 * |B_up| / |B_h|`` (0.03 deg for 1.5 deg across).
    axis_field_angle_deg : float
        Angle between the fitted true rotation axis and ``B_enu``: what a single-axis rotation
        always determines, whatever else is known.
    R_body_mag : ndarray (3, 3)
    B_enu_nT : ndarray (3,)
    residual_rms_nT : float
    heading_before, heading_after : HeadingStats or None
        Heading error of the nominal and of the compensated attitude against the true one
        when a true attitude is given; without it ``heading_before`` is the error the fitted
        tilt predicts for the nominal attitude and ``heading_after`` is None.
    notes : tuple of str
        Observability in words.

    """

    tilt_deg: float
    azimuth_deg: float
    sigma_tilt_deg: float
    sigma_azimuth_deg: float
    lean_enu_deg: F64
    sigma_lean_deg: F64
    R_body_mag: F64
    B_enu_nT: F64
    residual_rms_nT: float
    n_samples: int
    unobservable_lean_dirs: tuple[F64, ...] = ()
    observable_lean_dirs: tuple[F64, ...] = ()
    sigma_observable_deg: tuple[float, ...] = ()
    axis_field_angle_deg: float = float("nan")
    heading_before: HeadingStats | None = None
    heading_after: HeadingStats | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    def effect_params(self) -> dict[str, float]:
        """CONVENTIONS ``axis_tilt`` params."""
        return {"tilt_deg": self.tilt_deg, "azimuth_deg": self.azimuth_deg}

    def to_dict(self) -> dict:
        """JSON-ready dict."""

        def f(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {
            "tilt_deg": self.tilt_deg,
            "azimuth_deg": self.azimuth_deg,
            "sigma_tilt_deg": f(self.sigma_tilt_deg),
            "sigma_azimuth_deg": f(self.sigma_azimuth_deg),
            "lean_enu_deg": self.lean_enu_deg.tolist(),
            "sigma_lean_deg": [f(s) for s in self.sigma_lean_deg],
            "unobservable_lean_dirs": [d.tolist() for d in self.unobservable_lean_dirs],
            "observable_lean_dirs": [d.tolist() for d in self.observable_lean_dirs],
            "sigma_observable_deg": list(self.sigma_observable_deg),
            "axis_field_angle_deg": self.axis_field_angle_deg,
            "R_body_mag": self.R_body_mag.tolist(),
            "B_enu_nT": self.B_enu_nT.tolist(),
            "residual_rms_nT": self.residual_rms_nT,
            "n_samples": self.n_samples,
            "heading_before": _opt_dict(self.heading_before),
            "heading_after": _opt_dict(self.heading_after),
            "notes": list(self.notes),
        }


def _opt_dict(h: HeadingStats | None) -> dict | None:
    return None if h is None else h.to_dict()


def _kabsch_R(y_mag: F64, b_body: F64) -> F64:
    """``R_body_mag`` minimising ``sum |y - R.T b|^2`` (Wahba)."""
    H = y_mag.T @ b_body  # sum y b^T; M = R.T = U V^T
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    M = U @ np.diag([1.0, 1.0, d]) @ Vt
    return M.T


def fit_axis_tilt(
    recording: Recording,
    aligned: AlignedSeries | None = None,
    *,
    nominal_axis_body: ArrayLike = (0.0, 0.0, 1.0),
    nominal_axis_enu: ArrayLike = (0.0, 0.0, 1.0),
    reference_field_enu_nT: ArrayLike | None = None,
    R_known_body_mag: ArrayLike | None = None,
    R_nominal_body_mag: ArrayLike | None = None,
    q_true_enu_body: ArrayLike | None = None,
    max_samples: int = 20000,
    prior_tilt_deg: float = 10.0,
) -> TiltResult:
    """Fit the turntable axis tilt jointly with ``R_body_mag`` (and ``B_enu``) by least squares.

    Model: ``y_k = R_body_mag.T C(T q_nom(Omega(t_k - tau))).T B_enu + noise`` (module
    docstring). Parameters: a left perturbation of ``R_body_mag`` (unless known), ``B_enu``
    (unless a reference field is given) and the lean vector of the axis (2). A weak prior
    (``prior_tilt_deg``, and 10 deg on the rotation perturbation) keeps the unobservable
    combinations at their starting values; observability is judged from the data alone (Schur
    complement of the lean block), and unobservable lean directions get infinite sigma.

    Parameters
    ----------
    recording : Recording
        With a turntable angle channel (and the magnetometer).
    aligned : AlignedSeries, optional
        Magnetometer samples to use (its stamps, readings and ``time_offset_s``); the whole
        magnetometer series of the recording otherwise.
    nominal_axis_body, nominal_axis_enu : array_like (3,)
        Nominal turntable axis in the body frame and in ENU.
    reference_field_enu_nT : array_like (3,), optional
        Known background field (IGRF or measured): makes the tilt towards the field observable.
    R_known_body_mag : array_like (3, 3), optional
        Known mounting (held fixed): with a reference field, makes the whole tilt observable.
    R_nominal_body_mag : array_like (3, 3), optional
        Starting value of the misalignment (identity otherwise).
    q_true_enu_body : array_like (N, 4), optional
        True attitude at the samples used (simulation): heading errors before/after are then
        measured against it.
    max_samples : int
        The fit uses at most this many evenly spaced samples.
    prior_tilt_deg : float
        1-sigma of the weak prior on each lean component.

    Returns
    -------
    TiltResult

    Raises
    ------
    ChannelError
        Without a turntable channel.
    EstimationError
        With too few samples inside the turntable span.

    """
    tt = recording.turntable
    if tt is None or len(tt) < 2:
        raise ChannelError(
            "axis tilt needs a turntable angle channel", role="attitude", path=recording.path
        )
    if aligned is not None:
        t_ns, y, tau = aligned.t_ns, np.asarray(aligned.mag_nT, float), aligned.time_offset_s
    else:
        t_ns, y, tau = recording.mag.t_ns, np.asarray(recording.mag.values, float), 0.0
    t_eval = t_ns.astype(np.int64) - int(round(tau * 1e9))
    inside = (t_eval >= tt.t_ns[0]) & (t_eval <= tt.t_ns[-1])
    if q_true_enu_body is not None:
        q_true_all = np.asarray(q_true_enu_body, dtype=float)[inside]
    t_eval, y = t_eval[inside], y[inside]
    if t_eval.size < 10:
        raise EstimationError(
            f"only {t_eval.size} magnetometer samples fall inside the turntable record",
            path=recording.path,
        )
    ref = float(tt.t_ns[0])
    omega_all = np.interp(
        (t_eval - ref).astype(float), (tt.t_ns - ref).astype(float), tt.angle_rad
    )
    n_enu = _unit(nominal_axis_enu)
    q_nom_all = turntable_quat(omega_all, nominal_axis_body, n_enu)
    step = max(1, t_eval.size // max_samples)
    q_nom, yk = q_nom_all[::step], y[::step]
    N = yk.shape[0]

    B_known = reference_field_enu_nT is not None
    R_known = R_known_body_mag is not None
    B0 = np.asarray(reference_field_enu_nT, float) if B_known else None
    if R_known:
        R0 = np.asarray(R_known_body_mag, float)
    elif R_nominal_body_mag is not None:
        R0 = np.asarray(R_nominal_body_mag, float)
    else:
        R0 = np.eye(3)

    # starting values without tilt: alternate B (mean restored field) and R (Wahba)
    def b_body(q: F64, B: F64) -> F64:
        return quat_rotate(quat_conj(q), np.broadcast_to(B, (q.shape[0], 3)))

    R, B = R0.copy(), (B0.copy() if B0 is not None else None)
    for _ in range(1 if (B_known and R_known) else 30):
        if not B_known:
            B = np.mean(quat_rotate(q_nom, yk @ R.T), axis=0)
        if not R_known:
            assert B is not None  # given, or set just above
            R = _kabsch_R(yk, b_body(q_nom, B))
    assert B is not None  # given, or set in the loop (which runs when it is not given)

    n_r = 0 if R_known else 3
    n_b = 0 if B_known else 3

    def unpack(x: F64) -> tuple[F64, F64, F64]:
        Rx = R if R_known else so3_exp(x[:3]) @ R
        Bx = B if B_known else x[n_r : n_r + 3]
        return Rx, Bx, x[n_r + n_b :]

    def predict(x: F64) -> F64:
        # (M2)-(M3) of THE forward model with the tilted turntable attitude
        Rx, Bx, lean = unpack(x)
        q_true = quat_mul(_tilt_quat_vec(lean, n_enu), q_nom)
        Ct = np.swapaxes(quat_to_matrix(q_true), -1, -2)
        return reading(Ct, Bx, Rx).y_nT

    x0 = np.concatenate([np.zeros(n_r), (B if not B_known else np.zeros(0)), np.zeros(2)])
    r0 = (predict(x0) - yk).ravel()
    s_ref = max(float(np.sqrt(np.mean(r0**2))), 1.0)
    sig_prior = np.concatenate(
        [
            np.full(n_r, np.radians(10.0)),
            np.full(n_b, np.inf),
            np.full(2, np.radians(prior_tilt_deg)),
        ]
    )
    w_prior = np.where(np.isfinite(sig_prior), s_ref / sig_prior, 0.0)
    w_prior *= 1e-3  # weak: only to fix what the data leave free

    def residual(x: F64) -> F64:
        return np.concatenate([(predict(x) - yk).ravel(), w_prior * (x - x0)])

    scale = np.concatenate([np.full(n_r, 1e-2), np.full(n_b, 100.0), np.full(2, 1e-2)])
    sol = least_squares(residual, x0, x_scale=scale, method="trf", xtol=1e-12, ftol=1e-12)
    x = sol.x
    J = sol.jac[: 3 * N]
    r = sol.fun[: 3 * N]
    dof = max(3 * N - x.size, 1)
    s2 = max(float(r @ r) / dof, 1e-12)
    info = J.T @ J / s2
    # Schur complement of the lean block against the nuisance parameters
    k = n_r + n_b
    I_ll, I_ln, I_nn = info[k:, k:], info[k:, :k], info[:k, :k]
    S = I_ll - (I_ln @ np.linalg.pinv(I_nn, rcond=1e-10) @ I_ln.T if k else 0.0)
    ev, evec = np.linalg.eigh(0.5 * (S + S.T))
    scale_ll = max(float(np.max(np.diag(I_ll))), 1e-300)
    obs = ev > 1e-7 * scale_ll
    cov = np.zeros((2, 2))
    for i in range(2):
        if obs[i]:
            cov += np.outer(evec[:, i], evec[:, i]) / ev[i]
    unobs = tuple(evec[:, i].copy() for i in range(2) if not obs[i])
    obs_dirs = tuple(evec[:, i].copy() for i in range(2) if obs[i])
    sig_obs = tuple(float(np.degrees(1.0 / np.sqrt(ev[i]))) for i in range(2) if obs[i])

    R_fit, B_fit, lean = unpack(x)
    tilt = float(np.linalg.norm(lean))
    az = float(np.degrees(np.arctan2(lean[0], lean[1])) % 360.0)

    def sig(g: F64) -> float:
        if any(abs(float(g @ u)) > 1e-6 * max(float(np.linalg.norm(g)), 1e-300)
               for u in unobs):
            return float("inf")
        return float(np.sqrt(max(float(g @ cov @ g), 0.0)))

    g_tilt = lean / tilt if tilt > 0 else np.array([1.0, 0.0])
    g_az = np.array([lean[1], -lean[0]]) / max(tilt**2, 1e-300)
    sig_lean = np.array(
        [sig(np.array([1.0, 0.0])), sig(np.array([0.0, 1.0]))]
    )

    notes = []
    if not B_known:
        notes.append(
            "B_enu estimated: a tilt of the rotation axis is absorbed exactly by B_enu and "
            "R_body_mag; give a reference field (and a known mounting) to determine it"
        )
    elif not R_known:
        notes.append(
            "reference field known, mounting fitted: only the lean towards the horizontal field "
            "is observable; the lean across it trades off with R_body_mag"
        )
    else:
        notes.append("reference field and mounting known: both tilt components observable")

    T_fit = _tilt_quat_vec(lean, n_enu)
    q_comp_all = quat_mul(T_fit, q_nom_all)
    if q_true_enu_body is not None:
        before = heading_stats(heading_error(q_nom_all, q_true_all, n_enu))
        after = heading_stats(heading_error(q_comp_all, q_true_all, n_enu))
    else:
        before = heading_stats(heading_error(q_nom_all, q_comp_all, n_enu))
        after = None
    return TiltResult(
        tilt_deg=float(np.degrees(tilt)),
        azimuth_deg=az,
        sigma_tilt_deg=float(np.degrees(sig(g_tilt))),
        sigma_azimuth_deg=float(np.degrees(sig(g_az))),
        lean_enu_deg=np.degrees(lean),
        sigma_lean_deg=np.degrees(sig_lean),
        R_body_mag=R_fit,
        B_enu_nT=np.asarray(B_fit, float),
        residual_rms_nT=float(np.sqrt(np.mean(r**2))),
        n_samples=N,
        unobservable_lean_dirs=unobs,
        observable_lean_dirs=obs_dirs,
        sigma_observable_deg=sig_obs,
        axis_field_angle_deg=float(
            np.degrees(np.arccos(np.clip(quat_rotate(T_fit, n_enu) @ _unit(B_fit), -1.0, 1.0)))
        ),
        heading_before=before,
        heading_after=after,
        notes=tuple(notes),
    )


# ----------------------------------------------------------------------------- processing


@dataclass(frozen=True)
class AxisTiltNote:
    """Stage: record the turntable axis tilt, or why it is not identifiable, in the calibration.

    Runs after the estimate (and diagnose), which build the calibration from an attitude that
    :class:`TurntableAttitude` has already compensated; the tilt is bookkeeping here
    (``Calibration.effects["axis_tilt"]``, CONVENTIONS params), restore does not apply it again.

    Parameters
    ----------
    params : tuple of (str, float)
        ``(("tilt_deg", t), ("azimuth_deg", az))``; empty when the tilt was not fitted.
    warnings : tuple of str
        Added to ``Calibration.warnings``.

    """

    params: tuple[tuple[str, float], ...] = ()
    warnings: tuple[str, ...] = ()

    requires: ClassVar[frozenset[str]] = frozenset({"calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"calibration"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` with ``axis_tilt`` in the calibration's effects and warnings."""
        cal = ctx.calibration
        assert cal is not None  # required: the pipeline checks it at build time
        effects = dict(cal.effects or {})
        warnings = tuple(cal.warnings)
        if self.params:
            found = effects.get("axis_tilt")
            if isinstance(found, dict) and found:
                warnings += (
                    "axis_tilt: the attitude was compensated for the fitted tilt "
                    f"{dict(self.params)}; a further tilt {found} was found on the compensated "
                    "attitude (not composed)",
                )
            effects["axis_tilt"] = dict(self.params)
        return ctx.replace(
            calibration=cal.replace(effects=effects, warnings=warnings + self.warnings)
        )


def plan_turntable(
    recording: Recording,
    *,
    reference_field_enu_nT: ArrayLike | None = None,
    nominal_axis_body: tuple[float, float, float] = (0.0, 0.0, 1.0),
    nominal_axis_enu: tuple[float, float, float] = (0.0, 0.0, 1.0),
) -> tuple[TurntableAttitude, AxisTiltNote]:
    """Stages for a recording whose attitude is a turntable angle: attitude and axis tilt.

    With a reference field the tilt is fitted (:func:`fit_axis_tilt`, jointly with the
    misalignment) and the attitude built from the angle is compensated for it (Tang 2016);
    without one the tilt is not identifiable (a tilted axis is absorbed exactly by ``B_enu``
    and ``R_body_mag``) and the returned note says so.

    Parameters
    ----------
    recording : Recording
        With a turntable angle channel.
    reference_field_enu_nT : array_like (3,), optional
        Known background field, ENU, nT.
    nominal_axis_body, nominal_axis_enu : 3-tuple
        Nominal turntable axis in the body frame and in ENU.

    Returns
    -------
    attitude_stage : TurntableAttitude
        Compensated when the tilt was fitted.
    note_stage : AxisTiltNote
        To run after the estimate: writes ``axis_tilt`` and warnings into the calibration.

    """
    if reference_field_enu_nT is None:
        why = (
            "axis_tilt not identifiable: no reference field given, and a tilt of the turntable "
            "axis is absorbed exactly by the estimated B_enu and R_body_mag; give a reference "
            "field (--reference-field or --igrf) to fit it (Tang 2016)"
        )
        return TurntableAttitude(nominal_axis_body, nominal_axis_enu), AxisTiltNote(
            warnings=(why,)
        )
    res = fit_axis_tilt(
        recording,
        nominal_axis_body=nominal_axis_body,
        nominal_axis_enu=nominal_axis_enu,
        reference_field_enu_nT=reference_field_enu_nT,
    )
    params = (("tilt_deg", res.tilt_deg), ("azimuth_deg", res.azimuth_deg))
    warnings = []
    if res.unobservable_lean_dirs:
        lean = np.asarray(res.observable_lean_dirs[0]) if res.observable_lean_dirs else None
        part = "" if lean is None else (
            f"; only the lean along (east, north) = ({lean[0]:+.2f}, {lean[1]:+.2f}) is "
            f"determined ({float(lean @ res.lean_enu_deg):+.3f} deg, "
            f"sigma {res.sigma_observable_deg[0]:.1e} deg)"
        )
        warnings.append(
            "axis_tilt partly identifiable: with the mounting R_body_mag estimated, the lean of "
            "the turntable axis across the horizontal field trades off with R_body_mag and is "
            f"held at zero{part}"
        )
    stage = TurntableAttitude(
        nominal_axis_body, nominal_axis_enu, tilt_deg=res.tilt_deg, azimuth_deg=res.azimuth_deg
    )
    return stage, AxisTiltNote(params=params, warnings=tuple(warnings))

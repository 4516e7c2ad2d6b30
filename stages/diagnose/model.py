"""The effect library: every physical effect ``diagnose`` can add to the forward model.

Forward model: (M1)-(M5) of :mod:`pipeline.model.forward` (CONVENTIONS, "Measurement
model"), one magnetometer sample stamped ``t``::

    b(t)   = C_enu_body(t - tau).T @ T.T @ (B_enu + F(t))      (M1)-(M2), body frame, nT
    m(t)   = R_body_mag.T @ b(t)                               (M3), mag frame, nT
    y0(t)  = D @ m(t)                                          (M4)
    y(t)   = y0(t) + o + o_step * 1[t in windows] + E_s @ dy0/dt   (M5)

with ``F(t)`` the ENU field terms (``field_drift``, ``disturbance``, ``field_gradient``:
``G (p(t) - p_ref)`` with ``p`` the attitude source's position; ``local_source``;
``field_map``: ``Q sum_j w_j g_j(x)``, minus the gradient of a potential in the Laplace
eigenfunctions of a box, :mod:`pipeline.model.field_map`, its weights with a GP prior that
the fit adds as a ridge; ``heading_drift`` turns the field about Up, (M1h)), ``T`` the
turntable-axis tilt (``axis_tilt``, the diagnosis' own term), ``D = I + S`` (``soft_iron``,
``S`` symmetric and traceless because the isotropic scale of ``D`` is the field magnitude
when ``B_enu`` is estimated), ``o`` (``hard_iron``), ``o_step`` (``hard_iron_step``), ``E_s``
(``eddy_current``). ``dy0/dt`` is the rate of change
of the undisturbed reading caused by the rotation of the platform (the field the airframe
sees changing), so that a time offset is exactly the isotropic special case ``E_s = -tau I``
to first order.

:func:`evaluate` builds the pieces (``C.T`` and its central differences, cached over a fit;
the field with every term; the sensor offsets in term order) and hands them to
:func:`pipeline.model.forward.reading`, which computes (M2)-(M5) for it and for the
calibration's :func:`pipeline.model.forward.evaluate`; the Jacobian blocks they share are
:func:`pipeline.model.forward.field_jacobian` (J2),
:func:`~pipeline.model.forward.soft_iron_jacobian` (J4) and
:func:`~pipeline.model.forward.time_offset_jacobian` (J5); the columns of the
diagnosis' own terms (drift, disturbance, gradient, heading, tilt, steps, eddy) are here.

The baseline model is ``R_body_mag`` and ``B_enu`` only. Every other term is an
:class:`Effect`; each has its parameters, its contribution to the predicted reading, its
analytic Jacobian (checked numerically in ``tests/test_effects.py``), a physical explanation
and an identifiability condition computed from the data.

Parameter vector layout: ``[dR (3), B (3), term_1 (k_1), term_2 (k_2), ...]``. ``dR`` and the
tilt of ``axis_tilt`` are left perturbations on SO(3) (``R <- exp([dR]x) R``; (J1) of the
forward model is the right one), so the Jacobian columns are evaluated at zero perturbation
and the state stores the rotation matrices.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from pipeline.core.geometry import quat_to_matrix, right_times, rows_times, skew, so3_exp
from pipeline.core.vocabulary import EffectKind
from pipeline.model.attitude import (
    MEAN_INTERPOLATION_ERROR_SHAPE,
    AttitudeInterpolator,
    Interpolated,
    attitude_noise_rad,
    interpolation_error_rad,
    interpolation_error_shape,
    mean_interpolation_noise_factor,
)
from pipeline.model.effects import EFFECTS, IRON_PRIOR
from pipeline.model.effects.heading_drift import heading_drift_params as heading_params_over
from pipeline.model.effects.local_source import bearing_rad
from pipeline.model.effects.soft_iron import SOFT_BASIS
from pipeline.model.field_map import BASIS_NAME, FieldMapBasis, map_points, weighted_field
from pipeline.model.forward import (
    Reading,
    ascending,
    field_jacobian,
    ramp_profile,
    reading,
    rot_z,
)
from pipeline.model.forward import drift_basis as forward_drift_basis
from pipeline.model.forward import source_offset_enu as forward_source_offset
from pipeline.model.parallel import PerThread

F64 = NDArray[np.float64]


#: kinds that are events in time, present only inside their windows (``Effect.event``)
LOCAL_KINDS = frozenset(k for k, e in EFFECTS.items() if e.event)


@dataclass(frozen=True)
class AttitudeTrack:
    """Attitude samples evaluated at any time by THE interpolator (C1 cubic on SO(3)).

    The prediction of the diagnosis is the one of calibrate and restore
    (:mod:`pipeline.model.attitude`): the C1 cubic between the samples, held constant outside
    their span, no smoothing. (Attitude noise and interpolation error belong in the
    weights of the likelihood, not in the prediction.)

    Attributes
    ----------
    t_s : ndarray (M,)
        Stamps in seconds from the first magnetometer sample, increasing.
    q_enu_body : ndarray (M, 4)
        Scalar-last unit quaternions.
    lam : float or None
        The interpolator's cubic weight ((A7) of :mod:`pipeline.model.attitude`); None: from
        the samples (:attr:`cubic_weight`).

    """

    t_s: F64
    q_enu_body: F64
    lam: float | None = None
    _interp: AttitudeInterpolator = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        t_s = np.asarray(self.t_s, dtype=float)
        # ns relative to the first sample keep the spacing exact to 1 ns
        t_ns = np.round((t_s - t_s[0]) * 1e9).astype(np.int64) if len(t_s) else t_s
        interp = AttitudeInterpolator(t_ns, self.q_enu_body, max_gap_s=np.inf, clamp=True,
                                      cubic_weight=self.lam)
        object.__setattr__(self, "_interp", interp)

    def at(self, t_s: F64) -> F64:
        """Quaternions ``q_enu_body`` at ``t_s`` (held constant outside the span), (N, 4)."""
        tq = np.asarray(t_s, dtype=float) - float(self.t_s[0])
        return self._interp.at_rel_s(tq).q_enu_body

    def position(self, t_s: F64) -> F64:
        """Where each ``t_s`` falls between its two attitude samples, 0..1, (N,)."""
        tq = np.asarray(t_s, dtype=float) - float(self.t_s[0])
        return self._interp.position_rel_s(tq)

    def omega_body(self, t_s: F64) -> F64:
        """Angular velocity of the attitude at ``t_s``, body frame, rad/s, (N, 3) (exact)."""
        tq = np.asarray(t_s, dtype=float) - float(self.t_s[0])
        return self._interp.at_rel_s(tq).omega_body_rad_s

    @property
    def cubic_weight(self) -> float:
        """``lam`` of the interpolator (:mod:`pipeline.model.attitude`, (A7))."""
        return float(self._interp.cubic_weight)

    @property
    def interpolator(self) -> AttitudeInterpolator:
        """THE interpolator of this track."""
        return self._interp

    def noise_factor(self, t_s: F64) -> F64:
        """Interpolation noise factor at ``t_s`` (:meth:`AttitudeInterpolator.noise_factor`)."""
        return self._interp.noise_factor(self.position(t_s))


    @cached_property
    def step_s(self) -> float:
        """Median sample spacing, s (computed once: every evaluation asks for it)."""
        return float(np.median(np.diff(self.t_s))) if len(self.t_s) > 1 else 0.01


@dataclass(frozen=True)
class FitData:
    """What the model is fitted to.

    Attributes
    ----------
    t_s : ndarray (N,)
        Magnetometer stamps, seconds from the first magnetometer sample of the recording.
    y_nT : ndarray (N, 3)
        Magnetometer readings, mag frame, nT.
    track : AttitudeTrack
        Attitude ``q_enu_body`` on the same time axis (sensing time = stamp - tau).
    B_known_enu_nT : ndarray (3,) or None
        A reference field; when given, ``B_enu`` is held at it (not estimated).
    turntable_axis_body : ndarray (3,) or None
        Nominal rotation axis of a single-axis attitude source (turntable), body frame.
    p_m : ndarray (N, 3) or None
        Position of the attitude source at each sample, m, in ``position_frame`` (finite:
        samples without a position are not in the data when positions are used).
    p_ref_m : ndarray (3,) or None
        Reference position ``p_ref`` of ``field_gradient`` (the mean position), m.
    position_frame : str or None
        ``enu`` or ``attitude_source_local`` (third axis up, horizontal axes rotated about Up
        by an unknown angle).
    noise_model : (float, float, float) or None
        ``(sigma_mag2, c_att, c_int)``, nT^2: the variance of a residual component is
        modelled as ``sigma_mag2 + c_att f(s) + c_int g(s)``, ``f`` the interpolated attitude
        noise factor and ``g`` the interpolation error's shape at where the sample falls
        between two attitude samples (:func:`sample_weights`). None: equal weights.
    stride : int
        Every ``stride``-th usable sample was kept (decimated to a sample budget).
    n_available : int or None
        Usable samples before the decimation.
    interp_error_nT : ndarray (N, 3) or None
        What the attitude's interpolation error alone would leave in the residual
        (:func:`interpolation_error_proxy`); terms it could produce are not named.
    position_origin : dict or None
        ``{lat_deg, lon_deg, height_m}`` of geodetic positions turned to local ENU metres
        (CONVENTIONS "Positions"); None for local frames.

    """

    t_s: F64
    y_nT: F64
    track: AttitudeTrack
    B_known_enu_nT: F64 | None = None
    turntable_axis_body: F64 | None = None
    p_m: F64 | None = None
    p_ref_m: F64 | None = None
    position_frame: str | None = None
    stride: int = 1
    n_available: int | None = None
    noise_model: tuple[float, float, float] | None = None
    interp_error_nT: F64 | None = None
    position_origin: dict[str, float] | None = None

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def subset(self, mask: np.ndarray) -> FitData:
        """Return the samples where ``mask`` is true (same attitude track)."""
        p = None if self.p_m is None else self.p_m[mask]
        e = None if self.interp_error_nT is None else self.interp_error_nT[mask]
        return replace(self, t_s=self.t_s[mask], y_nT=self.y_nT[mask], p_m=p, interp_error_nT=e)

    @property
    def dp_m(self) -> F64:
        """Positions relative to the reference, (N, 3), m (zeros without positions)."""
        if self.p_m is None:
            return np.zeros((len(self), 3))
        ref = np.zeros(3) if self.p_ref_m is None else self.p_ref_m
        return self.p_m - ref

    @property
    def compiled(self) -> bool:
        """Whether the model's loops run compiled (numba): with positions, and only then.

        A recording with positions loads numba for its located sources
        (:mod:`pipeline.model.dipole_kernels`); the attitude's compiled pass
        (:mod:`pipeline.model.attitude_kernels`) then costs nothing more. Without positions
        no process pays for the compiler.
        """
        return self.p_m is not None

    @property
    def duration_s(self) -> float:
        """Span of the samples, s."""
        return float(self.t_s[-1] - self.t_s[0]) if len(self) > 1 else 0.0


@dataclass(frozen=True)
class Term:
    """One effect as a model term.

    Attributes
    ----------
    kind : EffectKind
    windows_s : tuple of (start, end)
        Half-open windows, s from the first magnetometer sample (local effects only).
    knot_step_s : float
        Spacing of the linear B-spline (hat) knots of a ``disturbance`` field, and of the
        sine modes of a ``hard_iron_step``'s transitions (one per ``knot_step_s``).
    ramps_s : tuple of (start, end)
        ``hard_iron_step``: the transitions while the magnet moved, each inside the window
        and touching one of its ends (``pipeline.model.forward.ramp_profile``).
    ramp_scale_s : float
        ``hard_iron_step``: the time scale of the GP prior of its transitions' modes, s (how
        quickly the field of a moving magnet may change shape); their prior's size is
        ``prior_nT`` and the noise it is weighed against ``noise_nT``.
    yaw_rad : float
        ``field_gradient`` in a position frame rotated about Up: the rotation ``Q = Rz(yaw)``
        from that frame to ENU, located by a search (like a window), not fitted.
    fit_yaw : bool
        ``local_source`` with positions in a frame of unknown bearing: the rotation
        ``Rz(psi)`` from the position frame to ENU is a seventh parameter of the source.
    domain_m : tuple of 3 (a, b)
        ``field_map``: the box of its basis in the position frame, m
        (:mod:`pipeline.model.field_map`); its bearing is ``yaw_rad`` (the gradient's).
    n_axis : tuple of 3 int
        ``field_map``: modes per axis (the complexity chosen on held-out blocks).
    length_scale_m : float
        ``field_map``: the GP prior's length scale ``l``, m.
    prior_nT : float
        ``field_map``: the prior's standard deviation of each field component, nT.
    noise_nT : float
        ``field_map``: the noise of the residual the prior is weighed against, nT: the
        ridge on weight ``j`` is ``(noise_nT^2 / var(w_j)) w_j^2`` in the fit's sum of squares.
    determined : tuple of k tuples of m floats
        A term the motion determines only in part: orthonormal columns ``A`` (k, m)
        spanning the combinations of its ``k`` parameters that are fitted; the value is
        ``fixed + A @ z`` with ``z`` the ``m`` fitted parameters, so the combinations
        outside the span (:meth:`undetermined`) stay at ``fixed``. Empty: every parameter
        is fitted.
    fixed : tuple of k floats
        The value of a partial term at zero fitted parameters (the undetermined combinations
        are held there); empty: zero.

    """

    kind: EffectKind
    windows_s: tuple[tuple[float, float], ...] = ()
    knot_step_s: float = 1.0
    ramps_s: tuple[tuple[float, float], ...] = ()
    ramp_scale_s: float = 0.0
    yaw_rad: float = 0.0
    fit_yaw: bool = False
    domain_m: tuple[tuple[float, float], ...] = ()
    n_axis: tuple[int, ...] = ()
    length_scale_m: float = 0.0
    prior_nT: float = 0.0
    noise_nT: float = 0.0
    determined: tuple[tuple[float, ...], ...] = ()
    fixed: tuple[float, ...] = ()

    @property
    def partial(self) -> bool:
        """Whether only some combinations of the term's parameters are fitted."""
        return bool(self.determined)

    def determined_matrix(self) -> F64:
        """Fitted combinations ``A`` (k, m), orthonormal columns; identity for a full term."""
        if not self.determined:
            return np.eye(self.full_size())
        return np.asarray(self.determined, dtype=float)

    def undetermined(self) -> F64:
        """Orthonormal columns (k, k - m) of the combinations held at ``fixed``.

        The orthogonal complement of :meth:`determined_matrix`, each column signed so that
        its largest component is positive (k - m = 0 columns for a full term).
        """
        B = self.determined_matrix()
        k, m = B.shape
        if m == k:
            return np.zeros((k, 0))
        U = np.linalg.svd(np.eye(k) - B @ B.T)[0][:, : k - m]
        big = np.argmax(np.abs(U), axis=0)
        return U * np.sign(U[big, np.arange(k - m)])

    def null_value(self) -> F64:
        """Value of the term at zero fitted parameters, (k,): ``fixed`` or zeros."""
        if self.fixed:
            return np.asarray(self.fixed, dtype=float)
        return np.zeros(self.full_size())

    def full_size(self) -> int:
        """Return the number of parameters of the unrestricted term (``k``)."""
        return self.unrestricted().n_params() if self.determined else self.n_params()

    def restricted(self, determined: F64, fixed: F64 | None = None) -> Term:
        """Return the term fitted only along the orthonormal columns ``determined`` (k, m)."""
        A = np.asarray(determined, dtype=float)
        f = () if fixed is None else tuple(float(x) for x in fixed)
        return replace(self, determined=tuple(tuple(float(x) for x in row) for row in A),
                       fixed=f)

    def unrestricted(self) -> Term:
        """Return the full term (every parameter fitted)."""
        return replace(self, determined=(), fixed=())

    def basis(self) -> FieldMapBasis:
        """Return the ``field_map`` basis of the term (its box and modes per axis)."""
        return FieldMapBasis.of(self.domain_m, self.n_axis)

    def prior_precision(self) -> F64 | None:
        """Ridge of the term's parameters, per nT^2, or None: its effect's prior."""
        return EFFECTS[self.kind].prior_precision(self)

    def knots(self) -> list[F64]:
        """Knot times of each disturbance window (hat functions, both ends included)."""
        out = []
        for a, b in self.windows_s:
            n = max(2, int(np.ceil((b - a) / self.knot_step_s)) + 1)
            out.append(np.linspace(a, b, n))
        return out

    def n_params(self) -> int:
        """Return the number of fitted parameters of the term (``m`` for a partial one)."""
        return self._n_params

    @cached_property
    def _n_params(self) -> int:
        """:meth:`n_params`, counted once per term (a step counts its transitions' modes)."""
        if self.determined:
            return len(self.determined[0])
        # the effect's module counts them (a step its transitions' modes, a map its basis)
        return EFFECTS[self.kind].n_params(self)

    def presence(self, t_s: F64) -> F64:
        """1 where the term acts: inside its windows, or everywhere without windows, (N,)."""
        if not self.windows_s:
            return np.ones(np.shape(t_s))
        return self.indicator(t_s)

    def step_profile(self, t_s: F64) -> tuple[F64, F64]:
        """``hard_iron_step``: plateau profile (N,) and transition basis (N, M).

        The offset is ``o s(t) + phi(t) c`` (``pipeline.model.forward.ramp_profile``); a step
        without transitions is ``s = 1[t in window]`` and ``M = 0``.
        """
        if not self.ramps_s:
            return self.indicator(t_s), np.zeros((np.size(t_s), 0))
        (window,) = self.windows_s
        return ramp_profile(t_s, window, self.ramps_s, self.knot_step_s)

    def indicator(self, t_s: F64) -> F64:
        """1 inside any window, else 0, shape (N,)."""
        ind = np.zeros(np.shape(t_s))
        for a, b in self.windows_s:
            ind[(t_s >= a) & (t_s < b)] = 1.0
        return ind




def source_offset_enu(term: Term, value: F64, p_m: F64, lever_enu: F64 | None = None) -> F64:
    """``r`` (N, 3), m, ENU: from the source at ``value[0:3]`` (position frame) to each ``p_m``.

    ``r = Rz(psi) (p - c) + C l``: the position frame turned to ENU by the source's yaw
    ``psi`` (``value[6]`` when ``fit_yaw``, else the term's ``yaw_rad``), plus the lever arm
    in ENU (``lever_enu``, (N, 3), when the model has one).
    """
    return forward_source_offset(value[0:3], bearing_rad(term, value), p_m, lever_enu)


def drift_basis(t_s: F64, t0_s: float, t1_s: float) -> F64:
    """Legendre P1..P4 of the time scaled to [-1, 1] over the recording, shape (N, 4).

    A slow field variation (diurnal, drift, up to about one period over the recording) is
    smooth: a few Legendre polynomials per ENU axis carry it; the constant is ``B_enu``.
    :func:`pipeline.model.forward.drift_basis` (``field_drift`` of (M1)) on ``t - t0``.
    """
    return forward_drift_basis(np.asarray(t_s) - t0_s, t1_s - t0_s)


@dataclass(frozen=True)
class ModelState:
    """Current values of every model parameter.

    Attributes
    ----------
    R_body_mag : ndarray (3, 3)
    B_enu_nT : ndarray (3,)
    terms : tuple of Term
    values : tuple of ndarray
        One parameter vector per term (axis_tilt stores its rotation in ``T_enu``).
    T_enu : ndarray (3, 3)
        Tilt of the turntable axis (identity without ``axis_tilt``).

    """

    R_body_mag: F64
    B_enu_nT: F64
    terms: tuple[Term, ...] = ()
    values: tuple[F64, ...] = ()
    T_enu: F64 = field(default_factory=lambda: np.eye(3))

    def n_params(self) -> int:
        """Length of the parameter (perturbation) vector."""
        return 6 + sum(t.n_params() for t in self.terms)

    def with_term(self, term: Term) -> ModelState:
        """Return the state with ``term`` appended at zero (no effect; ``fixed`` if partial).

        A term another one in the model shares a direction with (``time_offset`` beside an
        ``eddy_current``) takes that one's shared part (:meth:`canonical`: ``tau =
        -tr(E_s)/3`` with ``E_s`` made traceless), the same prediction to first order.
        """
        st = replace(self, terms=self.terms + (term,),
                     values=self.values + (term.null_value(),))
        shared = any(EFFECTS[t.kind].shares_with is term.kind for t in self.terms)
        return st.canonical() if shared else st

    def gauged(self) -> frozenset[EffectKind]:
        """Return the kinds held off the direction they share with another kind in the model.

        (:attr:`pipeline.model.effects.base.Effect.shares_with`.) A time offset and an eddy
        term share one direction to first order (``E_s = -tau I``); beside a time offset the
        eddy term is traceless: 8 free parameters (:meth:`n_free`), its isotropic part held
        at zero (its :meth:`~pipeline.model.effects.base.Effect.gauge_projector` in
        :func:`evaluate` and :meth:`update`).
        """
        kinds = {t.kind for t in self.terms}
        return frozenset(k for k in kinds if EFFECTS[k].shares_with in kinds)

    def n_free(self) -> int:
        """Free parameters, :meth:`n_params` less the shared directions.

        The count of the unit-information prior (``log n_eff`` each,
        :func:`~stages.diagnose.statistics.occam`) and of Occam's razor between two
        descriptions (nested.simplest).
        """
        return self.n_params() - sum(_shared_dimensions(k) for k in self.gauged())

    def canonical(self) -> ModelState:
        """Return the state with each shared part moved to the effect that holds it.

        The same prediction to first order; the state of :meth:`gauged` (for the rate pair,
        ``tau <- tau - tr(E_s)/3`` and ``E_s`` traceless). Any other state is returned as it
        is.
        """
        kinds = [t.kind for t in self.terms]
        vals = list(self.values)
        gauged = self.gauged()
        for i, kind in enumerate(kinds):
            if kind in gauged:
                eff = EFFECTS[kind]
                j = kinds.index(cast(EffectKind, eff.shares_with))
                own, other = eff.fold_shared(vals[i], vals[j])
                if not np.array_equal(other, vals[j]):  # else nothing was shared
                    vals[i], vals[j] = own, other
        if all(v is w for v, w in zip(vals, self.values, strict=True)):
            return self
        return replace(self, values=tuple(vals))

    @property
    def has_partial(self) -> bool:
        """Whether a term of the model is fitted only along some combinations."""
        return any(t.partial for t in self.terms)

    def unrestricted(self) -> ModelState:
        """Return the same values with every parameter free (the full Jacobian's layout)."""
        return replace(self, terms=tuple(t.unrestricted() for t in self.terms))

    def value(self, kind: EffectKind) -> F64 | None:
        """Parameter vector of the first term of ``kind``, or None."""
        for t, v in zip(self.terms, self.values, strict=True):
            if t.kind is kind:
                return v
        return None

    def offsets(self) -> list[int]:
        """Start index of each term's block in the parameter vector."""
        out, i = [], 6
        for t in self.terms:
            out.append(i)
            i += t.n_params()
        return out

    def prior_precision(self) -> F64 | None:
        """Ridge of every parameter, (P,), per nT^2; None when no term has a prior.

        The fit (:func:`stages.diagnose.fit.fit`) adds ``sum_i prec_i x_i^2`` to the sum of
        squares: each term's prior from its effect (:meth:`Term.prior_precision`: the GP
        priors of a map's weights and of a step's transitions); every other parameter has
        none (zero).
        """
        precs = [t.unrestricted().prior_precision() for t in self.terms]
        if all(p is None for p in precs):
            return None
        out = np.zeros(self.n_params())
        for t, i, prec in zip(self.terms, self.offsets(), precs, strict=True):
            if prec is not None:
                if t.partial:
                    # the ridge acts on the fitted coordinates z of ``fixed + A z``: the
                    # diagonal of A.T diag(prec) A (none for a term held whole, m = 0)
                    A = t.determined_matrix()
                    prec = np.einsum("km,k,km->m", A, prec, A)
                out[i : i + t.n_params()] = prec
        return out

    def prior_noise2(self) -> F64:
        """Return the noise variance each parameter's ridge is weighed against, (P,), nT^2.

        A prior's ridge is ``noise_nT^2 / var`` (:meth:`prior_precision`): with it, the
        prior's own variance ``var`` of each parameter is recovered whatever the residual
        has become since (:func:`stages.diagnose.statistics.prior_occam`). Zero where a
        parameter has no prior.
        """
        out = np.zeros(self.n_params())
        for t, i in zip(self.terms, self.offsets(), strict=True):
            out[i : i + t.n_params()] = t.noise_nT**2
        return out

    def flat_values(self) -> F64:
        """Return the parameters as one vector (P,): zeros for ``dR``, ``B_enu`` (perturbations)."""
        return np.concatenate([np.zeros(6)] + [_fitted_coordinates(t, v)
                                               for t, v in zip(self.terms, self.values,
                                                               strict=True)])

    def D(self) -> F64:
        """Soft-iron matrix ``I + S`` (identity without ``soft_iron``)."""
        s = self.value(EffectKind.SOFT_IRON)
        return np.eye(3) if s is None else np.eye(3) + np.tensordot(s, SOFT_BASIS, axes=1)

    def tau_s(self) -> float:
        """Time offset, s (0 without ``time_offset``)."""
        v = self.value(EffectKind.TIME_OFFSET)
        return 0.0 if v is None else float(v[0])

    def update(self, dx: F64, fixed_B: bool = False) -> ModelState:
        """Apply a perturbation ``dx`` (left perturbation for rotations)."""
        R = so3_exp(dx[0:3]) @ self.R_body_mag
        B = self.B_enu_nT if fixed_B else self.B_enu_nT + dx[3:6]
        vals, T = [], self.T_enu
        gauged = self.gauged()
        for t, v, i in zip(self.terms, self.values, self.offsets(), strict=True):
            d = dx[i : i + t.n_params()]
            if t.partial:
                d = t.determined_matrix() @ d
            if t.kind in gauged:
                d = EFFECTS[t.kind].gauge_projector() @ d  # held off the shared direction
            vals.append(v + d)
            # a term that holds its rotation in the state turns it (its values keep account)
            T = EFFECTS[t.kind].turn_frame(T, d)
        return replace(self, R_body_mag=R, B_enu_nT=B, values=tuple(vals), T_enu=T)

    def with_terms(self, terms: Sequence[Term], values: Sequence[F64]) -> ModelState:
        """Return the state with ``terms`` and their ``values`` in place of its own.

        A term whose effect holds its rotation in the state (``T_enu``, :attr:`~pipeline.
        model.effects.base.Effect.holds_frame`) takes it along when it leaves.
        """
        keeps = any(EFFECTS[t.kind].holds_frame for t in terms)
        return replace(self, terms=tuple(terms), values=tuple(values),
                       T_enu=self.T_enu if keeps else np.eye(3))


def _shared_dimensions(kind: EffectKind) -> int:
    """Return how many directions a gauged ``kind`` gives up to the effect it shares them with."""
    return len(EFFECTS[kind].shared_basis())


def _fitted_coordinates(term: Term, value: F64) -> F64:
    """Return the fitted parameters ``z`` (m,) of a value: ``A.T (value - fixed)`` if partial."""
    v = np.asarray(value, dtype=float).reshape(-1)
    if not term.partial:
        return v
    return term.determined_matrix().T @ (v - term.null_value())


@dataclass(frozen=True)
class Evaluation:
    """Prediction and Jacobian of the model at a state.

    Attributes
    ----------
    y_nT : ndarray (N, 3)
        Predicted reading, mag frame.
    J : ndarray (N, 3, P) or None
        d y / d (perturbation vector).
    ydot0_nT_s : ndarray (N, 3)
        Rotation-induced rate of change of the undisturbed reading ``D R.T db/dt``.
    G : ndarray (N, 3, 3)
        d y / d B_enu (per sample).
    sqrt_w : ndarray (N,) or None
        Square roots of the likelihood's weights (:func:`sample_weights`).
    J_held : ndarray (N, 3, Q) or None
        d y / d (the combinations partial terms hold at ``fixed``, :meth:`Term.undetermined`,
        in term order): what the model would gain if they were free. None without partial
        terms or without the Jacobian.

    """

    y_nT: F64
    J: F64 | None
    ydot0_nT_s: F64
    G: F64
    sqrt_w: F64 | None = None
    J_held: F64 | None = None

    @property
    def jac(self) -> F64:
        """``J`` of an evaluation made with the Jacobian (raises for one made without)."""
        if self.J is None:
            raise ValueError("the model was evaluated without its Jacobian")
        return self.J


def sample_weights(data: FitData, tau_s: float) -> F64 | None:
    """Likelihood weights of the samples from where they fall between attitude samples.

    The prediction is THE one (:mod:`pipeline.model.attitude`); what it cannot know about
    the attitude between two samples goes into the likelihood. The white noise of the
    attitude samples reaches the interpolated attitude with the variance factor ``f(s)``
    (:func:`pipeline.model.attitude.interpolation_noise_factor`), the interpolation's own
    error with ``g(s)`` (:func:`pipeline.model.attitude.interpolation_error_shape`: none on a
    sample, most midway), ``s`` the position of ``t - tau`` between its two samples. Each
    residual component then has the variance ``v = sigma_mag2 + c_att f(s) + c_int g(s)``
    (``FitData.noise_model``); the weight is ``w = v_mean / v`` with ``v_mean`` its average
    over ``s``, a constant: ``sum w r^2`` then has the same expectation whatever ``tau`` (an
    unweighted fit would drift ``tau`` and the eddy terms towards the low-noise mid-points).

    Returns
    -------
    ndarray (N,) or None
        None without a noise model.

    """
    if data.noise_model is None:
        return None
    return _weights_at(data, data.track.position(data.t_s - tau_s))


def _weights_at(data: FitData, pos: F64) -> F64 | None:
    """:func:`sample_weights` from where the sensing times fall between attitude samples."""
    if data.noise_model is None:
        return None
    s2, c, c_int = data.noise_model
    f = data.track.interpolator.noise_factor(pos)
    g = interpolation_error_shape(pos)
    v_mean = (s2 + mean_interpolation_noise_factor(data.track.cubic_weight) * c
              + MEAN_INTERPOLATION_ERROR_SHAPE * c_int)
    return v_mean / (s2 + c * f + c_int * g)


def _angle_variance_nT2(data: FitData) -> float:
    """Variance (nT^2) per component of ``C.T B`` per unit squared isotropic angle error.

    A small isotropic attitude error of RMS angle ``e`` moves each component by
    ``2/9 |B|^2 e^2`` in variance (``|B|`` from the readings).
    """
    y = np.asarray(data.y_nT, dtype=float)
    return 2.0 / 9.0 * float(np.mean(np.sum(y * y, axis=1)))


def estimate_noise_model(residual_nT: F64, data: FitData, e_int_nT: float | None = None
                         ) -> tuple[float, float, float] | None:
    """``(sigma_mag2, c_att, c_int)`` (nT^2) of :func:`sample_weights` from a baseline fit.

    ``c_att = 2/9 |B|^2 sigma_att^2``: an isotropic attitude error of RMS angle
    ``sigma_att`` (:func:`pipeline.model.attitude.attitude_noise_rad`, from the track's
    second differences) moves each component of ``C.T B`` by ``2/9 |B|^2 sigma_att^2`` in
    variance; ``c_int`` the same for the interpolation's own error midway
    (:func:`interpolation_error_nT`, from the track interpolated at two and four times its
    spacing); ``sigma_mag2`` is what the residual variance leaves (at least 5 % of
    it). None when both are negligible (below 0.1 % of the residual variance).
    """
    var = float(np.mean(np.asarray(residual_nT) ** 2))
    if not np.isfinite(var) or var <= 0:
        return None
    sig = attitude_noise_rad(data.track.q_enu_body)
    c = _angle_variance_nT2(data) * sig * sig
    if e_int_nT is None:
        e_int_nT = interpolation_error_nT(data)
    c_int = e_int_nT**2 / MEAN_INTERPOLATION_ERROR_SHAPE  # midway
    if c + c_int < 1e-3 * var:
        return None
    f = data.track.noise_factor(data.t_s)
    s2 = max(var - c * float(np.mean(f)) - c_int * MEAN_INTERPOLATION_ERROR_SHAPE, 0.05 * var)
    return (s2, c, c_int)


def interpolation_error_nT(data: FitData) -> float:
    """RMS of the interpolation error at the magnetometer, nT (noise taken out).

    :func:`pipeline.model.attitude.interpolation_error_rad` midway, averaged over the
    interval (``8/15`` of the midway variance), as a component of ``C.T B`` (``2/9 |B|^2``
    per unit squared angle, as the attitude noise of :func:`estimate_noise_model`).
    """
    e = interpolation_error_rad(data.track.interpolator)
    return float(np.sqrt(_angle_variance_nT2(data) * MEAN_INTERPOLATION_ERROR_SHAPE) * e)


def interpolation_error_proxy(state: ModelState, data: FitData) -> F64:
    """Return the interpolation error's imprint on the readings, (N, 3), nT, from the track.

    The model is evaluated with every other attitude sample (the same curve, ``lam`` and
    stamps at twice the spacing) and with all of them: the difference is the error at twice
    the spacing less the error at the spacing, ``(2^p - 1)`` times the latter (``p = 4`` for
    the cubic's midway error on evenly spaced samples, ``2`` for SLERP, blended by ``lam``;
    :func:`pipeline.model.attitude.interpolation_error_rad`). A proxy of the error's size and
    of the way it projects on the model's terms, not of its sign at each sample.
    """
    tr = data.track
    lam = tr.cubic_weight
    half = AttitudeTrack(tr.t_s[0::2], tr.q_enu_body[0::2], lam=lam)
    y_full = evaluate(state, data, jacobian=False).y_nT
    y_half = evaluate(state, replace(data, track=half), jacobian=False).y_nT
    p = 2.0 + 2.0 * lam
    return (y_half - y_full) / (2.0**p - 1.0)


_CT_CACHE: PerThread[dict[tuple, tuple[Any, _Attitude]]] = PerThread(dict)


@dataclass(frozen=True)
class _Attitude:
    """The attitude at some sensing times: ``C.T`` (N, 3, 3) and the interpolation itself.

    The interpolation (:class:`pipeline.model.attitude.Interpolated`) also gives where each
    time falls between two attitude samples and, computed on first use, the angular velocity
    there: the weights and the time offset's column of the same evaluation read them.
    """

    Ct: F64
    at: Interpolated


def _attitude(track: AttitudeTrack, t_s: F64, key: tuple | None = None,
              owners: Any = None, compiled: bool = False) -> _Attitude:
    """Return the attitude of ``track`` at ``t_s``; cached per (track, stamps, shift) in a fit.

    The cache keeps a reference to the objects whose ids form the key (``owners``), so an id
    cannot be reused by another array while its entry lives. ``compiled``: by the compiled
    pass (:meth:`AttitudeInterpolator.at_rel_s`), where numba is loaded anyway.
    """
    cache = _CT_CACHE.value
    if key is not None:
        hit = cache.get(key)
        if hit is not None and all(a is b for a, b in zip(hit[0], owners, strict=True)):
            return hit[1]
    tq = np.asarray(t_s, dtype=float) - float(track.t_s[0])  # as AttitudeTrack.at
    at = track.interpolator.at_rel_s(tq, compiled=compiled)
    out = _Attitude(at.Ct, at)
    if key is not None:
        if len(cache) > 48:
            cache.clear()  # bounded: the cache only spans the iterations of one fit
        cache[key] = (owners, out)
    return out


def _CT(track: AttitudeTrack, t_s: F64, key: tuple | None = None, owners: Any = None,
        compiled: bool = False) -> F64:
    """``C_enu_body(t).T`` (N, 3, 3); cached per (track, stamps, shift) during a fit."""
    return _attitude(track, t_s, key, owners, compiled).Ct


_MAP_CACHE: PerThread[dict[tuple, tuple[Any, F64]]] = PerThread(dict)


def _map_field(term: Term, p_m: F64, lever_enu: F64 | None) -> F64:
    """``g_j(x)`` (N, 3, K) of a ``field_map`` at the sensor, ``x = p + Q.T C l``.

    Without a lever arm it depends on the positions and the basis only: cached over a fit
    (keyed by the positions' id, with a reference to them so the id cannot be reused).
    """
    if lever_enu is not None:
        return term.basis().field(map_points(p_m, term.yaw_rad, lever_enu))
    key = (id(p_m), len(p_m), term.domain_m, term.n_axis, term.yaw_rad)
    cache = _MAP_CACHE.value
    hit = cache.get(key)
    if hit is not None and hit[0] is p_m:
        return hit[1]
    out = term.basis().field(p_m)
    if len(cache) > 8:
        cache.clear()
    cache[key] = (p_m, out)
    return out


@dataclass(frozen=True)
class _Forward:
    """The prediction at a state with what its Jacobian reuses (:func:`_forward`).

    ``att``: the attitude at the sensing times; ``Cp``, ``Cm``: ``C.T`` a difference step
    ``h`` later and earlier; ``lever_enu``: ``C l`` or None; ``Bt``, ``h_rad``,
    ``Bt_unturned``, ``kept``: as :func:`_enu_field` returns them; ``TT``: the tilt;
    ``Bp``: the field it turns; ``rd``: (M2)-(M5); ``E``: the eddy matrix in use; ``Gp``,
    ``G``: d y / d B_enu before and after the tilt; ``sqrt_w``: the roots of the
    likelihood's weights.
    """

    att: _Attitude
    Cp: F64
    Cm: F64
    h: float
    lever_enu: F64 | None
    Bt: F64
    h_rad: F64 | None
    Bt_unturned: F64 | None
    kept: dict[int, Any]
    TT: F64
    Bp: F64
    rd: Reading
    E: F64
    Gp: F64
    G: F64
    sqrt_w: F64 | None


#: The last :func:`_forward` with the state and data it was computed for: a fit evaluates
#: a candidate without the Jacobian, then, once the step is accepted, the same state
#: object with it. Kept by reference, so an identity match is the same objects.
_FORWARD_CACHE: PerThread[list[tuple[ModelState, FitData, _Forward]]] = PerThread(list)


def _forward(state: ModelState, data: FitData) -> _Forward:
    """Return the prediction at ``state`` and its shared pieces, reused for the same objects."""
    last = _FORWARD_CACHE.value
    if last:
        st, dt, fw = last[0]
        if st is state and dt is data:
            return fw
    t = data.t_s
    n = t.shape[0]
    tau = state.tau_s()
    # 3 samples: the rate regressor then shares no attitude sample with the reading's own
    # interpolation, so it cannot fit attitude noise
    h = max(3.0 * data.track.step_s, 1e-3)
    s = t - tau  # sensing time (CONVENTIONS: tau > 0 means stamps are late)
    compiled = data.compiled
    base = (id(data.track), id(t), n, tau, h, compiled)
    own = (data.track, t)
    att = _attitude(data.track, s, base + (0,), own, compiled)
    Ct = att.Ct
    Cp = _CT(data.track, s + h, base + (1,), own, compiled)
    Cm = _CT(data.track, s - h, base + (-1,), own, compiled)
    Cdot = (Cp - Cm) / (2.0 * h)  # d/dt C.T, central difference of the interpolated track

    # --- ENU field at each sample: B + drift + disturbances
    # lever_arm: the sensor sits at p + C l (CONVENTIONS), so every spatial term sees the
    # position moved by C(t) l, ENU (the lever arm's own tau-dependence is left out of
    # the time offset's Jacobian: second order, |omega x l| tau)
    lever = state.value(EffectKind.LEVER_ARM)
    lever_enu = None if lever is None or data.p_m is None else np.einsum("nji,j->ni", Ct, lever)
    Bt, h_rad, Bt_unturned, kept = _enu_field(state, data, lever_enu)
    TT = state.T_enu.T
    Bp = Bt @ TT.T  # T.T @ B_t per row (axis_tilt)

    # (M2)-(M5): THE prediction (pipeline.model.forward.reading), sensor terms in term order
    R = state.R_body_mag
    D = state.D()
    offsets: list[F64] = []
    E_term: F64 | None = None
    gauged = state.gauged()
    for term, v in zip(state.terms, state.values, strict=True):
        eff = EFFECTS[term.kind]
        if (off := eff.offset_nT(term, v, t)) is not None:
            offsets.append(off)
        if (e := eff.eddy_matrix(term, v, term.kind in gauged)) is not None:
            E_term = e
    rd = reading(Ct, Bp, R, D, offsets, E_term, Cdot)
    E = np.zeros((3, 3)) if E_term is None else E_term
    Gp = field_jacobian(Ct, R, D, E, Cdot)  # (J2), before the tilt
    G = right_times(Gp, TT)
    # the positions of the interpolation at t - tau, as sample_weights(data, tau) finds them
    w = _weights_at(data, att.at.position) if data.noise_model is not None else None
    sqrt_w = None if w is None else np.sqrt(w)
    fw = _Forward(att=att, Cp=Cp, Cm=Cm, h=h, lever_enu=lever_enu, Bt=Bt, h_rad=h_rad,
                  Bt_unturned=Bt_unturned, kept=kept, TT=TT, Bp=Bp, rd=rd, E=E, Gp=Gp, G=G,
                  sqrt_w=sqrt_w)
    last[:] = [(state, data, fw)]
    return fw


def evaluate(state: ModelState, data: FitData, jacobian: bool = True) -> Evaluation:
    """Predicted magnetometer reading and its Jacobian (vectorised over samples).

    Parameters
    ----------
    state : ModelState
        Parameter values and terms.
    data : FitData
        Stamps, readings and attitude track.
    jacobian : bool
        Also return the Jacobian with respect to the perturbation vector.

    Returns
    -------
    Evaluation

    """
    if jacobian and state.has_partial:
        return _partial_evaluation(state, data)
    fw = _forward(state, data)
    rd, G = fw.rd, fw.G
    y, b, m = rd.y_nT, rd.b_body_nT, rd.m_nT
    bdot, mdot, ydot0 = rd.bdot_nT_s, rd.mdot_nT_s, rd.ydot0_nT_s
    if not jacobian:
        return Evaluation(y, None, ydot0, G, fw.sqrt_w)

    n = data.t_s.shape[0]
    h, Ct, E = fw.h, fw.att.Ct, fw.E
    Cddot = (fw.Cp - 2.0 * Ct + fw.Cm) / (h * h)
    DRt = state.D() @ state.R_body_mag.T
    J = np.zeros((n, 3, state.n_params()))
    # R: left perturbation, R.T <- R.T exp(-[d]x): dm/dd = R.T [b]x, with the eddy term's
    # E D R.T [bdot]x; [v]x = sum_k v_k [e_k]x, so both are one product of the rows (b, bdot)
    # with the six constant matrices D R.T [e_k]x and E D R.T [e_k]x
    units = [skew(e) for e in np.eye(3)]
    per_unit = np.stack([DRt @ u for u in units] + [E @ DRt @ u for u in units])
    J[:, :, 0:3] = (np.concatenate([b, bdot], axis=1) @ per_unit.reshape(6, 9)).reshape(n, 3, 3)
    if data.B_known_enu_nT is None:
        J[:, :, 3:6] = G
        if fw.h_rad is not None:  # dB_t/dB = Rz(h)
            Rz = np.zeros((n, 3, 3))
            Rz[:, 0, 0] = Rz[:, 1, 1] = np.cos(fw.h_rad)
            Rz[:, 1, 0] = np.sin(fw.h_rad)
            Rz[:, 0, 1] = -np.sin(fw.h_rad)
            Rz[:, 2, 2] = 1.0
            J[:, :, 3:6] = np.matmul(G, Rz)
    bddot = rows_times(Cddot, fw.Bp)
    _term_columns(J, state, _Linearisation(
        data=data, lever_enu=fw.lever_enu, Ct=Ct, omega_body=fw.att.at.omega_body_rad_s, G=G,
        Gp=fw.Gp, TT=fw.TT, b=b, bddot=bddot, m=m, mdot=mdot, ydot0=ydot0, E=E,
        R=state.R_body_mag, D=state.D(), Bt=fw.Bt, h_rad=fw.h_rad, Bt_unturned=fw.Bt_unturned,
        gauged=state.gauged(), terms=tuple(zip(state.terms, state.values, strict=True)),
        kept=fw.kept))
    return Evaluation(y, J, ydot0, G, fw.sqrt_w)


@dataclass(frozen=True)
class _Samples:
    """The samples as a term's field sees them (:class:`pipeline.model.effects.base.Samples`)."""

    data: FitData
    lever_enu: F64 | None

    @property
    def t_s(self) -> F64:
        """Stamps, s."""
        return self.data.t_s

    @property
    def p_m(self) -> F64 | None:
        """Positions, m, or None."""
        return self.data.p_m

    @property
    def dp_m(self) -> F64:
        """Positions minus their reference, m (zeros without positions)."""
        return self.data.dp_m

    @property
    def span_s(self) -> float:
        """The drifts' time span (:func:`drift_span`)."""
        return drift_span(self.data)

    def map_field(self, term: Any) -> F64:
        """Return a ``field_map``'s basis fields at the sensor (:func:`_map_field`, cached)."""
        assert self.data.p_m is not None  # a map is evaluated only with positions
        return _map_field(term, self.data.p_m, self.lever_enu)


@dataclass(frozen=True)
class _Linearisation(_Samples):
    """What the prediction computed at a state, for the Jacobian columns of its terms.

    :class:`pipeline.model.effects.base.Linearisation`: ``Ct``: attitudes (N, 3, 3) at the
    sensing times; ``omega_body``: the interpolated rate there; ``G``, ``Gp``: d y / d B_enu
    after and before the tilt ``TT``; ``R``, ``D``: the rotation and ``I + S``; ``b``,
    ``bddot``: the field in the body frame and its second derivative; ``m``, ``mdot``: the
    reading before the eddy term and its rate; ``ydot0``: the eddy regressor; ``E``: the eddy
    matrix in use; ``Bt``, ``Bt_unturned``, ``h_rad``: the ENU field with and without the
    heading drift's turn, and the turn; ``gauged``: the kinds held off a shared direction;
    ``terms``: every term with its value; ``kept``: what each term's field kept for its
    columns, by term index (:func:`_enu_field`).
    """

    Ct: F64
    omega_body: F64
    G: F64
    Gp: F64
    TT: F64
    b: F64
    bddot: F64
    m: F64
    mdot: F64
    ydot0: F64
    E: F64
    R: F64
    D: F64
    Bt: F64
    h_rad: F64 | None
    Bt_unturned: F64 | None
    gauged: frozenset[EffectKind]
    terms: tuple[tuple[Any, F64], ...]
    kept: dict[int, Any]


def _partial_evaluation(state: ModelState, data: FitData) -> Evaluation:
    """Evaluate a state with partial terms.

    The full Jacobian of the same values, then each partial term's block turned to its
    fitted combinations (``J_full A``) and to the held ones (``J_full U``).
    """
    full = evaluate(state.unrestricted(), data, jacobian=True)
    Jf = full.jac
    blocks, held = [Jf[:, :, :6]], []
    i = 6
    for term in state.terms:
        width = term.full_size()
        blk = Jf[:, :, i : i + width]
        if term.partial:
            blocks.append(right_times(blk, term.determined_matrix()))
            held.append(right_times(blk, term.undetermined()))
        else:
            blocks.append(blk)
        i += width
    return replace(full, J=np.concatenate(blocks, axis=2),
                   J_held=np.concatenate(held, axis=2))


def _enu_field(state: ModelState, data: FitData, lever_enu: F64 | None
               ) -> tuple[F64, F64 | None, F64 | None, dict[int, Any]]:
    """Return the ENU field at each sample, the heading drift's turn and the field unturned.

    ``B`` plus each term's field (:meth:`Effect.add_field`, in the model's order), then
    turned about Up by a term that turns it (``heading_drift``, (M1h)); (None, None) without
    one. Last, what each term's columns reuse, by term index (a source's offsets and dipole
    matrices).
    """
    at = _Samples(data, lever_enu)
    Bt = np.broadcast_to(state.B_enu_nT, (len(data.t_s), 3)).copy()
    kept: dict[int, Any] = {}
    for k, (term, v) in enumerate(zip(state.terms, state.values, strict=True)):
        kept[k] = EFFECTS[term.kind].add_field(term, v, at, Bt)
    h_rad, Bt_unturned = None, None
    for term, v in zip(state.terms, state.values, strict=True):
        turned = EFFECTS[term.kind].turned_enu(term, v, at, Bt)
        if turned is not None:
            Bt_unturned = Bt
            Bt, h_rad = turned
    return Bt, h_rad, Bt_unturned, kept


def row_spans(state: ModelState, t_s: F64) -> tuple[tuple[int, int, int, int], ...]:
    """Return the Jacobian's windowed columns at ``state``: ``(i, j, a, b)`` per window of a term.

    Columns ``[i, j)`` vanish outside samples ``[a, b)`` (the effects'
    :meth:`~pipeline.model.effects.base.Effect.column_windows`, found in the stamps
    ``t_s``, which must be in order). None for a model with terms held in part, whose
    columns are combinations (:func:`_partial_evaluation`), nor for stamps out of order.
    """
    if state.has_partial or not ascending(t_s):
        return ()
    out = []
    for term, i in zip(state.terms, state.offsets(), strict=True):
        for c0, c1, t0, t1 in EFFECTS[term.kind].column_windows(term):
            a, b = np.searchsorted(t_s, [t0, t1])
            out.append((i + c0, i + c1, int(a), int(b)))
    return tuple(out)


def _term_columns(J: F64, state: ModelState, lin: _Linearisation) -> None:
    """Write each term's Jacobian columns into ``J`` (N, 3, P) in place (its effect's)."""
    for j, (term, i, v) in enumerate(zip(state.terms, state.offsets(), state.values,
                                         strict=True)):
        EFFECTS[term.kind].columns(term, v, lin, lin.kept[j], J[:, :, i : i + term.n_params()])


def drift_span(data: FitData) -> float:
    """Time span used to scale the drift basis (fixed per recording, not per subset)."""
    return float(data.track.t_s[-1]) if data.track.t_s[-1] > 0 else 1.0


def heading_drift_params(value: F64, data: FitData) -> dict[str, Any]:
    """CONVENTIONS params of ``heading_drift`` over ``data``'s span (the module's formula)."""
    return heading_params_over(value, drift_span(data))


def heading_signature_fraction(v_enu_nT: F64, B_enu_nT: F64) -> float:
    """Fraction of an ENU field change that a heading drift can produce (0..1).

    A heading error ``h`` turns the field about Up: ``dB = h (-B_N, B_E, 0)``. East and North
    change in the ratio ``-B_N : B_E``; Up and ``|B|`` do not change. The fraction is the
    energy of ``v_enu_nT`` (N, 3) along that direction over its total energy.
    """
    d = np.array([-B_enu_nT[1], B_enu_nT[0], 0.0])
    nd = float(np.linalg.norm(d))
    tot = float(np.sum(np.asarray(v_enu_nT) ** 2))
    if nd <= 0 or tot <= 0:
        return 0.0
    return float(np.sum((np.asarray(v_enu_nT) @ (d / nd)) ** 2) / tot)


def source_params(term: Term, value: F64, data: FitData,
                  lever_body_m: F64 | None = None, tau_s: float = 0.0) -> dict[str, Any]:
    """CONVENTIONS params of ``local_source``: where, how strong, when, and the closest pass.

    ``closest_approach_m`` / ``_s``: the smallest distance from the source to the sensor
    (the tracked point moved by the lever arm ``lever_body_m`` when there is one) while the
    source was there, and when (s from the first magnetometer sample).
    """
    windows = ([[float(a), float(b)] for a, b in term.windows_s] if term.windows_s
               else [[0.0, drift_span(data)]])
    out: dict[str, Any] = {
        "position_m": np.asarray(value[0:3], dtype=float).tolist(),
        "position_frame": data.position_frame or "enu",
        "position_origin": data.position_origin,
        "moment_Am2": np.asarray(value[3:6], dtype=float).tolist(),
        "windows_s": windows,
        "closest_approach_m": None,
        "closest_approach_s": None,
    }
    if data.p_m is not None and len(data):
        here = term.presence(data.t_s) > 0
        if here.any():
            lever = None
            if lever_body_m is not None:
                C = quat_to_matrix(data.track.at(data.t_s[here] - tau_s))
                lever = C @ np.asarray(lever_body_m, dtype=float)
            d = np.linalg.norm(source_offset_enu(term, value, data.p_m[here], lever), axis=1)
            j = int(np.argmin(d))
            out["closest_approach_m"] = float(d[j])
            out["closest_approach_s"] = float(data.t_s[here][j])
    return out


def map_field_at_data(term: Term, value: F64, state: ModelState, data: FitData) -> F64:
    """Return the ``field_map``'s ENU field at the sensor for every sample, (N, 3), nT.

    Each gradient row (N, 3, K) with ``value``: ``Q sum_j w_j g_j(x)`` at ``x = p + Q.T C l``
    (the lever arm ``l`` when the model has one, turned by the attitude at ``t - tau``).
    """
    if data.p_m is None or not len(data):
        return np.zeros((len(data), 3))
    return weighted_field(_map_columns(term, state, data), value)


def _map_columns(term: Term, state: ModelState, data: FitData) -> F64:
    """``Q g_j(x)`` (N, 3, K): the ENU field of each basis function at the sensor."""
    lever = state.value(EffectKind.LEVER_ARM)
    lever_enu = None
    if lever is not None:
        C = quat_to_matrix(data.track.at(data.t_s - state.tau_s()))
        lever_enu = C @ np.asarray(lever, dtype=float)
    g = term.basis().field(map_points(np.asarray(data.p_m), term.yaw_rad, lever_enu))
    return np.einsum("ij,njk->nik", rot_z(term.yaw_rad), g)


def map_params(term: Term, value: F64, state: ModelState, data: FitData) -> dict[str, Any]:
    """CONVENTIONS params of ``field_map``.

    ``peak_to_peak_nT``: max - min of each ENU component of the map's field over the
    positions the sensor visited (the samples of the fit).
    """
    f = map_field_at_data(term, value, state, data)
    p2p = (f.max(axis=0) - f.min(axis=0)) if len(f) else np.zeros(3)
    return {
        "basis": BASIS_NAME,
        "n_basis": int(term.n_params()),
        "length_scale_m": float(term.length_scale_m),
        "domain_m": [[float(a), float(b)] for a, b in term.domain_m],
        "weights": np.asarray(value, dtype=float).tolist(),
        "position_frame": data.position_frame or "enu",
        "position_origin": data.position_origin,
        "peak_to_peak_nT": [float(x) for x in p2p],
    }


@dataclass(frozen=True)
class FitContext:
    """The fit a term's outputs are read from: the diagnosis' side of ``FitView``.

    The effect modules (:mod:`pipeline.model.effects`) write each term's CONVENTIONS
    ``params`` and sigmas; the pieces only the diagnosis evaluates (a dipole's closest
    approach, a map's range over the samples) they ask of this view.
    """

    state: ModelState
    data: FitData

    @property
    def span_s(self) -> float:
        """Time span of the drift polynomials, s (:func:`drift_span`)."""
        return drift_span(self.data)

    @property
    def p_ref_m(self) -> F64 | None:
        """The positions' reference point, m."""
        return self.data.p_ref_m

    @property
    def position_frame(self) -> str | None:
        """The frame the positions are given in."""
        return self.data.position_frame

    @property
    def D(self) -> F64:
        """The fitted soft-iron matrix."""
        return self.state.D()

    @property
    def T_enu(self) -> F64:
        """The fitted turntable-axis tilt."""
        return self.state.T_enu

    def source_params(self, term: Term, value: F64) -> dict[str, Any]:
        """Return a ``local_source``'s params (:func:`source_params`)."""
        return source_params(term, value, self.data, self.state.value(EffectKind.LEVER_ARM),
                             self.state.tau_s())

    def map_params(self, term: Term, value: F64) -> dict[str, Any]:
        """Return a ``field_map``'s params (:func:`map_params`)."""
        return map_params(term, value, self.state, self.data)

    def map_range_sigma(self, term: Term, cov: F64) -> list[float]:
        """Return the first-order sigma of a ``field_map``'s range per ENU component.

        The range of each component is ``f(x_max) - f(x_min)`` at the samples where the
        fitted map is largest and smallest: the weights' covariance on the difference of
        the two samples' basis rows.
        """
        if self.data.p_m is None or not len(self.data):
            return [0.0, 0.0, 0.0]
        A = _map_columns(term, self.state, self.data)  # (N, 3, K)
        v = self.state.values[list(self.state.terms).index(term)]
        f = weighted_field(A, v)
        p2p = []
        for d in range(3):
            a = A[int(np.argmax(f[:, d])), d] - A[int(np.argmin(f[:, d])), d]
            p2p.append(float(np.sqrt(max(float(a @ cov @ a), 0.0))))
        return p2p


def term_params(term: Term, value: F64, state: ModelState, data: FitData) -> dict[str, Any]:
    """CONVENTIONS ``params`` of a fitted term (arrays as lists): its effect module's."""
    return EFFECTS[term.kind].params(term, value, FitContext(state, data))


def held_covariance(term: Term, cov: F64) -> F64:
    """Covariance (k, k) of every parameter of a term from its fitted block ``cov`` (m, m).

    A partial term: ``A cov A' + s^2 U U'``, its held combinations ``U`` as uncertain as
    their prior (:data:`IRON_PRIOR`, ``s`` per combination): the data say nothing about
    them, so the sigma is what is known of such a term before the recording. A full term:
    ``cov`` itself.
    """
    if not term.partial:
        return cov
    A, U = term.determined_matrix(), term.undetermined()
    s = IRON_PRIOR[term.kind.value]
    return A @ cov @ A.T + s * s * (U @ U.T)


def held_directions(term: Term) -> list[Any]:
    """Return what a partial term holds, in its CONVENTIONS params' terms, unit length.

    ``hard_iron``: mag-frame unit vectors (3,) of the held offset components; ``soft_iron``:
    symmetric traceless 3x3 matrices (unit Frobenius norm) along which ``D`` is held;
    otherwise the held combinations of the term's parameters. Lists, JSON-ready.
    """
    U = term.undetermined()
    if term.kind is EffectKind.SOFT_IRON:
        out = []
        for u in U.T:
            M = np.tensordot(u, SOFT_BASIS, axes=1)
            out.append((M / np.linalg.norm(M)).tolist())
        return out
    return [u.tolist() for u in U.T]


def term_sigma(term: Term, cov: F64, state: ModelState, data: FitData) -> dict[str, Any]:
    """1-sigma of the CONVENTIONS params from the term's block of the covariance.

    ``cov``: (m, m) over the fitted parameters; a partial term's held combinations get
    their prior's sigma (:func:`held_covariance`); the effect module turns the parameters'
    covariance into its params' sigmas.
    """
    return EFFECTS[term.kind].sigma(term, held_covariance(term, cov), FitContext(state, data))


def without_term(state: ModelState, i: int) -> ModelState:
    """``state`` without its ``i``-th term."""
    return state.with_terms(state.terms[:i] + state.terms[i + 1:],
                            state.values[:i] + state.values[i + 1:])


def moved_last_to(state: ModelState, i: int) -> ModelState:
    """``state`` with its last term moved to position ``i`` (values with it)."""
    order = list(range(len(state.terms) - 1))
    order.insert(i, len(state.terms) - 1)
    return dataclasses.replace(state, terms=tuple(state.terms[k] for k in order),
                               values=tuple(state.values[k] for k in order))

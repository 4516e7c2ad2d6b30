"""What every effect module provides, and the registry that collects them.

An effect is one physical cause ``diagnose`` can add to the forward model (CONVENTIONS,
"Effects"). Each lives in its own module of this package as one subclass of :class:`Effect`,
registered under its :class:`~pipeline.core.vocabulary.EffectKind` by :func:`register`; the
code that used to switch on the kind (the parameter count, the catalogue's words) asks the
registry instead, so that adding an effect is one module plus one line in
:mod:`pipeline.model.effects`.
"""

from __future__ import annotations

from typing import Any, ClassVar, Protocol

import numpy as np
from numpy.typing import NDArray

from pipeline.core.vocabulary import EffectKind
from pipeline.model.field_map import FieldMapBasis

F64 = NDArray[np.float64]

#: A term (or the rotation) keeping less than this fraction of the information of its weakest
#: parameter combination once the other parameters are free is confounded by the motion: its
#: sigma is over 10 times what it would be alone, and a model error of a tenth of the noise
#: moves it by a sigma. Not estimated, by calibrate (``stages.estimators.checks``) and by
#: diagnose alike.
CONFOUND_RATIO = 1e-2

#: Below this much turning in all (deg), every term that acts like a field looks like the
#: background field itself.
MIN_TURN_DEG = 20.0

#: A rotation whose second-largest angular-velocity moment is below this fraction of the
#: largest is about a single axis (:attr:`Motion.axis_spread`).
SINGLE_AXIS_SPREAD = 0.02


def standard_deviations(cov: F64) -> F64:
    """Return the 1-sigma of each parameter from its covariance.

    A rounding's negative variance reads as zero.
    """
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))


class TermShape(Protocol):
    """The shape of a model term that its parameter count depends on.

    ``stages.diagnose.model.Term`` satisfies it; the protocol keeps this layer from naming
    the diagnosis (``pipeline`` never imports ``stages``).
    """

    # read-only: the terms are frozen dataclasses
    @property
    def windows_s(self) -> tuple[tuple[float, float], ...]:
        """Half-open windows of a local effect, s from the first sample."""
        ...

    @property
    def yaw_rad(self) -> float:
        """Bearing of a ``field_gradient``'s position frame about Up."""
        ...

    @property
    def fit_yaw(self) -> bool:
        """Whether a ``local_source`` fits the bearing of the position frame."""
        ...

    @property
    def n_axis(self) -> tuple[int, ...]:
        """A ``field_map``'s modes per axis."""
        ...

    def knots(self) -> list[F64]:
        """Return the knot times of each window of a ``disturbance``."""
        ...

    def step_profile(self, t_s: F64) -> tuple[F64, F64]:
        """Return a ``hard_iron_step``'s plateau profile (N,) and transition basis (N, M)."""
        ...

    def presence(self, t_s: F64) -> F64:
        """Return 1 where the term acts (inside its windows, or everywhere without), (N,)."""
        ...

    def basis(self) -> FieldMapBasis:
        """Return a ``field_map``'s basis."""
        ...


class Samples(Protocol):
    """What a term's field needs of the samples at one state of the fit.

    ``stages.diagnose.model`` implements it (and :class:`Linearisation`); this layer does not
    name the diagnosis.
    """

    @property
    def t_s(self) -> F64:
        """Stamps, s from the first sample (N,)."""
        ...

    @property
    def p_m(self) -> F64 | None:
        """Positions (N, 3), m, in the position frame; None without positions."""
        ...

    @property
    def dp_m(self) -> F64:
        """Positions minus their reference point (N, 3), m; zeros without positions."""
        ...

    @property
    def span_s(self) -> float:
        """Time from the first to the last sample of the recording, s (the drifts' domain)."""
        ...

    @property
    def lever_enu(self) -> F64 | None:
        """The lever arm ``C l`` in ENU (N, 3), m, when the model has one."""
        ...

    def map_field(self, term: TermShape) -> F64:
        """Return a ``field_map``'s basis fields ``g_j(x)`` at the sensor (N, 3, K)."""
        ...


class Motion(Protocol):
    """What decides whether a recording's motion determines a term.

    ``stages.diagnose.catalogue`` implements it from the motion statistics and the data.
    """

    @property
    def total_turn_deg(self) -> float:
        """The rotation angle integrated over the recording, deg."""
        ...

    @property
    def axis_spread(self) -> float:
        """Second largest / largest eigenvalue of the angular velocity's second moment."""
        ...

    @property
    def rate_cv(self) -> float:
        """Coefficient of variation of the rotation rate (0: a constant rate)."""
        ...

    @property
    def has_positions(self) -> bool:
        """The recording carries the sensor's positions."""
        ...

    @property
    def field_known(self) -> bool:
        """A reference field is given (``B_enu`` is not estimated)."""
        ...

    def position_confounding(self) -> tuple[float, float]:
        """Return the positions' RMS spread, m, and the part of it not a function of time."""
        ...


class Linearisation(Samples, Protocol):
    """What the prediction computed at a state, for the Jacobian columns of its terms.

    Names as in (M1)-(M5) and (J1)-(J5) of :mod:`pipeline.model.forward`.
    """

    @property
    def Ct(self) -> F64:
        """``C_enu_body.T`` at the sensing times (N, 3, 3)."""
        ...

    @property
    def omega_body(self) -> F64:
        """The interpolated angular rate at the sensing times, body frame (N, 3), rad/s."""
        ...

    @property
    def G(self) -> F64:
        """``d y / d B_enu`` after the axis tilt (N, 3, 3)."""
        ...

    @property
    def Gp(self) -> F64:
        """``d y / d B_enu`` before the axis tilt (N, 3, 3)."""
        ...

    @property
    def TT(self) -> F64:
        """The tilt ``T.T`` (3, 3)."""
        ...

    @property
    def R(self) -> F64:
        """``R_body_mag`` (3, 3)."""
        ...

    @property
    def D(self) -> F64:
        """``I + S`` (3, 3)."""
        ...

    @property
    def E(self) -> F64:
        """The eddy matrix in use (3, 3)."""
        ...

    @property
    def b(self) -> F64:
        """The field in the body frame (N, 3), nT."""
        ...

    @property
    def bddot(self) -> F64:
        """Its second time derivative (N, 3), nT/s^2."""
        ...

    @property
    def m(self) -> F64:
        """The reading before the eddy term (N, 3), nT."""
        ...

    @property
    def mdot(self) -> F64:
        """Its rate (N, 3), nT/s."""
        ...

    @property
    def ydot0(self) -> F64:
        """The eddy regressor ``dy0/dt`` (N, 3), nT/s."""
        ...

    @property
    def Bt(self) -> F64:
        """The ENU field at the sensor, after the heading drift's turn (N, 3), nT."""
        ...

    @property
    def Bt_unturned(self) -> F64 | None:
        """The same before the turn; None without a heading drift."""
        ...

    @property
    def h_rad(self) -> F64 | None:
        """The heading drift's turn (N,), rad; None without one."""
        ...

    @property
    def gauged(self) -> frozenset[EffectKind]:
        """The effects held off the direction they share with another in the model.

        (:attr:`Effect.shares_with`.)
        """
        ...

    @property
    def terms(self) -> tuple[tuple[Any, F64], ...]:
        """Every term of the model with its value, in the model's order."""
        ...


class FitView(Protocol):
    """What a term's outputs need of the fit it came from (the diagnosis' state and data).

    ``stages.diagnose.model.FitContext`` implements it. The dipole and the map are evaluated
    by the diagnosis, which the effect modules do not import: their ``params`` and
    ``sigma`` ask the view for those pieces.
    """

    @property
    def span_s(self) -> float:
        """Time from the first to the last sample, s (the drift polynomials' domain)."""
        ...

    @property
    def p_ref_m(self) -> F64 | None:
        """The positions' reference point, m, or None without positions."""
        ...

    @property
    def position_frame(self) -> str | None:
        """The frame the positions are given in."""
        ...

    @property
    def D(self) -> F64:
        """The fitted soft-iron matrix ``I + S`` (3, 3)."""
        ...

    @property
    def T_enu(self) -> F64:
        """The fitted turntable-axis tilt (3, 3)."""
        ...

    def source_params(self, term: Any, value: F64) -> dict[str, Any]:
        """Return a ``local_source``'s CONVENTIONS params (position, moment, approach)."""
        ...

    def map_params(self, term: Any, value: F64) -> dict[str, Any]:
        """Return a ``field_map``'s CONVENTIONS params (weights, basis, range)."""
        ...

    def map_range_sigma(self, term: Any, cov: F64) -> list[float]:
        """Return the first-order sigma of a ``field_map``'s range per ENU component."""
        ...


class RestorePart:
    """One fitted term in the restore's forward model, built from its CONVENTIONS params.

    :class:`pipeline.model.forward.ForwardModel` holds one per term that is a field in ENU
    ((M1): :meth:`field_enu`), a turn of it ((M1h): :meth:`heading_rad`) or an offset
    that changes in time ((M5): :meth:`offset_nT`); the sensor's constants (``D``, ``o``,
    ``tau``, ``E_s``, the lever arm) are the model's own fields
    (:meth:`Effect.model_fields`). A part is a frozen value: it holds numbers only.
    """

    #: Its field depends on the sensor's position.
    needs_positions: ClassVar[bool] = False

    def field_enu(self, t_s: F64, p_m: F64 | None, lever_enu: F64 | None) -> F64 | None:
        """Return the term's ENU field at ``t_s`` (s from the first sample), (N, 3), nT.

        ``p_m``: positions (N, 3), m, every row finite, or None without positions (a term
        that :attr:`needs_positions` then has no field); ``lever_enu``: ``C l`` in ENU
        (N, 3), m, or None. The model masks the rows that had no position. None (the
        default): the term is not a field.
        """
        return None

    def heading_rad(self, t_s: F64) -> F64 | None:
        """Return ``h(t)`` of (M1h), rad, (N,); None (the default): the term turns nothing."""
        return None

    def offset_nT(self, t_s: F64) -> F64 | None:
        """Return the term's offset of the reading, mag frame, (N, 3); or None."""
        return None


class Effect:
    """One effect: its name, its words, its parameters and its part of the forward model.

    The forward model of the diagnosis (``stages.diagnose.model``, (M1)-(M5) of
    :mod:`pipeline.model.forward`) asks each term's effect for its part: a field in ENU
    (:meth:`add_field`), a turn of that field (:meth:`turned_enu`), an offset in the
    magnetometer frame (:meth:`offset_nT`), an eddy matrix (:meth:`eddy_matrix`), and the
    term's Jacobian columns (:meth:`columns`); a spatial term also gives the field's gradient
    at the sensor (:meth:`gradient_enu`), which the lever arm's columns sum.

    Attributes
    ----------
    kind : EffectKind
        The CONVENTIONS name, the registry's key.
    physics : str
        What on a survey platform causes it.
    signature : str
        How it shows in the residual.
    frame : str
        Frame in which its residual lives (``mag`` or ``enu``).
    identifiable_in_part : bool
        Some of its directions are confounded with the model's other parameters by nature,
        and the rest still carry the physics: the term is admitted on its best-determined
        direction and fitted there (the confounded directions stay at zero), instead of
        being refused on its weakest one.
    n_fixed : int or None
        The number of parameters when it does not depend on the term's windows or options;
        None when :meth:`n_params` counts them.
    held_prior : float or None
        The prior's standard deviation of each parameter (or combination of them) a
        recording's motion cannot determine, held at zero instead (sensor iron only: its
        "none" is a natural reference); None: the term is never held in part.
    needs_turning : bool
        The term is told from the background field only if the platform turns
        (:data:`MIN_TURN_DEG` in all); :meth:`undetermined` checks it first.
    confounded_with : str
        What the term looks like when the motion confounds it (:meth:`undetermined`'s words).
    event : bool
        The term is an event in time: present only inside its windows (a magnet brought
        near, a vehicle passing). The scan's windows propose it; the report gives one row
        per event, windows that touch being one.
    holds_frame : bool
        The term's rotation is held by the model's state (``T_enu``, turned on the left by
        :meth:`turn_frame` at each step; the term's values only keep account of the steps),
        and leaves with the term.
    shares_with : EffectKind or None
        An effect whose prediction this one reproduces to first order along some direction
        of its parameters (a gauge: an eddy term's isotropic part is a time offset). When
        both are in the model this one is held off that direction (:meth:`gauge_projector`)
        and the shared part belongs to the other (:meth:`fold_shared`), so that the two do
        not trade along it and the count of free parameters drops by its dimension.
    contains : EffectKind or None
        A simpler effect this one holds whole as a special case (an eddy term ``E_s = -tau I``
        is a time offset; a field drift along ``(-B_N, B_E, 0)`` is a heading drift): the
        diagnosis offers the simpler description of a fitted term, and this one only in
        place of the simpler, never beside it (except in parts, :attr:`shares_with`).
    in_window : EffectKind or None
        An effect that describes a term of this one over its window (a disturbance fixed in
        ENU is, where the platform holds its attitude, one offset in the sensor frame: a
        ``hard_iron_step``); the window's edges are searched where a held offset changes.
    min_window_s : float
        The shortest window a term of this effect holds, s (an object left near the sensor:
        0.5 s; a shorter excess is a bump).
    merges : bool
        Terms of this effect whose windows touch are candidates for one event: one term over
        both, the outer transitions kept (:meth:`merged_start`).
    trades_with : frozenset of EffectKind
        Effects a term of this one can trade with along a direction they share, the data
        paying for the new term by moving the other (a traceless eddy term beside a time
        offset where the sensor barely turns; a drift over the recording beside a transient
        in mid recording): the term must earn its margin with those held.
    acts_through : frozenset of EffectKind
        Effects this one acts only through (one must be in the model): a lever arm moves the
        sensor within a field that varies in space; a map is the field beyond the gradient's
        first order, in its bearing.
    each_round : bool
        A candidate in every round of the diagnosis' search (an effect of the whole
        recording); otherwise it is offered where the residual scan opens a window (an
        event, a source: ``stages/diagnose/candidates.py``), by a candidate of its own (a
        map), or it is not a fitted term (``sample_hold``).
    turntable_only : bool
        A property of a single-axis attitude source (a turntable's tilted axis): offered only
        when the attitude comes from one (``--turntable``) or the field is known.
    rate_signature : bool
        Its signature is read against the rate of change of the reading, ``dy/dt`` (a lag,
        an eddy term): the finding's signature plot carries that regressor.
    local_in_space : bool
        Its field is local in space (a compact object): present throughout, it acts where the
        sensor passes it, and its finding's windows are where its own field stands out.
    absorbing : bool
        A candidate of this effect can explain part of any other's excess (a map along a path
        fits a bump in time where the path crosses a smooth anomaly): its fit is tried after
        the others.

    """

    kind: ClassVar[EffectKind]
    physics: ClassVar[str]
    signature: ClassVar[str]
    frame: ClassVar[str]
    identifiable_in_part: ClassVar[bool] = False
    n_fixed: ClassVar[int | None] = None
    held_prior: ClassVar[float | None] = None
    needs_turning: ClassVar[bool] = True
    confounded_with: ClassVar[str] = "terms already in the model"
    event: ClassVar[bool] = False
    holds_frame: ClassVar[bool] = False
    shares_with: ClassVar[EffectKind | None] = None
    contains: ClassVar[EffectKind | None] = None
    in_window: ClassVar[EffectKind | None] = None
    min_window_s: ClassVar[float] = 0.0
    merges: ClassVar[bool] = False
    trades_with: ClassVar[frozenset[EffectKind]] = frozenset()
    acts_through: ClassVar[frozenset[EffectKind]] = frozenset()
    absorbing: ClassVar[bool] = False
    each_round: ClassVar[bool] = False
    turntable_only: ClassVar[bool] = False
    rate_signature: ClassVar[bool] = False
    local_in_space: ClassVar[bool] = False

    def n_params(self, term: TermShape) -> int:
        """Return the number of parameters of ``term``, a term of this effect.

        Parameters
        ----------
        term : TermShape
            The term (its windows, transitions, options).

        Returns
        -------
        int

        Raises
        ------
        ValueError
            The effect is not a term of the forward model (``sample_hold`` is handled on
            the data).

        """
        if self.n_fixed is None:
            raise ValueError(f"{self.kind.value} is not a term of the forward model")
        return self.n_fixed

    def explanation(
        self, params: dict[str, Any], duration_s: float, note: str | None = None
    ) -> str:
        """Return the words for one finding: the physics, the signature and :meth:`remark`.

        Parameters
        ----------
        params : dict
            The finding's CONVENTIONS params.
        duration_s : float
            Span of the recording, s.
        note : str, optional
            ``field_drift`` with positions in the recording: what the test of a spatial
            gradient found (replaces the remark that drift and gradient cannot be separated).

        Returns
        -------
        str

        """
        return f"{self.physics}; signature: {self.signature}" + self.remark(
            params, duration_s, note)

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return the report's sentence: what the finding is, with its size and units.

        ``params`` and ``sigma`` are the finding's CONVENTIONS values (``diagnosis.json``);
        the numbers are written through :mod:`pipeline.core.words`. An effect found only as
        events in time (one report row per event) keeps this plain name.
        """
        return f"{self.kind.value}."

    def remark(
        self, params: dict[str, Any], duration_s: float, note: str | None = None
    ) -> str:
        """Return what the fitted values suggest, ``". "``-led (empty: nothing to add)."""
        return ""

    def beside_kin(self, params: list[dict[str, Any]], short: bool = False) -> list[str]:
        """Return what each finding of this effect says about the others of its kind.

        ``params`` are the final findings' CONVENTIONS values, in the order found; the
        result holds one text per finding (empty: nothing to add): ``". "``-led for the
        explanation, or with ``short`` a sentence for the report's (:meth:`sentence`). Most
        effects have nothing to say; a ``local_source`` names the findings that are one
        object.
        """
        return [""] * len(params)

    def undetermined(self, motion: Motion, efficiency: float,
                     horizontal_fraction: float | None = None) -> str | None:
        """Return why this recording cannot determine the term, or None if it can.

        First the platform must turn (:attr:`needs_turning`), then the effect's own
        conditions (:meth:`motion_reason`), last the term must keep :data:`CONFOUND_RATIO`
        of its information beside the model's other parameters.

        Parameters
        ----------
        motion : Motion
            The recording's motion and what it carries.
        efficiency : float
            Smallest eigenvalue ratio of the term's efficient information (Schur complement
            against the parameters already in the model) to its own information: the
            fraction of the weakest parameter combination the other parameters cannot mimic.
        horizontal_fraction : float, optional
            ``|B_horizontal| / |B|`` of the current field.

        Returns
        -------
        str or None

        """
        if self.needs_turning and motion.total_turn_deg < MIN_TURN_DEG:
            return (
                f"the platform turned only {motion.total_turn_deg:.0f} deg in total: without "
                "turning, every term that acts like a field looks like the background field itself"
            )
        why = self.motion_reason(motion, horizontal_fraction)
        if why is not None:
            return why
        if efficiency < CONFOUND_RATIO:
            return (
                f"the motion leaves this term looking like {self.confounded_with}: it cannot be "
                "told apart from them in this recording"
            )
        return None

    def motion_reason(self, motion: Motion, horizontal_fraction: float | None) -> str | None:
        """Return what this effect in particular needs of the motion and lacks, or None."""
        return None

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS ``params`` of a fitted term (arrays as lists, JSON-ready).

        Parameters
        ----------
        term : Term
            The term (``stages.diagnose.model.Term``: windows, options).
        value : ndarray (k,)
            Its fitted parameters.
        fit : FitView
            The fit it belongs to.

        Returns
        -------
        dict
            Named as in CONVENTIONS ("Effects").

        """
        raise ValueError(f"{self.kind.value} is not a term of the forward model")

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return the 1-sigma of :meth:`params` from the term's covariance.

        Parameters
        ----------
        term : Term
            The term.
        cov : ndarray (k, k)
            Covariance of all its parameters (a partial term's held ones at their prior).
        fit : FitView
            The fit it belongs to.

        Returns
        -------
        dict
            The keys of :meth:`params` that have a sigma.

        """
        raise ValueError(f"{self.kind.value} is not a term of the forward model")


    def add_field(self, term: Any, value: F64, at: Samples, B_enu: F64) -> Any:
        """Add the term's field to the ENU field at the sensor ``B_enu`` (N, 3), nT, in place.

        Returns what :meth:`columns` of the same evaluation reuses (a source's offsets and
        dipole matrices), or None. The default adds nothing: the term is not a field in ENU.
        """
        return None

    def turned_enu(self, term: Any, value: F64, at: Samples, B_enu: F64
                   ) -> tuple[F64, F64] | None:
        """Return the ENU field turned by the term (N, 3) and the turn (N,), rad; or None."""
        return None

    def offset_nT(self, term: Any, value: F64, t_s: F64) -> F64 | None:
        """Return the term's offset of the reading, mag frame ((3,) or (N, 3)), or None."""
        return None

    def eddy_matrix(self, term: Any, value: F64, gauged: bool) -> F64 | None:
        """Return the term's ``E_s`` (3, 3) in (M5), or None.

        ``gauged``: the term is held off the direction it shares (:attr:`shares_with`).
        """
        return None

    def turn_frame(self, T_enu: F64, step: F64) -> F64:
        """Return the state's frame ``T_enu`` after a parameter ``step`` (:attr:`holds_frame`)."""
        return T_enu

    def gauge_projector(self) -> F64:
        """Return the projector (k, k) onto the directions kept beside :attr:`shares_with`."""
        raise NotImplementedError(f"{self.kind.value} shares no direction with another effect")

    def kept_basis(self) -> F64:
        """Return an orthonormal basis (m, k) of the directions kept beside :attr:`shares_with`."""
        raise NotImplementedError(f"{self.kind.value} shares no direction with another effect")

    def shared_basis(self) -> F64:
        """Return an orthonormal basis (k - m, k) of the directions it shares."""
        raise NotImplementedError(f"{self.kind.value} shares no direction with another effect")

    def fold_shared(self, own: F64, other: F64) -> tuple[F64, F64]:
        """Return ``own`` off the shared direction and ``other`` holding its part there.

        The same prediction to first order (see :attr:`shares_with`).
        """
        raise NotImplementedError(f"{self.kind.value} shares no direction with another effect")

    def gradient_enu(self, term: Any, value: F64, at: Samples) -> F64 | None:
        """Return ``dB/dr``, the gradient of the term's field at the sensor, ENU, or None.

        (N, 3, 3) or (1, 3, 3); None: the term's field does not depend on the position.
        """
        return None

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write the term's Jacobian columns ``d y / d value`` into ``out`` (N, 3, k).

        ``out`` is zero on entry; ``kept`` is what :meth:`add_field` returned.
        Every implementation is checked against central differences
        (``tests/test_effects.py``, ``tests/test_local_source.py``, ``tests/test_field_map.py``).
        """
        raise ValueError(f"{self.kind.value} is not a term of the forward model")


    def column_windows(self, term: Any) -> tuple[tuple[int, int, float, float], ...]:
        """Return the term's columns that vanish outside a time window: ``(i, j, t0, t1)``.

        Columns ``[i, j)`` of :meth:`columns` are zero at every sample outside ``[t0, t1)``
        (s from the first magnetometer sample, the samples' own stamps). The normal equations
        sum their products over those rows alone (``pipeline.model.solve.normal_equations``).
        Empty (the default): every column may act at any time. Checked against
        :meth:`columns` for every effect that declares windows (``tests/test_effects.py``).
        """
        return ()

    def merged_start(self, a: tuple[Any, F64], b: tuple[Any, F64], merged: Any) -> F64:
        """Return the start values of ``merged``, one term over the pieces ``a`` and ``b``.

        Each piece is ``(term, value)``; only effects that :attr:`merges` have it.
        """
        raise NotImplementedError(f"{self.kind.value} terms are not merged")

    def prior_precision(self, term: Any) -> F64 | None:
        """Return the ridge of the term's parameters (k,), per nT^2, or None (no prior).

        The fit adds ``sum_i prec_i x_i^2`` to the sum of squares: the negative log of a
        Gaussian prior times ``2 noise^2``. None (the default): every parameter is free.
        """
        return None

    def model_fields(self, params: dict[str, Any]) -> dict[str, Any]:
        """Return the restore's model fields a sensor term sets from its CONVENTIONS params.

        ``{"offset_nT": ...}`` for ``hard_iron``, ``{"D": ...}`` for ``soft_iron``, ...: the
        keyword arguments of :class:`~pipeline.model.forward.ForwardModel`. Empty (the
        default): the term is a :class:`RestorePart`, or not part of the restore.
        """
        return {}

    def restore_part(self, params: dict[str, Any]) -> RestorePart | None:
        """Return the term's :class:`RestorePart` from its CONVENTIONS params, or None.

        None: the term is not a part (a sensor constant, or not in the restore's model).
        """
        return None

    def restorable(self, params: dict[str, Any]) -> bool:
        """Return whether the params carry what the restore needs (the fitted curve).

        ``diagnose`` writes a drift's Legendre coefficients or a disturbance's knots beside
        the CONVENTIONS params; a calibration without them cannot restore the term, which
        the model then lists as unmodelled.
        """
        return True


#: kind -> its effect, filled by :func:`register` as the modules are imported
EFFECTS: dict[EffectKind, Effect] = {}


def register(cls: type[Effect]) -> type[Effect]:
    """Register one instance of ``cls`` under its kind (a class decorator).

    Raises
    ------
    ValueError
        Two modules claim the same kind.

    """
    if cls.kind in EFFECTS:
        raise ValueError(f"effect {cls.kind.value} registered twice")
    EFFECTS[cls.kind] = cls()
    return cls

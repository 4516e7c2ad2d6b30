"""Estimate stage: the misalignment ``R_body_mag`` and, on request, ``o``, ``D`` and ``tau``.

:func:`fit_calibration` is the library entry point; :class:`Estimate` wraps it as a stage
(requires ``recording`` and ``aligned``, provides ``calibration``). The estimators live in
:mod:`stages.estimators`, one module each, behind the ``Estimator`` protocol.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pipeline.core.errors import EstimationError, UsageError
from pipeline.core.recording import AlignedSeries, Recording
from pipeline.core.verdict import judge, sensor_noise_nT
from pipeline.core.vocabulary import EstimateTerm, EstimatorKind, RobustLoss
from pipeline.model.calibration import Calibration
from pipeline.model.forward import MAX_TIME_OFFSET_S
from pipeline.model.sample_hold import detect_sample_hold, repeated
from stages.context import Context
from stages.estimators.base import EstimationProblem, Estimator, NoiseModel
from stages.estimators.registry import ESTIMATORS

__all__ = [
    "Estimate",
    "Judge",
    "carry_checks",
    "with_verdict",
    "NoiseModel",
    "fit_calibration",
    "make_estimator",
]


#: the estimator used when none is named
DEFAULT_ESTIMATOR: EstimatorKind = EstimatorKind.ML


def make_estimator(kind: EstimatorKind | str) -> Estimator:
    """Return the estimator object for ``kind`` from the registry (default hyperparameters).

    Raises
    ------
    UsageError
        ``kind`` is not in :data:`stages.estimators.registry.ESTIMATORS`.

    """
    name = getattr(kind, "value", kind)
    if name not in ESTIMATORS:
        raise UsageError(f"unknown estimator {name!r}: choose one of {', '.join(ESTIMATORS)}")
    module, cls = ESTIMATORS[name].split(":")
    return getattr(importlib.import_module(module), cls)()


def _terms(terms: Iterable[EstimateTerm | str]) -> frozenset[EstimateTerm]:
    return frozenset(EstimateTerm(t) for t in terms)


def _robust(robust: bool | RobustLoss | str) -> RobustLoss:
    if isinstance(robust, bool):
        return RobustLoss.HUBER if robust else RobustLoss.NONE
    return RobustLoss(robust)


def fit_calibration(
    recording: Recording | None,
    aligned: AlignedSeries,
    *,
    estimator: EstimatorKind = DEFAULT_ESTIMATOR,
    terms: Iterable[EstimateTerm | str] = frozenset(),
    reference_field_enu_nT: Sequence[float] | np.ndarray | None = None,
    R_nominal_body_mag: np.ndarray | None = None,
    robust: bool | RobustLoss = False,
    windows_ns: Sequence[tuple[int, int]] | None = None,
    noise: NoiseModel | None = None,
    drop_repeats: bool = True,
) -> Calibration:
    """Estimate the calibration of one recording.

    Parameters
    ----------
    recording : Recording or None
        Its raw attitude series is used to re-interpolate at ``t - tau`` when the time offset
        is estimated; ``None`` uses the aligned samples themselves.
    aligned : AlignedSeries
        Magnetometer samples (nT, frame mag) with the attitude at ``t - aligned.time_offset_s``.
    estimator : EstimatorKind
        Which method (default maximum likelihood).
    terms : iterable of EstimateTerm
        Extra terms: ``OFFSET`` (``o``), ``SOFT_IRON`` (``D``), ``TIME_OFFSET`` (``tau``).
    reference_field_enu_nT : array_like (3,), optional
        Known background field (ENU, nT); fixes ``B`` and makes the rotation about a single
        rotation axis observable.
    R_nominal_body_mag : ndarray (3, 3), optional
        Nominal mounting; the result is also reported as the small rotation from it.
    robust : bool or RobustLoss
        ``True`` is Huber; IRLS on the whitened per-sample residuals.
    windows_ns : sequence of (start, end), optional
        Use only samples inside these half-open windows.
    noise : NoiseModel, optional
        Sensor figures for the weighting; ``None`` means unknown isotropic noise (the
        covariance is then scaled by the residual variance).
    drop_repeats : bool
        Leave out repeated sample-and-hold messages (:mod:`pipeline.model.sample_hold`) when the
        recording has them.

    Returns
    -------
    Calibration

    Raises
    ------
    EstimationError
        Too few samples, NaN data, or an estimator that cannot work on this motion
        (:class:`~pipeline.core.errors.NotObservableError`).

    """
    al = aligned
    if windows_ns:
        keep = np.zeros(len(al), bool)
        for a, b in windows_ns:
            keep |= (al.t_ns >= int(a)) & (al.t_ns < int(b))
        al = al.select(keep)
    ref = None
    if reference_field_enu_nT is not None:
        ref = np.asarray(reference_field_enu_nT, float).reshape(3)
        if not np.all(np.isfinite(ref)) or np.linalg.norm(ref) <= 0:
            raise EstimationError(f"reference field {ref.tolist()} is not a usable vector")
    R_nom = None if R_nominal_body_mag is None else np.asarray(R_nominal_body_mag, float)
    if R_nom is not None:
        R_nom = R_nom.reshape(3, 3)
        if not np.allclose(R_nom @ R_nom.T, np.eye(3), atol=1e-6) or np.linalg.det(R_nom) < 0:
            raise EstimationError("the nominal mounting R_nominal_body_mag is not a rotation")

    # Sample-and-hold (CONVENTIONS effect sample_hold): a repeated message carries no new
    # conversion and was sensed up to one native period before its stamp; left out.
    hold = detect_sample_hold(al.t_ns, al.mag_nT) if drop_repeats else None
    if hold is not None:
        al = al.select(hold.first)
    if EstimateTerm.TIME_OFFSET in _terms(terms) and recording is not None and (
            recording.attitude is not None and len(recording.attitude) >= 2):
        # tau is estimated within +-MAX_TIME_OFFSET_S (pipeline.model.forward): a sample
        # closer than that to either end of the attitude may be sensed outside it, where the
        # attitude would be a held end sample, not the attitude at t - tau

        margin = int(round(MAX_TIME_OFFSET_S * 1e9))
        ta = recording.attitude.t_ns
        inner = (al.t_ns >= int(ta.min()) + margin) & (al.t_ns <= int(ta.max()) - margin)
        if inner.sum() >= 0.5 * len(al):
            al = al.select(inner)
    problem = EstimationProblem(
        t_ns=al.t_ns,
        mag_nT=al.mag_nT,
        q_enu_body=al.q_enu_body,
        time_offset0_s=float(al.time_offset_s),
        attitude=None if recording is None else recording.attitude,
        terms=_terms(terms),
        reference_field_enu_nT=ref,
        R_nominal_body_mag=R_nom,
        robust=_robust(robust),
        noise=noise,
    )
    cal = make_estimator(estimator).fit(problem)
    if hold is not None:
        cal = cal.replace(
            sample_hold=hold.params(),
            warnings=cal.warnings + (
                f"sample-and-hold: {100 * hold.repeated_fraction:.0f} % of the magnetometer "
                f"messages repeat the previous one (native rate {hold.native_rate_hz:.1f} Hz, "
                f"messages {hold.message_rate_hz:.1f} Hz); the repeats were left out",),
        )
    return with_verdict(cal, al)


#: A rotation sigma above this (deg) about a body axis is a doubt: 1 deg of misalignment
#: costs about 870 nT on a 50,000 nT field, more than any sensor's noise.
POOR_AXIS_SIGMA_DEG = 1.0


def with_verdict(cal: Calibration, aligned: AlignedSeries,
                 residual_rms_nT: float | None = None, diagnosed: bool = False,
                 heldout_rms_nT: float | None = None) -> Calibration:
    """Return ``cal`` with its verdict (:mod:`pipeline.core.verdict`) from the aligned samples.

    The sensor noise is measured in the still windows of ``aligned`` (repeated
    sample-and-hold messages left out); the fit's checks (``cal.checks``) give the refusals
    and doubts, and a rotation known to worse than :data:`POOR_AXIS_SIGMA_DEG` about a body
    axis the motion does determine is one more. ``residual_rms_nT`` overrides the
    calibration's own (a later, fuller model); ``diagnosed``: the diagnosis ran (the
    verdict's advice points to its findings); ``heldout_rms_nT``: the final model's error
    on held-out samples, when the diagnosis measured it (the verdict judges and quotes it).
    """
    keep = ~repeated(aligned.mag_nT)
    noise = sensor_noise_nT(aligned.t_ns, aligned.mag_nT, aligned.q_enu_body, keep)
    res = cal.residual_rms_nT if residual_rms_nT is None else residual_rms_nT
    refusals = list(cal.checks.get("refusals", ()))
    if len(cal.unobservable_axes_body) >= 3:
        refusals.insert(0, "the platform did not rotate: nothing about the misalignment is "
                        "observable; record rotations about at least two different axes")
    # a doubt about the rotation's own precision, kept beside the checks' (the report lists
    # them all; judged again, the previous one is replaced)
    poor = "the rotation about body "
    doubts = [d for d in cal.checks.get("doubts", ()) if not d.startswith(poor)]
    sig = np.asarray(cal.sigma_rotvec_deg, float)
    if len(cal.unobservable_axes_body) == 0 and np.all(np.isfinite(sig)):
        i = int(np.argmax(sig))
        if sig[i] > POOR_AXIS_SIGMA_DEG:
            doubts.append(f"{poor}{'xyz'[i]} is only known to {sig[i]:.1f} deg: the motion "
                          "barely turned the sensor about that axis")
    return cal.replace(verdict=judge(res, noise, refusals=refusals, doubts=doubts,
                                     diagnosed=diagnosed, heldout_rms_nT=heldout_rms_nT),
                       checks={**cal.checks, "doubts": doubts})


#: check key that carries the estimate's unobservable axes through the diagnosis' model
CARRIED_AXES = "unobservable_axes_of_estimate"


def carry_checks(before: Calibration, after: Calibration, *, explained: bool = False,
                 ) -> Calibration:
    """Return ``after`` (a fuller model of the same recording) with ``before``'s checks.

    The estimate's global checks (starts, terms not estimated, sample-and-hold, effective
    samples, the rotation axes the motion cannot determine) still hold for the final model;
    its rotation sigmas are never smaller than the estimate's sandwich sigmas (correlated
    residuals do not go away with more terms). The
    split-half disagreement is carried (as sigma and doubt) only when the final model has not
    ``explained`` more than the estimate (a diagnosis with findings models the physics that
    made the halves disagree; its own sigmas then stand).
    """
    checks = dict(before.checks)
    floor = before.sigma_rotvec_deg
    if explained:
        if "sigma_rotvec_sandwich_deg" in checks:
            floor = np.asarray(checks["sigma_rotvec_sandwich_deg"], float)
        checks["doubts"] = [d for d in checks.get("doubts", ())
                            if not d.startswith("the two halves")]
    sig = np.asarray(after.sigma_rotvec_deg, float)
    if floor is not None:
        sig = np.fmax(sig, np.asarray(floor, float))
        sig = np.where(np.isinf(after.sigma_rotvec_deg), np.inf, sig)
    if before.unobservable_axes_body and not after.unobservable_axes_body:
        # an axis the motion cannot determine stays so under a fuller model (more terms
        # never determine the rotation better), though that model may not list it; it is
        # listed again once the final model is complete (Judge)
        checks[CARRIED_AXES] = [np.asarray(a, float).tolist()
                                for a in before.unobservable_axes_body]
    return after.replace(
        sigma_rotvec_deg=sig,
        checks={**checks, **after.checks},
        not_estimated=before.not_estimated,
        sample_hold=before.sample_hold if after.sample_hold is None else after.sample_hold,
        n_eff=before.n_eff if after.n_eff is None else after.n_eff,
        warnings=tuple(dict.fromkeys(before.warnings + after.warnings)),
    )


@dataclass(frozen=True)
class Judge:
    """Stage: the verdict on the final calibration (after diagnosis), from the aligned data."""

    requires: ClassVar[frozenset[str]] = frozenset({"aligned", "calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"calibration"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` with ``calibration.verdict`` for its final model.

        The rotation axes the estimate found unobservable, carried through a fuller model
        that does not list them (:func:`carry_checks`), are listed in the calibration again.
        """
        diag = ctx.diagnosis
        cal = ctx.need_calibration()
        if CARRIED_AXES in cal.checks:
            checks = dict(cal.checks)
            axes = checks.pop(CARRIED_AXES)
            cal = cal.replace(checks=checks, unobservable_axes_body=cal.unobservable_axes_body
                              or tuple(np.asarray(a, float) for a in axes))
        # the held-out figure is the diagnosis' final model's: it speaks for the answer only
        # when that model is the answer (not a model the user restricted with --estimate)
        held = None
        if diag is not None and cal.estimator == "diagnose":
            held = (diag.final or {}).get("heldout_rms_nT")
        return ctx.replace(calibration=with_verdict(
            cal, ctx.need_aligned(), diagnosed=diag is not None,
            heldout_rms_nT=None if held is None else float(held)))


@dataclass(frozen=True)
class Estimate:
    """Stage: fit the calibration (see :func:`fit_calibration` for the parameters)."""

    estimator: EstimatorKind = DEFAULT_ESTIMATOR
    terms: frozenset = frozenset()
    reference_field_enu_nT: tuple[float, float, float] | None = None
    R_nominal_body_mag: tuple | None = None
    robust: RobustLoss = RobustLoss.NONE
    noise: NoiseModel | None = None
    use_segments: bool = False

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "aligned"})
    provides: ClassVar[frozenset[str]] = frozenset({"calibration"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` with ``calibration`` set.

        With ``use_segments`` and segments in the context, only samples inside them are used.
        """
        windows = None
        if self.use_segments and ctx.segments:
            windows = [(s.start_ns, s.end_ns) for s in ctx.segments]
        cal = fit_calibration(
            ctx.recording,
            ctx.need_aligned(),
            estimator=self.estimator,
            terms=self.terms,
            reference_field_enu_nT=self.reference_field_enu_nT,
            R_nominal_body_mag=None
            if self.R_nominal_body_mag is None
            else np.asarray(self.R_nominal_body_mag, float),
            robust=self.robust,
            windows_ns=windows,
            noise=self.noise,
        )
        return ctx.replace(calibration=cal)

"""Estimate stage: the misalignment ``R_body_mag`` and, on request, ``o``, ``D`` and ``tau``.

:func:`fit_calibration` is the library entry point; :class:`Estimate` wraps it as a stage
(requires ``recording`` and ``aligned``, provides ``calibration``). The estimators live in
:mod:`stages.estimators`, one module each, behind the ``Estimator`` protocol.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from pipeline.core.errors import EstimationError, UsageError
from pipeline.core.recording import AlignedSeries, Recording
from pipeline.core.style import GLUE
from pipeline.core.verdict import judge, sensor_noise_nT
from pipeline.core.vocabulary import EstimateTerm, EstimatorKind, RobustLoss
from pipeline.core.words import sig2
from pipeline.model.calibration import Calibration
from pipeline.model.forward import MAX_TIME_OFFSET_S
from pipeline.model.sample_hold import detect_sample_hold, repeated
from stages.context import Context
from stages.estimators.base import EstimationProblem, Estimator, NoiseModel
from stages.estimators.ml import fisher_rotation_crb_deg
from stages.estimators.registry import ESTIMATORS

if TYPE_CHECKING:
    from stages.diagnose.result import Finding

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
            warnings=cal.warnings + (hold.warning(left_out=True),),
        )
    return with_verdict(cal, al)


#: A rotation sigma above this (deg) about a body axis is a doubt: 1 deg of misalignment
#: costs about 870 nT on a 50,000 nT field, more than any sensor's noise.
POOR_AXIS_SIGMA_DEG = 1.0

#: check key of the rotation's sigma (deg, body x, y, z) under white noise: what the motion
#: alone determines, the residual's correlation left out (the final model's)
WHITE_SIGMA = "sigma_rotvec_white_deg"

#: how a doubt about the rotation's own precision begins (judged again, it is replaced)
POOR_AXIS_DOUBT = "the rotation about body "

#: A finding whose windows cover more than this share of the recording acted throughout it:
#: leaving its time out would leave nothing to fit.
WHOLE_RECORDING_SHARE = 0.9


@dataclass(frozen=True)
class LargestEffect:
    """The effect of the diagnosis that explains the most of the residual.

    Attributes
    ----------
    effect : str
        Its name (an ``EffectKind`` value).
    size_nT : float or None
        The magnitude of its field offset where it is one (``offset_nT``), nT.
    windows_s : tuple of (float, float)
        When it acted, s from the first sample; empty when it acted over the whole recording.

    """

    effect: str
    size_nT: float | None
    windows_s: tuple[tuple[float, float], ...]

    def words(self) -> str:
        """Return it for a person: its name, its size and when it acted."""
        text = "a " + self.effect.replace("_", " ")
        if self.size_nT is not None and np.isfinite(self.size_nT):
            text += f" of {_count(self.size_nT)} nT"
        if self.windows_s:
            text += " at " + ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in self.windows_s)
        else:
            text += " over the whole recording"
        return text


def _count(x: float, step: float = 1.0) -> str:
    """Return ``x`` rounded to ``step`` with a no-break space between thousands (11 346)."""
    return f"{int(round(float(x) / step) * step):,}".replace(",", GLUE)


def largest_effect(findings: Sequence[Finding], effects: dict[str, Any] | None,
                   duration_s: float) -> LargestEffect | None:
    """Return the finding that lowered the residual's variance the most, or None.

    Its size and windows are the final model's (``effects`` of the calibration) where that
    model holds it as an effect of its own, else the finding's. Findings handled on the data
    rather than as a term of the model (sample-and-hold) are not candidates.

    Parameters
    ----------
    findings : sequence of Finding
        The diagnosis' findings (``Diagnosis.findings``).
    effects : dict or None
        ``Calibration.effects`` of the final model.
    duration_s : float
        Length of the recording, s (a window covering nearly all of it is no window).

    """
    best, gain = None, 0.0
    for f in findings:
        ev = f.evidence or {}
        before, after = ev.get("rms_before_nT"), ev.get("rms_after_nT")
        if f.effect == "sample_hold" or before is None or after is None:
            continue
        g = float(before) ** 2 - float(after) ** 2
        if np.isfinite(g) and g > gain:
            best, gain = f, g
    if best is None:
        return None
    params = (effects or {}).get(best.effect)
    if not isinstance(params, dict):  # absent, or several terms of one kind
        params = best.params
    off = params.get("offset_nT")
    size = None if off is None else float(np.linalg.norm(np.asarray(off, float)))
    wins = params.get("windows_s") or (best.where or {}).get("windows_s") or ()
    windows = tuple((float(a), float(b)) for a, b in wins)
    span = sum(b - a for a, b in windows)
    if duration_s > 0 and span >= WHOLE_RECORDING_SHARE * duration_s:
        windows = ()
    return LargestEffect(best.effect, size, windows)


def _beyond(xs: Sequence[float], limit: float) -> list[str]:
    """Return sigmas to one decimal, or to as many more (up to 3) as show each exceeds ``limit``.

    A sigma quoted because it exceeds a threshold must read above it (1.03 deg over 1 deg
    printed as "1.0" says the opposite); the sigmas of one sentence share their decimals.
    """
    dec = 1
    while dec < 3 and any(round(x, dec) <= limit for x in xs):
        dec += 1
    return [f"{x:.{dec}f}" for x in xs]


def _listed(items: Sequence[str]) -> str:
    """Return ``x``, ``x and y``, ``x, y and z``."""
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def motion_sigma_deg(cal: Calibration, aligned: AlignedSeries,
                     noise_nT: float | None) -> np.ndarray | None:
    """Return the rotation's sigma (deg, body x, y, z) that the motion alone determines.

    The white-noise sigma of the model that is the answer (``checks`` key
    :data:`WHITE_SIGMA`, written by the maximum-likelihood estimator and by the diagnosis for
    its final model). An estimator that does not write it (li2020, ellipsoid, dpi) gets the
    Cramer-Rao bound of its own terms on the aligned attitudes under the measured sensor
    noise (:func:`stages.estimators.ml.fisher_rotation_crb_deg`, the field unknown). None
    when neither is available (no still window to measure the noise).
    """
    white = cal.checks.get(WHITE_SIGMA)
    if white is not None:
        return np.asarray(white, float)
    if noise_nT is None or not np.isfinite(noise_nT) or noise_nT <= 0:
        return None
    terms = frozenset(t for t, v in ((EstimateTerm.OFFSET, cal.offset_nT),
                                     (EstimateTerm.SOFT_IRON, cal.D)) if v is not None)
    p = EstimationProblem(t_ns=aligned.t_ns, mag_nT=aligned.mag_nT,
                          q_enu_body=aligned.q_enu_body, terms=terms,
                          noise=NoiseModel(sigma_mag_nT=float(noise_nT)))
    try:
        return fisher_rotation_crb_deg(p, np.asarray(cal.R_body_mag, float),
                                       np.asarray(cal.B_enu_nT, float),
                                       D=cal.D, offset_nT=cal.offset_nT)
    except (EstimationError, np.linalg.LinAlgError):
        return None


def poor_axis_doubts(cal: Calibration, motion_deg: np.ndarray | None,
                     effect: LargestEffect | None = None) -> list[str]:
    """Return the doubts about the axes the rotation is known to worse than the threshold.

    A sigma over :data:`POOR_AXIS_SIGMA_DEG` about a body axis has one of two causes. Where
    the motion alone (``motion_deg``, white noise and the geometry of the turns) already
    leaves the axis that poorly determined, the motion is to blame and the remedy is to turn
    about it. Where the motion determines it well, the sigma is wide because of what the
    residual holds: samples correlated in time (few independent ones) or an effect the model
    carries; the doubt quotes the motion's sigma and the independent samples, and names
    ``effect``, the largest the diagnosis found (:func:`largest_effect`), if any. Each cause
    is one doubt listing all its axes, the one with the widest sigma first.
    """
    sig = np.asarray(cal.sigma_rotvec_deg, float)
    poor = [i for i in np.argsort(-sig) if sig[i] > POOR_AXIS_SIGMA_DEG]
    if not poor:
        return []
    mot = np.full(3, np.inf) if motion_deg is None else np.asarray(motion_deg, float)
    # an unknown motion sigma (inf) or a NaN one leaves the blame with the motion
    by_motion = [i for i in poor if not mot[i] <= POOR_AXIS_SIGMA_DEG]
    by_residual = [i for i in poor if i not in by_motion]
    out: list[tuple[float, str]] = []
    for motion_poor, axes in ((True, sorted(by_motion)), (False, sorted(by_residual))):
        if not axes:
            continue
        widest = float(max(sig[i] for i in axes))
        names = _listed(["xyz"[i] for i in axes])
        head = (f"{POOR_AXIS_DOUBT}{names} is only known to "
                f"{_listed(_beyond([sig[i] for i in axes], POOR_AXIS_SIGMA_DEG))} deg")
        if motion_poor:
            one = len(axes) == 1
            out.append((widest, f"{head}: the motion barely turned the sensor about "
                                f"{'that axis' if one else 'those axes'}"))
            continue
        text = (f"{head}, though the motion alone determines it to "
                f"{_listed([sig2(mot[i]) for i in axes])} deg: what the residual holds "
                "widens the sigma")
        if cal.n_eff is not None and np.isfinite(cal.n_eff):
            n_eff = _count(cal.n_eff) if cal.n_eff >= 1 else "fewer than 1"
            text += (f" (its samples are correlated in time: {n_eff} independent "
                     f"samples of {_count(cal.n_samples)})")
        if effect is not None:
            text += f"; the largest effect in the model is {effect.words()}"
        out.append((widest, text))
    # the widest sigma's cause first: the verdict states the first doubt
    return [text for _, text in sorted(out, key=lambda x: -x[0])]


def with_verdict(cal: Calibration, aligned: AlignedSeries,
                 residual_rms_nT: float | None = None, diagnosed: bool = False,
                 heldout_rms_nT: float | None = None,
                 effect: LargestEffect | None = None) -> Calibration:
    """Return ``cal`` with its verdict (:mod:`pipeline.core.verdict`) from the aligned samples.

    The sensor noise is measured in the still windows of ``aligned`` (repeated
    sample-and-hold messages left out); the fit's checks (``cal.checks``) give the refusals
    and doubts, and a rotation known to worse than :data:`POOR_AXIS_SIGMA_DEG` about a body
    axis the motion does determine is one more, attributed to the motion or to the residual
    (:func:`poor_axis_doubts`).

    Parameters
    ----------
    cal : Calibration
        The calibration that is the answer.
    aligned : AlignedSeries
        Its samples.
    residual_rms_nT : float, optional
        Overrides the calibration's own residual (a later, fuller model).
    diagnosed : bool
        The diagnosis ran: the verdict's advice points to its findings.
    heldout_rms_nT : float, optional
        The final model's error on held-out samples, when the diagnosis measured it (the
        verdict judges and quotes it).
    effect : LargestEffect, optional
        The largest effect the diagnosis found: a sigma the motion does not explain names it.

    Returns
    -------
    Calibration

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
    doubts = [d for d in cal.checks.get("doubts", ()) if not d.startswith(POOR_AXIS_DOUBT)]
    sig = np.asarray(cal.sigma_rotvec_deg, float)
    if len(cal.unobservable_axes_body) == 0 and np.all(np.isfinite(sig)) and np.any(
            sig > POOR_AXIS_SIGMA_DEG):
        # first: the verdict states the first doubt, and a rotation known only to degrees is
        # the largest uncertainty of the answer; the sigmas it quotes already include what
        # the other checks measured (the halves' disagreement widens them)
        doubts = poor_axis_doubts(cal, motion_sigma_deg(cal, aligned, noise), effect) + doubts
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
        # the estimate's share of independent samples (its residual's correlation), over
        # the final model's samples: the count is quoted as "N independent samples of M"
        # with M the final model's, so both must count the same samples
        n_eff=after.n_eff if after.n_eff is not None else (
            None if before.n_eff is None or not before.n_samples
            else before.n_eff / before.n_samples * after.n_samples),
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
        A rotation sigma the motion does not explain names the diagnosis' largest effect
        (:func:`largest_effect`).
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
        effect = None if diag is None else largest_effect(diag.findings, cal.effects,
                                                           diag.duration_s)
        return ctx.replace(calibration=with_verdict(
            cal, ctx.need_aligned(), diagnosed=diag is not None,
            heldout_rms_nT=None if held is None else float(held), effect=effect))


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

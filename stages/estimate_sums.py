"""Stage EstimateFromSums: the ML fit of a long recording from the sums of every sample."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.core.errors import EstimationError
from pipeline.core.vocabulary import EstimateTerm
from pipeline.model.calibration import Calibration
from stages.context import Context
from stages.estimators.checks import SplitCheck, apply_split
from stages.estimators.streaming import StreamStats, fit_stats

#: halves with fewer samples than this are not fitted on their own
MIN_HALF_SAMPLES = 200


@dataclass(frozen=True)
class EstimateFromSums:
    """Stage: the ML rotation and the terms asked for, from the sums of every sample.

    The runner's first pass reduces every aligned sample of a long recording to fixed-size
    sums (:class:`stages.estimators.streaming.SampleSums`); Gauss-Newton runs on the sums
    alone (:func:`stages.estimators.streaming.fit_stats`), with the block sandwich
    covariance. Without soft iron or time offset the sums are those of the recording's two
    halves: their fits check the whole's sigmas as the in-memory estimator's split halves do
    (:func:`split_halves`).

    Parameters
    ----------
    terms : frozenset of EstimateTerm
        Estimated beside the rotation; at most :attr:`SUPPORTED_TERMS`.
    reference_field_enu_nT : 3-tuple of float, optional
        Known background field (ENU, nT); estimated when None.

    """

    terms: frozenset[EstimateTerm] = frozenset()
    reference_field_enu_nT: tuple[float, float, float] | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"sums"})
    provides: ClassVar[frozenset[str]] = frozenset({"calibration"})
    #: the terms the sums determine besides the rotation and the field
    SUPPORTED_TERMS: ClassVar[frozenset[EstimateTerm]] = frozenset(
        {EstimateTerm.OFFSET, EstimateTerm.SOFT_IRON, EstimateTerm.TIME_OFFSET})

    def run(self, ctx: Context) -> Context:
        """Fit ``calibration`` from ``ctx.sums``."""
        terms = frozenset(EstimateTerm(t) for t in self.terms)
        unknown = terms - self.SUPPORTED_TERMS
        if unknown:
            raise EstimationError("the streaming estimator cannot estimate "
                                  + ", ".join(sorted(t.value for t in unknown)))
        sums = ctx.need_sums()
        ref = self.reference_field_enu_nT
        kw: dict[str, Any] = {
            "estimate_offset": EstimateTerm.OFFSET in terms,
            "reference_field_enu_nT": None if ref is None else np.asarray(ref, float),
            "block_sandwich": True}
        if sums.terms is not None:
            fit = fit_stats(sums.terms, estimate_soft_iron=EstimateTerm.SOFT_IRON in terms,
                            estimate_time_offset=EstimateTerm.TIME_OFFSET in terms, **kw)
            return ctx.replace(calibration=fit.to_calibration())
        if sums.halves is None:
            raise EstimationError("no sums of the recording to fit")
        first, second = sums.halves
        cal = fit_stats(first + second, **kw).to_calibration()
        return ctx.replace(calibration=split_halves(cal, (first, second), kw, sums.split_s))


def split_halves(cal: Calibration, halves: tuple[StreamStats, StreamStats],
                 kw_fit: dict[str, Any], split_s: float) -> Calibration:
    """Return the fit ``cal`` of the whole checked against the fits of its two halves.

    As the in-memory estimator does (:func:`stages.estimators.checks.apply_split`): when the
    halves disagree beyond their sigmas, the disagreement goes into the rotation's sigmas
    (and into the verdict's doubts when it more than doubles them), and the check is recorded
    in ``checks["split"]`` (``split_s``: where the halves meet, s from the first sample).
    """
    if min(h.n for h in halves) < MIN_HALF_SAMPLES:
        return cal
    try:
        a, b = (fit_stats(h, **kw_fit).to_calibration() for h in halves)
    except (EstimationError, np.linalg.LinAlgError):
        return cal
    if (a.unobservable_axes_body or b.unobservable_axes_body) and not cal.unobservable_axes_body:
        return cal
    split = SplitCheck.compare(a, b, split_s)
    cal = cal.replace(checks={**cal.checks, "split": split.to_dict()})
    return apply_split(cal, split)

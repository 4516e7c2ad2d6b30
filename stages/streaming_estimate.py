"""Stage StreamingEstimate: the ML fit of a long recording from chunked sufficient statistics."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pipeline.core.recording import Context
from stages.estimators.base import Term

#: aligned samples reduced at once by :class:`StreamingEstimate` (bounds its temporaries)
STREAM_BLOCK = 200_000


@dataclass(frozen=True)
class StreamingEstimate:
    """Stage: ML rotation and the requested terms of a long recording from streamed sums.

    :mod:`stages.estimators.streaming`: the aligned samples are reduced block by block
    (:class:`~stages.estimators.streaming.StreamAccumulator`, every sample, one pass) to a
    fixed set of sums and Gauss-Newton runs on the sums, so estimation costs one pass over
    the data and no per-sample matrices. ``terms`` may name any of :attr:`SUPPORTED_TERMS`:
    the offset ``o``, the soft iron ``D`` and the time offset ``tau`` (from the second-order
    expansion of the attitude about each stamp). ``estimate_offset`` is the older spelling
    of ``Term.OFFSET``.
    """

    estimate_offset: bool = False
    reference_field_enu_nT: tuple[float, float, float] | None = None
    terms: frozenset = frozenset()

    requires: ClassVar[frozenset[str]] = frozenset({"aligned"})
    provides: ClassVar[frozenset[str]] = frozenset({"calibration"})
    #: the terms this stage estimates besides the rotation and the field
    SUPPORTED_TERMS: ClassVar[frozenset[Term]] = frozenset(
        {Term.OFFSET, Term.SOFT_IRON, Term.TIME_OFFSET})

    def run(self, ctx: Context) -> Context:
        """Fit ``calibration`` from ``ctx.aligned``."""
        from pipeline.core.errors import EstimationError
        from stages.estimators.streaming import StreamAccumulator, fit_stats

        terms = frozenset(Term(t) for t in self.terms)
        unknown = terms - self.SUPPORTED_TERMS
        if unknown:
            raise EstimationError("the streaming estimator cannot estimate "
                                  + ", ".join(sorted(t.value for t in unknown)))
        al = ctx.need_aligned()
        acc = StreamAccumulator()
        for i in range(0, len(al), STREAM_BLOCK):
            acc.add(al.q_enu_body[i : i + STREAM_BLOCK], al.mag_nT[i : i + STREAM_BLOCK],
                    al.t_ns[i : i + STREAM_BLOCK])
        ref = None if self.reference_field_enu_nT is None else np.asarray(
            self.reference_field_enu_nT, dtype=float)
        fit = fit_stats(acc.result(),
                        estimate_offset=self.estimate_offset or Term.OFFSET in terms,
                        estimate_soft_iron=Term.SOFT_IRON in terms,
                        estimate_time_offset=Term.TIME_OFFSET in terms,
                        reference_field_enu_nT=ref)
        cal = fit.to_calibration()
        if cal.time_offset_s is not None:
            # the aligned attitude is at t - al.time_offset_s: tau is counted from there
            cal = cal.replace(time_offset_s=float(al.time_offset_s) + cal.time_offset_s)
        return ctx.replace(calibration=cal)

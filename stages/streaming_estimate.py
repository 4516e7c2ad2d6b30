"""Stage StreamingEstimate: the ML fit of a long recording from chunked sufficient statistics."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pipeline.core.recording import Context

#: aligned samples reduced at once by :class:`StreamingEstimate` (bounds its temporaries)
STREAM_BLOCK = 200_000


@dataclass(frozen=True)
class StreamingEstimate:
    """Stage: ML rotation (and offset) of a long recording from chunked sufficient statistics.

    :mod:`stages.estimators.streaming`: the aligned samples are reduced block by block to a
    fixed set of sums and Gauss-Newton runs on the sums, so estimation costs one pass over
    the data and no per-sample matrices.
    """

    estimate_offset: bool = False
    reference_field_enu_nT: tuple[float, float, float] | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"aligned"})
    provides: ClassVar[frozenset[str]] = frozenset({"calibration"})

    def run(self, ctx: Context) -> Context:
        """Fit ``calibration`` from ``ctx.aligned``."""
        from stages.estimators.streaming import SufficientStats, fit_stats

        al = ctx.need_aligned()
        blocks = (
            SufficientStats.from_samples(al.q_enu_body[i : i + STREAM_BLOCK],
                                         al.mag_nT[i : i + STREAM_BLOCK],
                                         al.t_ns[i : i + STREAM_BLOCK])
            for i in range(0, len(al), STREAM_BLOCK)
        )
        st = sum(blocks, SufficientStats())
        ref = None if self.reference_field_enu_nT is None else np.asarray(
            self.reference_field_enu_nT, dtype=float)
        fit = fit_stats(st, estimate_offset=self.estimate_offset, reference_field_enu_nT=ref)
        return ctx.replace(calibration=fit.to_calibration())

"""Stage OnDecimated: another stage run on every k-th magnetometer sample of a long recording."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.core.recording import Context


@dataclass(frozen=True)
class OnDecimated:
    """Stage: run ``inner`` on every ``step``-th magnetometer sample of a long recording.

    Segmentation and diagnosis of hours of data need not see every sample (their windows
    are seconds long); the fields ``inner`` provides are taken over into the full context.
    The attitude is kept whole so the decimated samples are aligned as before.
    """

    inner: Any
    step: int

    @property
    def requires(self) -> frozenset[str]:
        """The inner stage's requirements."""
        return self.inner.requires

    @property
    def provides(self) -> frozenset[str]:
        """The inner stage's results."""
        return self.inner.provides

    def run(self, ctx: Context) -> Context:
        """Run ``inner`` on the decimated context; return ``ctx`` with its results."""
        small = decimate_context(ctx, self.step)
        out = self.inner.run(small)
        # a restore result of the decimated samples is not one of the recording's: the
        # Restore stage computes it again on every sample
        return ctx.replace(**{k: getattr(ctx if k == "restored" else out, k)
                              for k in self.inner.provides})


def decimate_context(ctx: Context, step: int) -> Context:
    """``ctx`` with every ``step``-th magnetometer sample (recording.mag and aligned)."""
    import dataclasses

    from pipeline.core.recording import AlignedSeries, VectorSeries

    rec, al = ctx.recording, ctx.aligned
    changes: dict[str, Any] = {}
    if rec is not None:
        m = rec.mag
        changes["recording"] = dataclasses.replace(
            rec, mag=VectorSeries(m.t_ns[::step], m.values[::step], m.frame, m.unit))
    if al is not None:
        if al.index is not None:
            keep = np.flatnonzero(al.index % step == 0)
            index = al.index[keep] // step
        else:
            keep, index = np.arange(0, len(al), step), None
        changes["aligned"] = AlignedSeries(al.t_ns[keep], al.mag_nT[keep], al.q_enu_body[keep],
                                           al.time_offset_s, index)
    return ctx.replace(**changes)

"""Resample stage: the attitude onto the magnetometer stamps (THE interpolator).

More in docs/modules.md, ``stages.resample``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pipeline.core.errors import InputError
from pipeline.core.recording import AlignedSeries, AttitudeSeries
from pipeline.model.attitude import AUTO_GAP_INTERVALS, MIN_AUTO_GAP_S, interpolate_attitude
from pipeline.model.attitude import auto_max_gap_s as _auto_max_gap_s
from stages.context import Context

__all__ = ["AUTO_GAP_INTERVALS", "MIN_AUTO_GAP_S", "Resample", "auto_max_gap_s",
           "interpolate_attitude"]


def auto_max_gap_s(attitude: AttitudeSeries) -> float:
    """Default gap threshold: ``max(0.05 s, 5 x median attitude interval)`` (the model's rule)."""
    return _auto_max_gap_s(attitude.t_ns)


@dataclass(frozen=True)
class Resample:
    """Attitude onto magnetometer stamps (THE interpolator at ``t - time_offset_s``).

    Parameters
    ----------
    time_offset_s : float
        ``tau`` (CONVENTIONS).
    max_gap_s : float or None
        Gap threshold, s; ``None``: :func:`auto_max_gap_s` of the recording's attitude.

    """

    time_offset_s: float = 0.0
    max_gap_s: float | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"recording"})
    provides: ClassVar[frozenset[str]] = frozenset({"aligned"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` with ``aligned``: magnetometer samples with a usable attitude."""
        rec = ctx.recording
        if rec is None or rec.attitude is None:
            raise InputError(
                "no attitude to resample" if rec is not None else "no recording",
                path=None if rec is None else rec.path,
                hint="a turntable recording needs the TurntableAttitude stage before Resample",
            )
        gap = auto_max_gap_s(rec.attitude) if self.max_gap_s is None else self.max_gap_s
        q, valid = interpolate_attitude(
            rec.attitude, rec.mag.t_ns, time_offset_s=self.time_offset_s, max_gap_s=gap
        )
        idx = np.flatnonzero(valid)
        aligned = AlignedSeries(
            rec.mag.t_ns[idx], rec.mag.values[idx], q[idx], float(self.time_offset_s), idx
        )
        return ctx.replace(aligned=aligned)

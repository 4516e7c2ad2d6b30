"""Resample stage: the attitude onto the magnetometer stamps (THE interpolator).

Time offset (CONVENTIONS): ``tau > 0`` means the magnetometer stamps are late, i.e. the
sample stamped ``t`` was sensed at ``t - tau``; the attitude is therefore taken at
``t - tau``.

Gaps: the attitude is not bridged across an interval between two consecutive attitude
samples longer than ``max_gap_s`` (motion capture loses the markers, an INS drops out).
The default of :class:`Resample` is ``max(0.05 s, 5 x the median attitude interval)``: five
missed samples of a fast source, and never less than 50 ms, which at the rotation rates of a
calibration manoeuvre (tens of deg/s) keeps the interpolation error of a bridged gap well under a
degree only for short gaps.
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

"""Resample stage: the attitude interpolated onto the magnetometer stamps by SLERP.

Time offset (CONVENTIONS): ``tau > 0`` means the magnetometer stamps are late, i.e. the
sample stamped ``t`` was sensed at ``t - tau``; the attitude is therefore taken at
``t - tau``.

Gaps: the attitude is not bridged across an interval between two consecutive attitude
samples longer than ``max_gap_s`` (motion capture loses the markers, an INS drops out).
The default of :class:`Resample` is ``max(0.05 s, 5 x the median attitude interval)``: five
missed samples of a fast source, and never less than 50 ms, which at the rotation rates of a
calibration manoeuvre (tens of deg/s) keeps the SLERP error of a bridged gap well under a
degree only for short gaps.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from pipeline.errors import InputError
from pipeline.geometry import quat_normalize, quat_slerp
from pipeline.recording import AlignedSeries, AttitudeSeries, Context

#: lower bound of the automatic gap threshold, s
MIN_AUTO_GAP_S = 0.05
#: automatic gap threshold in median attitude intervals
AUTO_GAP_INTERVALS = 5.0


def auto_max_gap_s(attitude: AttitudeSeries) -> float:
    """Default gap threshold: ``max(0.05 s, 5 x median attitude interval)``."""
    t = np.asarray(attitude.t_ns)
    d = np.diff(t)
    if not bool(np.all(d > 0)):  # sorted without duplicates (what ingest gives) skips the sort
        t = np.unique(t)
        d = np.diff(t)
    if len(t) < 2:
        return MIN_AUTO_GAP_S
    return max(MIN_AUTO_GAP_S, AUTO_GAP_INTERVALS * float(np.median(d)) * 1e-9)


def interpolate_attitude(
    attitude: AttitudeSeries,
    t_ns: NDArray[np.int64],
    *,
    time_offset_s: float = 0.0,
    max_gap_s: float = 0.1,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """SLERP of ``q_enu_body`` at ``t - time_offset_s``.

    Parameters
    ----------
    attitude : AttitudeSeries
        Need not be sorted; duplicated stamps keep their first sample.
    t_ns : ndarray of int64, shape (N,)
        Query stamps (magnetometer), ns.
    time_offset_s : float
        ``tau`` of CONVENTIONS: the attitude is taken at ``t - tau``.
    max_gap_s : float
        Bracketing attitude samples further apart than this are not interpolated between.

    Returns
    -------
    q_enu_body : ndarray, shape (N, 4)
        Unit quaternions, scalar-last (NaN where not valid).
    valid : ndarray of bool, shape (N,)
        False outside the attitude span or inside a gap.

    """
    t_q = np.asarray(t_ns, dtype=np.int64)
    ta = np.asarray(attitude.t_ns, dtype=np.int64)
    qa = np.asarray(attitude.q_enu_body, dtype=float)
    if len(ta) and np.any(np.diff(ta) <= 0):
        order = np.argsort(ta, kind="stable")
        ta, qa = ta[order], qa[order]
        keep = np.concatenate([[True], np.diff(ta) > 0])
        ta, qa = ta[keep], qa[keep]
    n = len(t_q)
    out = np.full((n, 4), np.nan)
    if len(ta) == 0 or n == 0:
        return out, np.zeros(n, dtype=bool)
    # query time relative to the first attitude stamp, in s: keeps float precision (epoch
    # ns do not fit a float64 exactly) and handles sub-ns offsets
    tq = (t_q - ta[0]).astype(float) * 1e-9 - float(time_offset_s)
    tr = (ta - ta[0]).astype(float) * 1e-9
    i = np.searchsorted(tr, tq, side="right") - 1  # tr[i] <= tq < tr[i + 1]
    exact_end = tq == tr[-1]
    i = np.where(exact_end, len(tr) - 2, i)
    inside = (i >= 0) & (i < len(tr) - 1)
    if len(tr) == 1:
        inside = tq == tr[0]
        out[inside] = quat_normalize(qa[0])
        return out, inside
    j = np.clip(i, 0, len(tr) - 2)
    dt = tr[j + 1] - tr[j]
    # a sample that falls exactly on an attitude stamp needs no bridging, even beside a gap
    on_sample = (tq == tr[j]) | (tq == tr[j + 1])
    valid = inside & ((dt <= max_gap_s + 1e-12) | on_sample)
    s = np.clip((tq - tr[j]) / dt, 0.0, 1.0)
    q = quat_slerp(qa[j[valid]], qa[j[valid] + 1], s[valid])
    out[valid] = q
    return out, valid


@dataclass(frozen=True)
class Resample:
    """Attitude onto magnetometer stamps (SLERP at ``t - time_offset_s``).

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

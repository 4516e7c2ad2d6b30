"""Segment stage: which stretches of a recording are rotations, static, manoeuvres, lines, turns.

Everything is decided from the angular rate computed from the attitude (``log(q_k^-1 q_k+1)``
per interval, smoothed over ``smooth_s`` by a time-weighted moving average), vectorised over
samples; Python loops run only over segments.

1. Intervals whose smoothed rate is below ``static_rate_deg_s`` are *still*: ``STATIC`` in a
   lab recording, ``LINE`` (near-constant heading) in a survey (``MotionContext.SURVEY``): the
   attitude alone cannot tell a parked vehicle from one driving straight.
   In a survey only the heading rate (about ENU up) counts, so pitch/roll wobble on a line
   does not end it.
2. Moving intervals whose rate direction agrees (within ``axis_tol_deg``) with the direction
   ``axis_window_s / 2`` before and after are on a *stable axis*; a run of them is split where
   the direction strays from the run's starting axis, and each piece that turns at least
   ``min_twist_deg`` about its fitted axis is a ``ROTATION`` (in a survey at least a full
   loop, 360 deg: a 180 deg turn between lines is a ``TURN``).
3. The remaining moving stretches (axis changing, or too little twist) are ``MANOEUVRE``, or
   ``TURN`` in a survey when the fitted axis is within ``turn_vertical_tol_deg`` of ENU up and
   the heading changes by at least ``turn_min_deg``.

Runs shorter than ``min_still_s`` / ``min_moving_s`` are absorbed by their neighbours first, and
segments shorter than ``min_segment_s`` are dropped (the segments need not cover the whole
recording). Each segment carries the descriptors of :func:`pipeline.tang.fit_rotation`.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from pipeline.errors import DataQualityError
from pipeline.recording import AlignedSeries, Context, Segment, SegmentKind
from pipeline.tang import angular_rate, fit_rotation

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

_GAP, _STILL, _STABLE, _UNSTABLE = 0, 1, 2, 3


class MotionContext(enum.Enum):
    """What kind of recording it is: decides the names of still and turning stretches."""

    LAB = "lab"
    SURVEY = "survey"


def _runs(labels: NDArray) -> tuple[I64, I64]:
    """Start and end (exclusive) indices of runs of equal values in a 1-D array."""
    if labels.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    change = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    starts = np.concatenate([[0], change]).astype(np.int64)
    ends = np.concatenate([change, [labels.size]]).astype(np.int64)
    return starts, ends


def _absorb_short(labels: NDArray, dur_s: F64, which: int, into: int, min_s: float) -> NDArray:
    """Relabel runs of ``which`` shorter than ``min_s`` (seconds) as ``into``."""
    if min_s <= 0:
        return labels
    out = labels.copy()
    s, e = _runs(labels)
    c = np.concatenate([[0.0], np.cumsum(dur_s)])
    for a, b in zip(s, e, strict=True):
        if labels[a] == which and c[b] - c[a] < min_s:
            out[a:b] = into
    return out


def smooth_rate(t_mid_s: F64, w: F64, dt_s: F64, half_s: float) -> F64:
    """Time-weighted moving average of rates ``w`` (M, 3) over ``[t - half, t + half]``.

    Uses cumulative sums (one pass, no per-sample loop): the average is the rotation accumulated
    in the window divided by the time it spans.
    """
    if half_s <= 0 or w.shape[0] == 0:
        return w.copy()
    cw = np.concatenate([np.zeros((1, 3)), np.cumsum(w * dt_s[:, None], axis=0)])
    cd = np.concatenate([[0.0], np.cumsum(dt_s)])
    lo = np.searchsorted(t_mid_s, t_mid_s - half_s, side="left")
    hi = np.searchsorted(t_mid_s, t_mid_s + half_s, side="right")
    d = cd[hi] - cd[lo]
    return (cw[hi] - cw[lo]) / np.where(d > 0, d, np.inf)[:, None]


@dataclass(frozen=True)
class SegmentMotion:
    """Find rotation segments, still stretches, manoeuvres, lines and turns.

    Parameters
    ----------
    min_twist_deg : float
        Smallest net rotation about a stable axis for a ``ROTATION`` segment.
    static_rate_deg_s : float
        Smoothed rotation rate below which the platform is still.
    axis_tol_deg : float
        Largest change of the rotation axis within a rotation segment.
    smooth_s : float
        Width of the moving average applied to the angular rate.
    axis_window_s : float
        Span over which the axis must stay put to count as stable.
    max_gap_s : float
        Attitude intervals longer than this break segments (occlusions, dropouts).
    min_still_s, min_moving_s, min_segment_s : float
        Shortest still run, moving run and reported segment (seconds).
    context : MotionContext
        ``LAB``: still stretches are ``STATIC``; ``SURVEY``: they are ``LINE`` and heading
        changes about the vertical are ``TURN``.
    turn_min_deg, turn_vertical_tol_deg : float
        Smallest heading change of a ``TURN`` and largest angle of its axis from ENU up.

    """

    min_twist_deg: float = 180.0
    static_rate_deg_s: float = 2.0
    axis_tol_deg: float = 20.0
    smooth_s: float = 0.25
    axis_window_s: float = 1.0
    max_gap_s: float = 0.25
    min_still_s: float = 0.5
    min_moving_s: float = 0.5
    min_segment_s: float = 0.5
    context: MotionContext = MotionContext.LAB
    turn_min_deg: float = 20.0
    turn_vertical_tol_deg: float = 30.0

    requires: ClassVar[frozenset[str]] = frozenset({"aligned"})
    provides: ClassVar[frozenset[str]] = frozenset({"segments"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` with ``segments`` (tuple of Segment, in time order)."""
        if ctx.aligned is None:
            raise DataQualityError("segmentation needs aligned attitude and magnetometer samples")
        return ctx.replace(segments=self.segment(ctx.aligned))

    # ------------------------------------------------------------------ the work
    def segment(self, aligned: AlignedSeries) -> tuple[Segment, ...]:
        """Segments of one aligned series (see the module docstring)."""
        t = np.asarray(aligned.t_ns, dtype=np.int64)
        q = np.asarray(aligned.q_enu_body, dtype=float)
        if t.shape[0] < 3:
            return ()
        wb, we, dt = angular_rate(t, q)
        t_s = (t - t[0]).astype(float) * 1e-9
        t_mid = 0.5 * (t_s[:-1] + t_s[1:])
        # a slow attitude source (e.g. 1 Hz) is not a gap at every sample
        max_gap = max(self.max_gap_s, 3.0 * float(np.median(dt)))
        gap = ~(dt > 0) | (dt > max_gap)
        dt_ok = np.where(gap, 0.0, dt)
        wb = np.where(gap[:, None], 0.0, wb)
        we = np.where(gap[:, None], 0.0, we)
        wbs = smooth_rate(t_mid, wb, dt_ok, 0.5 * self.smooth_s)
        wes = smooth_rate(t_mid, we, dt_ok, 0.5 * self.smooth_s)
        rate = np.linalg.norm(wbs, axis=1)
        if self.context is MotionContext.SURVEY:
            # survey: a line is near-constant heading; pitch/roll wobble does not end it
            moving = np.abs(wes[:, 2]) >= np.radians(self.static_rate_deg_s)
        else:
            moving = rate >= np.radians(self.static_rate_deg_s)

        u = wbs / np.where(rate > 0, rate, 1.0)[:, None]
        h = 0.5 * self.axis_window_s
        i_prev = np.searchsorted(t_mid, t_mid - h, side="left")
        i_next = np.clip(np.searchsorted(t_mid, t_mid + h, side="right") - 1, 0, len(t_mid) - 1)
        c = np.cos(np.radians(self.axis_tol_deg))
        ok_prev = (np.sum(u * u[i_prev], axis=1) > c) | ~moving[i_prev]
        ok_next = (np.sum(u * u[i_next], axis=1) > c) | ~moving[i_next]
        labels = np.where(moving, np.where(ok_prev & ok_next, _STABLE, _UNSTABLE), _STILL)
        labels = _absorb_short(labels, dt_ok, _STILL, _UNSTABLE, self.min_still_s)
        moving_lab = np.where(labels == _STILL, _STILL, 9)
        short_moving = _absorb_short(moving_lab, dt_ok, 9, _STILL, self.min_moving_s)
        labels = np.where(short_moving == _STILL, _STILL, labels)
        labels = np.where(gap, _GAP, labels)

        # pieces: (start interval, end interval exclusive, kind or None for "other moving")
        pieces: list[tuple[int, int, SegmentKind | None]] = []
        starts, ends = _runs(labels)
        for a, b in zip(starts, ends, strict=True):
            lab = labels[a]
            if lab == _GAP:
                continue
            if lab == _STILL:
                survey = self.context is MotionContext.SURVEY
                pieces.append((int(a), int(b), SegmentKind.LINE if survey else SegmentKind.STATIC))
            elif lab == _UNSTABLE:
                pieces.append((int(a), int(b), None))
            else:
                for a2, b2 in self._split_axis(u, int(a), int(b), t_mid):
                    ax = self._axis(wbs, dt_ok, a2, b2)
                    twist = abs(float(np.sum((wbs[a2:b2] @ ax) * dt_ok[a2:b2])))
                    need = self.min_twist_deg
                    if self.context is MotionContext.SURVEY:
                        need = max(need, 360.0)  # a survey turn is a rotation only if it loops
                    kind = SegmentKind.ROTATION if np.degrees(twist) >= need else None
                    pieces.append((a2, b2, kind))

        # merge neighbouring "other moving" pieces (no gap between them)
        merged: list[list] = []
        for a, b, k in pieces:
            if merged and k is None and merged[-1][2] is None and merged[-1][1] == a:
                merged[-1][1] = b
            else:
                merged.append([a, b, k])

        mag = np.asarray(aligned.mag_nT, dtype=float)
        out: list[Segment] = []
        for a, b, k in merged:
            dur = float(np.sum(dt_ok[a:b]))
            if dur < self.min_segment_s:
                continue
            s0, s1 = a, b + 1  # samples a..b (interval b-1 ends at sample b)
            fit = fit_rotation(
                t[s0:s1], q[s0:s1], field_dirs_body=mag[s0:s1], w_body=wbs[a:b], w_enu=wes[a:b]
            )
            if k is None:
                k = SegmentKind.MANOEUVRE
                if self.context is MotionContext.SURVEY:
                    cos_tol = np.cos(np.radians(self.turn_vertical_tol_deg))
                    vertical = abs(fit.axis_enu[2]) >= cos_tol
                    if vertical and fit.twist_deg >= self.turn_min_deg:
                        k = SegmentKind.TURN
            # half-open: sample b starts the next piece; the last piece keeps the last sample
            end_ns = int(t[b]) if b < t.shape[0] - 1 else int(t[-1]) + 1
            still = k in (SegmentKind.STATIC, SegmentKind.LINE)
            out.append(
                Segment(
                    start_ns=int(t[s0]),
                    end_ns=end_ns,
                    kind=k,
                    # a still stretch has no meaningful axis or rate profile
                    axis_body=None if still else fit.axis_body,
                    axis_enu=None if still else fit.axis_enu,
                    twist_deg=fit.twist_deg,
                    rate_cv=None if still else fit.rate_cv,
                    swing_rms_deg=fit.swing_rms_deg,
                    coverage=fit.coverage,
                )
            )
        return tuple(out)

    @staticmethod
    def _axis(w: F64, dt: F64, a: int, b: int) -> F64:
        S = (w[a:b] * dt[a:b, None]).T @ w[a:b]
        ax = np.linalg.eigh(S)[1][:, -1]
        return ax if float(np.sum((w[a:b] @ ax) * dt[a:b])) >= 0 else -ax

    def _split_axis(self, u: F64, a: int, b: int, t_mid: F64) -> list[tuple[int, int]]:
        """Split a stable-axis run where the axis strays from the direction it started with."""
        c = np.cos(np.radians(self.axis_tol_deg))
        out = []
        while a < b:
            i_ref = int(np.searchsorted(t_mid, t_mid[a] + 0.5 * self.axis_window_s))
            ref = np.sum(u[a : max(min(i_ref, b), a + 1)], axis=0)
            ref /= max(np.linalg.norm(ref), 1e-300)
            bad = np.flatnonzero(u[a:b] @ ref < c)
            cut = b if bad.size == 0 else a + max(int(bad[0]), 1)
            out.append((a, cut))
            a = cut
        return out


def segment_windows(
    segments: Iterable[Segment], kinds: Iterable[SegmentKind] | None = None
) -> list[tuple[int, int]]:
    """Half-open windows ``(start_ns, end_ns)`` of the segments of the given kinds.

    Parameters
    ----------
    segments : iterable of Segment
        Output of :class:`SegmentMotion`.
    kinds : iterable of SegmentKind, optional
        Kinds to keep (all when omitted).

    Returns
    -------
    list of (int, int)
        In time order; what ``fit_calibration(..., windows_ns=...)`` accepts.

    """
    keep = None if kinds is None else {SegmentKind(k) for k in kinds}
    return sorted(
        (int(s.start_ns), int(s.end_ns)) for s in segments if keep is None or s.kind in keep
    )


@dataclass(frozen=True)
class Fold:
    """One cross-validation fold: fit on ``train_ns``, evaluate on ``test_ns`` (half-open)."""

    train_ns: tuple[tuple[int, int], ...]
    test_ns: tuple[tuple[int, int], ...]


INFORMATIVE = (SegmentKind.ROTATION, SegmentKind.MANOEUVRE, SegmentKind.TURN)


def folds(
    segments: Iterable[Segment], kinds: Iterable[SegmentKind] = INFORMATIVE
) -> list[Fold]:
    """Leave-one-segment-out folds over the informative segments (rotation, manoeuvre, turn).

    Static stretches and lines carry no attitude change and would make poor held-out sets.
    Fewer than two informative segments give no folds (an empty list).

    Parameters
    ----------
    segments : iterable of Segment
        Output of :class:`SegmentMotion`.
    kinds : iterable of SegmentKind
        Which segments take part.

    Returns
    -------
    list of Fold

    """
    wins = segment_windows(segments, kinds)
    if len(wins) < 2:
        return []
    return [
        Fold(tuple(w for j, w in enumerate(wins) if j != i), (wins[i],)) for i in range(len(wins))
    ]


def segment_table(segments: Iterable[Segment], t0_ns: int = 0) -> str:
    """Plain-text table of segments (seconds from ``t0_ns``), for notes and the CLI."""
    rows = [
        f"{'kind':<10}{'start_s':>9}{'end_s':>9}{'twist':>9}{'axis_body':>24}"
        f"{'rate_cv':>9}{'swing':>8}{'cover':>7}"
    ]
    for s in segments:
        ax = "" if s.axis_body is None else "[" + ", ".join(f"{v:+.2f}" for v in s.axis_body) + "]"
        rows.append(
            f"{s.kind.value:<10}{(s.start_ns - t0_ns) * 1e-9:9.2f}{(s.end_ns - t0_ns) * 1e-9:9.2f}"
            f"{(s.twist_deg or 0.0):9.1f}{ax:>24}{(s.rate_cv or 0.0):9.3f}"
            f"{(s.swing_rms_deg or 0.0):8.2f}{(s.coverage or 0.0):7.2f}"
        )
    return "\n".join(rows)

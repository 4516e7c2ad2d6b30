"""Segment stage: which stretches of a recording are static, lines, turns, rotations, manoeuvres.

More in docs/modules.md, ``stages.segment``.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from pipeline.core.errors import DataQualityError
from pipeline.core.geometry import quat_conj, quat_mul
from pipeline.core.recording import AlignedSeries, Segment, SegmentKind
from pipeline.model.tang import (
    RotationFit,
    TwistSide,
    angular_rate,
    fit_rotation,
    rotation_angle,
    swing_twist,
)
from stages.context import Context

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

# interval labels: gap, quiet (still or steady line), moving; and within a moving run
_GAP, _QUIET, _MOVING = 0, 1, 2
_STABLE, _UNSTABLE = 3, 4


class MotionContext(enum.Enum):
    """What kind of recording it is.

    ``AUTO`` (default) tells lines, turns, rotations, static stretches and manoeuvres apart
    from the motion alone. ``LAB`` never reports lines or turns (a steady stretch is part of a
    manoeuvre, a turn about the vertical a rotation or manoeuvre). ``SURVEY`` also names still
    stretches ``LINE`` (the attitude alone cannot tell a parked vehicle from one driving
    straight).
    """

    AUTO = "auto"
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


def absorb_short_runs(labels: NDArray, dur_s: F64, min_s: float, fixed: int = _GAP) -> NDArray:
    """Relabel runs shorter than ``min_s`` (seconds) with the label of their longer neighbour.

    Shortest first: each pass relabels the runs that are shorter than ``min_s`` and than both
    neighbours (so two neighbours never swap), then equal neighbours fuse and the next pass
    sees the longer runs. Runs labelled ``fixed`` (gaps) never change and never spread; a short
    run with only ``fixed`` neighbours becomes ``fixed`` (dropped).

    Parameters
    ----------
    labels : ndarray of int, shape (M,)
        One label per interval.
    dur_s : ndarray, shape (M,)
        Duration of each interval, s.
    min_s : float
        Shortest run kept.
    fixed : int
        Label that neither absorbs nor is absorbed.

    Returns
    -------
    ndarray of int, shape (M,)

    """
    out = np.asarray(labels).copy()
    if min_s <= 0 or out.size == 0:
        return out
    c = np.concatenate([[0.0], np.cumsum(dur_s)])
    while True:
        s, e = _runs(out)
        lab = out[s]
        dur = c[e] - c[s]
        movable = lab != fixed
        eff = np.where(movable, dur, np.inf)  # a gap never counts as the shorter neighbour
        left = np.concatenate([[np.inf], eff[:-1]])
        right = np.concatenate([eff[1:], [np.inf]])
        flip = movable & (dur < min_s) & (dur < left) & (dur <= right)
        if not np.any(flip):
            return out
        lab_l = np.concatenate([[fixed], lab[:-1]])
        lab_r = np.concatenate([lab[1:], [fixed]])
        dur_l = np.where(lab_l != fixed, np.concatenate([[-1.0], dur[:-1]]), -1.0)
        dur_r = np.where(lab_r != fixed, np.concatenate([dur[1:], [-1.0]]), -1.0)
        new = np.where(dur_l >= dur_r, lab_l, lab_r)
        new = np.where((dur_l < 0) & (dur_r < 0), fixed, new)
        lab = np.where(flip, new, lab)
        out = np.repeat(lab, e - s)


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


def attitude_noise_floor(w_body: F64, w_enu: F64, dt_s: F64) -> tuple[float, float]:
    """White attitude noise per sample (rad): largest body axis, and heading (ENU up).

    With ``n_k`` white attitude noise of standard deviation ``s`` per axis, the rotation
    increments ``d_k = w_k dt_k`` carry ``n_k+1 - n_k`` and their second differences
    ``n_k+2 - 2 n_k+1 + n_k`` have variance ``6 s^2``; smooth motion adds only
    ``(dw/dt) dt^2``. The spread is taken as 1.4826 MAD (robust to fast manoeuvres).

    Parameters
    ----------
    w_body, w_enu : ndarray, shape (M, 3)
        Rates per interval, rad/s (zero across gaps).
    dt_s : ndarray, shape (M,)
        Interval durations, s (zero across gaps).

    Returns
    -------
    sigma_body_rad, sigma_heading_rad : float

    """
    ok = dt_s > 0
    pair = ok[1:] & ok[:-1]
    if np.count_nonzero(pair) < 10:
        return 0.0, 0.0
    db = np.diff(w_body * dt_s[:, None], axis=0)[pair]
    dz = np.diff(w_enu[:, 2] * dt_s)[pair]

    def spread(x: F64) -> F64:
        return 1.4826 * np.median(np.abs(x - np.median(x, axis=0)), axis=0) / np.sqrt(6.0)

    return float(np.max(spread(db))), float(spread(dz))


@dataclass(frozen=True)
class SegmentMotion:
    """Find static stretches, lines, turns, rotation segments and manoeuvres.

    Parameters
    ----------
    min_twist_deg : float
        Smallest net rotation about a stable axis for a ``ROTATION`` segment.
    static_rate_deg_s : float
        Smallest still threshold on the smoothed rate (the noise floor may raise it).
    heading_rate_deg_s : float
        Smallest threshold on the heading rate (about ENU up) of a steady line.
    noise_factor : float
        Thresholds are at least this many times the estimated rate noise floor.
    line_wobble_rate_deg_s : float
        Largest smoothed rate of a steady (line) interval: pitch/roll wobble.
    line_max_tilt_deg : float
        Largest RMS tilt swing (off the ENU vertical) of a ``LINE``.
    min_line_s : float
        Shortest ``LINE``; shorter steady stretches join the neighbouring manoeuvre.
    axis_tol_deg : float
        Largest change of the rotation axis within a rotation segment.
    smooth_s : float
        Width of the moving average applied to the angular rate.
    axis_window_s : float
        Span over which the axis must stay put to count as stable.
    max_gap_s : float
        Attitude intervals longer than this break segments (occlusions, dropouts).
    min_segment_s : float
        Shortest segment (seconds): shorter runs are absorbed by their neighbours.
    context : MotionContext
        ``AUTO`` (default), ``LAB`` or ``SURVEY`` (see :class:`MotionContext`).
    turn_min_deg, turn_max_deg : float
        Heading change of a ``TURN`` (a larger one about the vertical is a rotation).
    turn_vertical_tol_deg : float
        Largest angle of a turn's axis from ENU up.
    turn_max_swing_deg : float
        Largest RMS swing of a turn (a tumbling manoeuvre with a net vertical rotation is no
        turn).

    """

    min_twist_deg: float = 180.0
    static_rate_deg_s: float = 0.6
    heading_rate_deg_s: float = 0.5
    noise_factor: float = 5.0
    line_wobble_rate_deg_s: float = 5.0
    line_max_tilt_deg: float = 10.0
    min_line_s: float = 10.0
    axis_tol_deg: float = 20.0
    smooth_s: float = 0.5
    axis_window_s: float = 1.0
    max_gap_s: float = 0.25
    min_segment_s: float = 3.0
    context: MotionContext = MotionContext.AUTO
    turn_min_deg: float = 20.0
    turn_max_deg: float = 300.0
    turn_vertical_tol_deg: float = 30.0
    turn_max_swing_deg: float = 30.0

    requires: ClassVar[frozenset[str]] = frozenset({"aligned"})
    provides: ClassVar[frozenset[str]] = frozenset({"segments"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` with ``segments`` (tuple of Segment, in time order)."""
        if ctx.aligned is None:
            raise DataQualityError("segmentation needs aligned attitude and magnetometer samples")
        return ctx.replace(segments=self.segment(ctx.aligned))

    # ------------------------------------------------------------------ the work
    def segment(self, aligned: AlignedSeries) -> tuple[Segment, ...]:
        """Segments of one aligned series (docs/modules.md)."""
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
        head = np.abs(wes[:, 2])

        # noise floor of a rate averaged over the smoothing window: (n_end - n_start) / W
        sig_b, sig_h = attitude_noise_floor(wb, we, dt_ok)
        win = max(self.smooth_s, float(np.median(dt_ok[~gap])) if np.any(~gap) else 1.0)
        # (3 axes for the magnitude, sqrt(2) from the two window ends)
        still_thr = max(
            np.radians(self.static_rate_deg_s), self.noise_factor * np.sqrt(6.0) * sig_b / win
        )
        head_thr = max(
            np.radians(self.heading_rate_deg_s), self.noise_factor * np.sqrt(2.0) * sig_h / win
        )
        steady = (head < head_thr) & (rate < np.radians(self.line_wobble_rate_deg_s))
        quiet = (rate < still_thr) | (steady & (self.context is not MotionContext.LAB))
        labels = np.where(gap, _GAP, np.where(quiet, _QUIET, _MOVING))
        labels = absorb_short_runs(labels, dt_ok, self.min_segment_s)

        # pieces: (start interval, end interval exclusive, kind or None for "other moving")
        pieces: list[tuple[int, int, SegmentKind | None]] = []
        starts, ends = _runs(labels)
        for a, b in zip(starts, ends, strict=True):
            a, b = int(a), int(b)
            if labels[a] == _GAP:
                continue
            if labels[a] == _QUIET:
                pieces.append((a, b, self._quiet_kind(q, rate, we, dt_ok, a, b, still_thr)))
            else:
                pieces.extend(self._moving_pieces(t, q, wbs, wes, dt_ok, rate, t_mid, a, b))
        pieces = self._absorb_pieces(pieces, dt_ok)

        mag = np.asarray(aligned.mag_nT, dtype=float)
        out: list[Segment] = []
        for a, b, k in pieces:
            s0, s1 = a, b + 1  # samples a..b (interval b-1 ends at sample b)
            fit = fit_rotation(
                t[s0:s1], q[s0:s1], field_dirs_body=mag[s0:s1], w_body=wbs[a:b], w_enu=wes[a:b]
            )
            if k is None:
                k = SegmentKind.TURN if self._is_turn(fit) else SegmentKind.MANOEUVRE
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

    # ------------------------------------------------------------------ pieces
    def _is_turn(self, fit: RotationFit) -> bool:
        """Tell whether a fitted stretch is a heading change about the vertical (a turn).

        Below a full rotation (``turn_max_deg``) and without tumbling (swing).
        """
        if self.context is MotionContext.LAB:
            return False
        vertical = abs(float(fit.axis_enu[2])) >= np.cos(np.radians(self.turn_vertical_tol_deg))
        return bool(
            vertical
            and self.turn_min_deg <= fit.twist_deg < self.turn_max_deg
            and fit.swing_rms_deg <= self.turn_max_swing_deg
        )

    def _quiet_kind(
        self, q: F64, rate: F64, we: F64, dt: F64, a: int, b: int, still_thr: float
    ) -> SegmentKind | None:
        """Classify a quiet run: STATIC (below the noise), LINE (long, level) or None (slow)."""
        T = float(np.sum(dt[a:b]))
        if T <= 0:
            return None
        rms = np.sqrt(float(np.sum(rate[a:b] ** 2 * dt[a:b])) / T)
        if rms < still_thr:
            return SegmentKind.LINE if self.context is MotionContext.SURVEY else SegmentKind.STATIC
        if self.context is MotionContext.LAB or T < self.min_line_s:
            return None
        heading_change = abs(float(np.degrees(np.sum(we[a:b, 2] * dt[a:b]))))
        # tilt wobble: swing off ENU up of the rotation since the start (evenly thinned)
        qq = q[a : b + 1 : max(1, (b - a) // 5000)]
        sw, _ = swing_twist(quat_mul(qq, quat_conj(qq[:1])), [0.0, 0.0, 1.0], TwistSide.LEFT)
        tilt_rms = float(np.degrees(np.sqrt(np.mean(rotation_angle(sw) ** 2))))
        if heading_change < self.turn_min_deg and tilt_rms <= self.line_max_tilt_deg:
            return SegmentKind.LINE
        return None

    def _moving_pieces(
        self,
        t: I64,
        q: F64,
        wbs: F64,
        wes: F64,
        dt: F64,
        rate: F64,
        t_mid: F64,
        a: int,
        b: int,
    ) -> list[tuple[int, int, SegmentKind | None]]:
        """Split a moving run into rotations about stable axes and other motion."""
        fit = fit_rotation(t[a : b + 1], q[a : b + 1], w_body=wbs[a:b], w_enu=wes[a:b])
        if self._is_turn(fit):
            return [(a, b, SegmentKind.TURN)]
        u = wbs[a:b] / np.where(rate[a:b] > 0, rate[a:b], 1.0)[:, None]
        tm = t_mid[a:b]
        h = 0.5 * self.axis_window_s
        i_prev = np.searchsorted(tm, tm - h, side="left")
        i_next = np.clip(np.searchsorted(tm, tm + h, side="right") - 1, 0, len(tm) - 1)
        c = np.cos(np.radians(self.axis_tol_deg))
        ok = (np.sum(u * u[i_prev], axis=1) > c) & (np.sum(u * u[i_next], axis=1) > c)
        lab = np.where(ok, _STABLE, _UNSTABLE)
        # short flickers of either label do not make or break a rotation
        lab = absorb_short_runs(lab, dt[a:b], min(self.axis_window_s, self.min_segment_s))
        out: list[tuple[int, int, SegmentKind | None]] = []
        s, e = _runs(lab)
        for a1, b1 in zip(s + a, e + a, strict=True):
            a1, b1 = int(a1), int(b1)
            if lab[a1 - a] == _UNSTABLE:
                out.append((a1, b1, None))
                continue
            for a2, b2 in self._split_axis(u, a1 - a, b1 - a, tm):
                a2, b2 = a2 + a, b2 + a
                ax = self._axis(wbs, dt, a2, b2)
                twist = np.degrees(abs(float(np.sum((wbs[a2:b2] @ ax) * dt[a2:b2]))))
                out.append((a2, b2, SegmentKind.ROTATION if twist >= self.min_twist_deg else None))
        return out

    def _absorb_pieces(
        self, pieces: list[tuple[int, int, SegmentKind | None]], dt: F64
    ) -> list[tuple[int, int, SegmentKind | None]]:
        """Fuse neighbouring "other" pieces, then absorb short pieces into the longer neighbour.

        Neighbours must touch (no gap between); a rotation absorbing a short piece stays a
        rotation (its axis is refitted over the longer window), two rotations never fuse.
        """
        c = np.concatenate([[0.0], np.cumsum(dt)])
        ps: list[list[Any]] = [list(p) for p in pieces]

        def fuse(ps: list[list]) -> list[list]:
            out: list[list] = []
            for p in ps:
                if (
                    out
                    and out[-1][1] == p[0]
                    and out[-1][2] is p[2]
                    and p[2] is not SegmentKind.ROTATION
                ):
                    out[-1][1] = p[1]
                else:
                    out.append(p)
            return out

        ps = fuse(ps)
        while True:
            dur = [c[p[1]] - c[p[0]] for p in ps]
            short = [i for i, d in enumerate(dur) if d < self.min_segment_s]
            if not short:
                break
            i = min(short, key=lambda j: dur[j])
            left = i - 1 if i > 0 and ps[i - 1][1] == ps[i][0] else None
            right = i + 1 if i + 1 < len(ps) and ps[i + 1][0] == ps[i][1] else None
            if left is None and right is None:
                del ps[i]  # isolated between gaps: too short to describe
                continue
            j = left if right is None or (left is not None and dur[left] >= dur[right]) else right
            assert j is not None  # left and right are not both None
            lo, hi = min(ps[i][0], ps[j][0]), max(ps[i][1], ps[j][1])
            ps[j] = [lo, hi, ps[j][2]]
            del ps[i]
            ps = fuse(ps)
        return [(int(a), int(b), k) for a, b, k in ps]

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

"""Figures (PNG, matplotlib Agg) and a self-contained ``report.html`` per recording.

More in docs/modules.md, ``stages.report``.
"""

from __future__ import annotations

import base64
import datetime as dt
import html
import os
import shlex
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import package_version
from pipeline.core import style
from pipeline.core.atomic import atomic_path, sha256_file, write_text_atomic
from pipeline.core.geometry import quat_rotate, quat_to_li2020_euler
from pipeline.core.recording import Recording, Segment, VectorSeries
from pipeline.core.style import minus, unsigned_zeros
from pipeline.core.verdict import plain_words, verdict_line
from pipeline.core.words import pm_vec
from pipeline.model.sample_hold import repeated
from stages.estimate import POOR_AXIS_SIGMA_DEG
from stages.estimators.registry import DESCRIPTIONS
from stages.report_grid import survey_html
from stages.report_map import (
    EVENT_EFFECTS,
    draw_map,
    event_windows,
    map_data,
    sources,
    write_map_json,
)
from stages.report_text import rows as finding_rows
from stages.report_text import rows_html, utc
from stages.restore import RestoreResult, RestoreTotals, restore_samples, view_data

ENU_LABELS = ("east", "north", "up")


def _plt():
    return style.pyplot()


def _png(fig: Any) -> bytes:
    return style.png(fig)


def utc_text(t_ns: int, with_date: bool = False) -> str:
    """Return the UTC time of ``t_ns`` (ns since the epoch), ``HH:MM:SS[.s]`` (with the date)."""
    sec, frac = divmod(int(t_ns), 1_000_000_000)
    d = dt.datetime.fromtimestamp(sec, tz=dt.timezone.utc)
    text = d.strftime("%Y-%m-%d %H:%M:%S" if with_date else "%H:%M:%S")
    tenth = frac // 100_000_000
    return f"{text}.{tenth}" if tenth else text


def _time_scale(duration_s: float) -> tuple[float, str]:
    """Divisor and unit for a time axis: seconds, minutes beyond 15 min, hours beyond 3 h."""
    if duration_s > 3 * 3600:
        return 3600.0, "h"
    if duration_s > 900:
        return 60.0, "min"
    return 1.0, "s"


def _time_label(t0_ns: int, unit: str) -> str:
    return f"time from {utc_text(t0_ns)} UTC ({unit})"


def _shade(ax: Any, segments: tuple[Segment, ...] | None, t0_ns: int, scale: float = 1.0
           ) -> dict[str, Any]:
    """Shade the segments by kind; return kind -> patch for a key."""
    from matplotlib.collections import PolyCollection
    from matplotlib.patches import Patch

    handles: dict[str, Any] = {}
    spans: dict[str, list] = {}
    for s in segments or ():
        kind = str(getattr(s.kind, "value", s.kind))
        a, b = (s.start_ns - t0_ns) * 1e-9 / scale, (s.end_ns - t0_ns) * 1e-9 / scale
        spans.setdefault(kind, []).append([(a, 0.0), (b, 0.0), (b, 1.0), (a, 1.0)])
    # one collection per kind (an axvspan per segment drew hundreds of patches per axis on
    # hours of data); x in data units, y across the axes
    for kind, polys in spans.items():
        colour = style.segment_colour(kind)
        ax.add_collection(PolyCollection(polys, facecolors=colour, edgecolors="none",
                                         linewidths=0, zorder=0,
                                         transform=ax.get_xaxis_transform()),
                          autolim=False)
        handles.setdefault(kind, Patch(color=colour, label=f"{kind} segment"))
    return handles


def _segment_key(fig: Any, handles: dict[str, Any]) -> float:
    """Add a key for the segment shading at the bottom left; return its height (figure units)."""
    if not handles:
        return 0.0
    fig.legend(handles=list(handles.values()), loc="lower left", ncol=len(handles),
               frameon=False, bbox_to_anchor=(0.01, 0.0), title=None)
    return 0.32 / fig.get_figheight()


def _decimate(n: int, max_points: int) -> np.ndarray:
    return np.arange(0, n, max(1, int(np.ceil(n / max_points))))


def bins(t: np.ndarray, v: np.ndarray, max_bins: int
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Bin a series into at most ``max_bins`` consecutive bins of equal sample count.

    Returns
    -------
    t_mid, lo, hi, mean : ndarray
        Mean time, minimum, maximum and mean of each bin (NaN samples ignored; a bin with
        none is NaN).
    k : int
        Samples per bin (1: the series as it is).

    """
    n = len(t)
    k = max(1, int(np.ceil(n / max(1, max_bins))))
    if k == 1:
        return t.astype(float), v, v, v, 1
    m = -(-n // k) * k
    tp: np.ndarray = np.full(m, np.nan)
    tp[:n] = t
    vp: np.ndarray = np.full(m, np.nan)
    vp[:n] = v
    tp, vp = tp.reshape(-1, k), vp.reshape(-1, k)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # bins without any valid sample
        return (np.nanmean(tp, axis=1), np.nanmin(vp, axis=1), np.nanmax(vp, axis=1),
                np.nanmean(vp, axis=1), k)


def band(ax: Any, t: np.ndarray, v: np.ndarray, colour: str, label: str, *,
         max_bins: int = 1500, alpha: float = 0.3, lw: float = 1.2) -> tuple[Any, int]:
    """Draw a long series as its min-max band per bin and the bin means as a line.

    At 285 Hz over hours a line of every sample is a solid block; the band keeps the full
    range (the noise) visible and the line the signal. A short series is drawn as it is.

    Returns
    -------
    handle : matplotlib artist or tuple of them
        For a legend entry (band and line together).
    k : int
        Samples per bin (1: every sample drawn).

    """
    tm, lo, hi, mean, k = bins(t, v, max_bins)
    if k == 1:
        (line,) = ax.plot(t, v, color=colour, lw=lw, label=label)
        return line, 1
    patch = ax.fill_between(tm, lo, hi, color=colour, alpha=alpha, lw=0)
    (line,) = ax.plot(tm, mean, color=colour, lw=lw)
    return (patch, line), k


def _legend(fig: Any, entries: list[tuple[Any, str]], k: int, **kw: Any) -> None:
    """One legend under the figure; a band and its line share an entry."""
    from matplotlib.legend_handler import HandlerTuple

    title = None if k <= 1 else f"lines: mean of {k} samples; bands: their min to max"
    fig.legend([h for h, _ in entries], [lab for _, lab in entries], frameon=False,
               handler_map={tuple: HandlerTuple(ndivide=None, pad=0)}, title=title,
               title_fontsize=10, alignment="left", **kw)


def _finite_range(*arrays: np.ndarray) -> float:
    vals = [a[np.isfinite(a)] for a in arrays]
    vals = [a for a in vals if a.size]
    if not vals:
        return 0.0
    allv = np.concatenate(vals)
    return float(np.percentile(allv, 99.5) - np.percentile(allv, 0.5))


def needs_own_scale(before: np.ndarray, after: np.ndarray) -> bool:
    """Whether "after" needs a panel at its own scale: "before" spans over 3 times more.

    Otherwise the second panel would repeat the first and is left out.
    """
    return _finite_range(before) > 3 * max(_finite_range(after), 1e-9)


def residual_figure_data(vd: Any) -> tuple[np.ndarray, np.ndarray]:
    """Return the arrays the residual figure is drawn from: time (s) and residual (nT, mag frame).

    Parameters
    ----------
    vd : ViewData
        :func:`stages.restore.view_data` of the context's restore result.

    Returns
    -------
    t_s : ndarray (M,)
        Seconds from the first magnetometer sample, samples with a usable attitude only.
    residual_nT : ndarray (M, 3)
        Measured minus predicted by the final model (every diagnosed effect included): the
        same numbers as the ``<mag>/residual`` channel of the corrected MCAP.

    """
    v = np.asarray(vd.valid, dtype=bool)
    return np.asarray(vd.t_s)[v], np.asarray(vd.residual_nT)[v]


def make_figures(
    recording: Recording,
    calibration: Any,
    segments: tuple[Segment, ...] | None = None,
    *,
    max_gap_s: float | None = None,
    dpi: int = 100,
    max_points: int = 1500,
    restored: Any = None,
    diagnosis: Any = None,
) -> dict[str, bytes]:
    """Render the report's figures.

    Parameters
    ----------
    recording : Recording
        With ``attitude`` filled.
    calibration : Calibration
        The model to restore with.
    segments : tuple of Segment, optional
        Shaded in the time plots (a key names their kinds).
    max_gap_s : float or None
        Attitude gap bridged by interpolation.
    dpi : int
        Resolution of the PNGs (the report shows them at about their size in inches).
    max_points : int
        Most bins per time series: a longer series is drawn as a min-max band per bin (the
        plotted range is the true fluctuation range) and the bin means as a line.
    restored : RestoreResult, optional
        ``ctx.restored``; computed when not given.
    diagnosis : Diagnosis or dict, optional
        Its event windows (disturbance, hard-iron step, local source) are shaded in the time
        plots and marked on the map.

    Returns
    -------
    dict of str to bytes
        File name (``fig_*.png``) -> PNG bytes: ``fig_enu.png``, ``fig_residual.png``,
        ``fig_sphere.png``, ``fig_attitude.png``, and ``fig_map.png`` when the recording has
        positions.

    """
    plt = _plt()
    if restored is None:
        restored = restore_samples(recording, calibration, max_gap_s=max_gap_s)
    vd = view_data(restored, calibration.R_body_mag)
    t0 = int(vd.t_ns[0]) if len(vd.t_ns) else 0
    scale, unit = _time_scale(float(vd.t_s[-1]) if len(vd.t_s) else 0.0)
    ts = vd.t_s / scale
    out: dict[str, bytes] = {}
    events = [(a / scale, b / scale, e) for a, b, e in
              event_windows(diagnosis, float(vd.t_s[-1]) if len(vd.t_s) else None)]
    shade = Shading(segments, t0, scale, events)
    pred = predicted_field(restored, calibration)
    with plt.rc_context(style.rc() | {"savefig.dpi": dpi, "figure.dpi": dpi}):
        out["fig_enu.png"] = _fig_enu(plt, vd, ts, t0, unit, shade, max_points, pred)
        out["fig_residual.png"] = _fig_residual(plt, vd, ts, t0, scale, unit, shade,
                                                max_points, quat_to_li2020_euler)
        out["fig_sphere.png"] = _fig_sphere(plt, vd, calibration)
        out["fig_attitude.png"] = _fig_attitude(plt, vd, ts, t0, unit, shade,
                                                max_points, quat_to_li2020_euler)
    md = report_map_data(recording, restored, calibration, diagnosis)
    if md is not None:
        out["fig_map.png"] = draw_map(md, dpi=dpi)
    return out


def predicted_field(restored: Any, calibration: Any) -> tuple[np.ndarray, np.ndarray]:
    """Return the field the fitted model predicts at each sample: ENU (N, 3) and |B| (N,).

    The background field plus every diagnosed field term (gradient, map, local sources,
    drift, disturbances) where and when the sensor was: ``B_enu + F(t)`` of
    :mod:`pipeline.model.forward` (M1). It follows from the restore result without
    evaluating the model again: the reading is ``y = D R.T C.T (B + F) + sensor + r``, so
    ``inv(D) (y - sensor) - inv(D) r`` is the prediction in the mag frame (its norm is
    ``|B + F|`` exactly) and turned by the attitude it is the ENU prediction (up to the
    heading-drift turn of the residual, far below a nanotesla). NaN without an attitude.
    """
    r = np.asarray(restored.residual_nT, dtype=float)
    D = getattr(calibration, "D", None)
    dr = r if D is None else np.linalg.solve(np.asarray(D, float), r.T).T
    m_pred = np.asarray(restored.calibrated_mag_nT, dtype=float) - dr
    norm = np.linalg.norm(m_pred, axis=1)
    enu = np.asarray(restored.enu_nT, dtype=float) - quat_rotate(
        restored.q_or_identity(), dr @ np.asarray(calibration.R_body_mag, float).T)
    bad = ~np.asarray(restored.valid, dtype=bool)
    norm[bad] = np.nan
    enu[bad] = np.nan
    return enu, norm


def report_map_data(recording: Recording, restored: Any, calibration: Any,
                    diagnosis: Any = None) -> dict[str, Any] | None:
    """Return the plan view's numbers (:func:`stages.report_map.map_data`) or None."""
    pos = getattr(recording, "position", None)
    if pos is None or not len(pos) or restored is None or not len(restored.t_ns):
        return None
    t = np.asarray(restored.t_ns, dtype=np.int64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        field = np.linalg.norm(np.asarray(restored.enu_nT, dtype=float), axis=1)
    _, model = predicted_field(restored, calibration)
    t0 = int(recording.mag.t_ns[0]) if len(recording.mag.t_ns) else int(t[0])
    return map_data(t, pos.at(t), field, model, frame=str(getattr(pos.frame, "value", pos.frame)),
                    t0_ns=t0, diagnosis=diagnosis, origin=pos.origin)


@dataclass(frozen=True)
class Shading:
    """What the time plots shade: motion segments by kind and the diagnosed events.

    ``events``: ``(start, end, effect)`` in the plot's time unit.
    """

    segments: tuple[Segment, ...] | None
    t0_ns: int
    scale: float
    events: list[tuple[float, float, str]]

    def draw(self, ax: Any) -> dict[str, Any]:
        """Shade ``ax``; return label -> patch for the key."""
        from matplotlib.patches import Patch

        keys = _shade(ax, self.segments, self.t0_ns, self.scale)
        for a, b, _ in self.events:
            ax.axvspan(a, b, facecolor=style.EVENT, alpha=0.55, edgecolor=style.EVENT_EDGE,
                       lw=1.0, zorder=0.5)
        if self.events:
            kinds = sorted({e.replace("_", " ") for _, _, e in self.events})
            keys["event"] = Patch(facecolor=style.EVENT, alpha=0.55, edgecolor=style.EVENT_EDGE,
                                  label="diagnosed event (" + ", ".join(kinds) + ")")
        return keys


def _fit_left(fig: Any, pad: float = 0.006) -> None:
    """Move the axes right until every y label and tick label is inside the figure.

    A fixed left margin cut the label of a residual of five-digit nT off; the room needed is
    measured on the figure's layout instead. The tight boxes lay out the ticks and labels
    themselves: drawing the figure first, as this once did, rasterised every figure twice
    (a third of a small recording's ``process``) for the same boxes. Only the axes of the
    leftmost column are laid out: the labels of the others lie over the column to their
    left, inside the figure, and each tight box lays out its axes' ticks anew.
    """
    renderer = fig.canvas.get_renderer()
    inv = fig.transFigure.inverted()
    shown = [ax for ax in fig.axes if ax.get_visible()]
    first = min(ax.get_position().x0 for ax in shown)
    x0 = min(inv.transform(ax.get_tightbbox(renderer).p0)[0] for ax in shown
             if ax.get_position().x0 <= first + 1e-6)
    if x0 < pad:
        left = fig.subplotpars.left + (pad - x0)
        fig.subplots_adjust(left=min(left, 0.3))


def _clip_to(ax: Any, t: np.ndarray, v: np.ndarray, colour: str) -> tuple[float, float, int]:
    """Limit ``ax`` to where nearly all of ``v`` lies; mark what lies beyond at the edges.

    The limits hold the 0.5 to 99.5 percentiles with a margin, so that a few spikes do not
    make a "closer scale" panel as wide as the first; every sample beyond them is drawn as a
    triangle on the edge it would cross. Returns the limits and how many samples are beyond.
    """
    ok = np.isfinite(v)
    if not np.any(ok):
        return 0.0, 1.0, 0
    lo, hi = np.percentile(v[ok], [0.5, 99.5])
    pad = 0.15 * max(hi - lo, 1e-9)
    lo, hi = float(lo - pad), float(hi + pad)
    above = ok & (v > hi)
    below = ok & (v < lo)
    for m, y, mk in ((above, hi, "^"), (below, lo, "v")):
        if np.any(m):
            tt = t[m]
            if len(tt) > 400:  # one marker per distinct place on the axis is enough
                tt = np.unique(np.round(tt, 2))
            ax.plot(tt, np.full(len(tt), y), mk, color=colour, ms=6, clip_on=False,
                    zorder=5)
    ax.set_ylim(lo, hi)
    return lo, hi, int(np.count_nonzero(above | below))


def _enu_series(vd: Any) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Return the rows of the ENU figure: (name, before, after) for east, north, up and |B|."""
    unc, cal = vd.uncalibrated_enu_nT, vd.calibrated_enu_nT
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mag_before = np.linalg.norm(vd.raw_mag_nT, axis=1)
        mag_before = np.where(np.isfinite(unc).all(axis=1), mag_before, np.nan)
        mag_after = np.linalg.norm(cal, axis=1)
    rows = [(name, unc[:, k], cal[:, k]) for k, name in enumerate(ENU_LABELS)]
    rows.append(("|B|", mag_before, mag_after))
    return rows


def closer_scale_rows(vd: Any) -> list[bool]:
    """Return, per row of the ENU figure, whether "after" gets a panel at a closer scale.

    Where "before" spans far more (:func:`needs_own_scale`); elsewhere the panel would repeat
    the first. The report's caption speaks of the closer scale only when one is drawn.
    """
    return [needs_own_scale(b, a) for _, b, a in _enu_series(vd)]


def _fig_enu(plt: Any, vd: Any, ts: np.ndarray, t0: int, unit: str, shade: Shading,
             max_points: int, pred: tuple[np.ndarray, np.ndarray]) -> bytes:
    """Li 2020 Figs. 5 and 8: east, north, up and |B|, before and after calibration.

    Beside them the field the fitted model predicts where and when the sensor was (the
    background field plus the diagnosed field terms): a step in "after" that the prediction
    follows is the field in space or a disturbance, not a calibration error. A second column
    shows "after" at its own scale only when "before" spans far more (the calibrated series
    would otherwise be a flat line); its scale holds nearly every sample and the few beyond
    it are marked on its edges.
    """
    pred_enu, pred_norm = pred
    series = _enu_series(vd)
    rows = [(f"{name} (nT)", b, a, m) for (name, b, a), m in
            zip(series, [pred_enu[:, 0], pred_enu[:, 1], pred_enu[:, 2], pred_norm],
                strict=True)]
    own_rows = closer_scale_rows(vd)
    own = any(own_rows)
    fig, axes = plt.subplots(4, 2 if own else 1, figsize=(12, 10), sharex=True, squeeze=False,
                             gridspec_kw={"width_ratios": [3, 2] if own else [1]})
    keys: dict[str, Any] = {}
    entries: list[tuple[Any, str]] = []
    k_bin = 1
    n_clipped = 0
    for k, (ylabel, before, after, model) in enumerate(rows):
        a = axes[k, 0]
        keys.update(shade.draw(a))
        # "before" broader underneath: where both agree (|B| without offsets) both show
        hb, k_bin = band(a, ts, before, style.BEFORE, "before", max_bins=max_points, lw=2.4)
        ha, _ = band(a, ts, after, style.AFTER, "after", max_bins=max_points)
        hm = _model_line(a, ts, model, max_points)
        a.set_ylabel(ylabel)
        if k == 0:
            entries = [(hb, "before calibration (attitude only)"), (ha, "after calibration"),
                       (hm, "field the model predicts there and then")]
        if own:
            b = axes[k, 1]
            if own_rows[k]:
                shade.draw(b)
                band(b, ts, after, style.AFTER, "after", max_bins=max_points)
                _model_line(b, ts, model, max_points)
                n_clipped += _clip_to(b, ts, after, style.AFTER)[2]
            else:
                b.set_visible(False)
    axes[0, 0].set_title("field in ENU and its magnitude |B|, before and after calibration")
    if own:
        first = own_rows.index(True)
        axes[first, 1].set_title("after calibration alone, closer scale")
        last = max(i for i, o in enumerate(own_rows) if o)
        axes[last, 1].xaxis.set_tick_params(labelbottom=True)
        axes[last, 1].set_xlabel(_time_label(t0, unit))
    if n_clipped:
        from matplotlib.lines import Line2D

        entries.append((Line2D([], [], ls="none", marker="^", color=style.AFTER, ms=6),
                        "beyond the closer scale (spikes)"))
    axes[-1, 0].set_xlabel(_time_label(t0, unit))
    y = _segment_key(fig, keys)
    _legend(fig, entries, k_bin, loc="lower left", ncol=4 if n_clipped else 3,
            bbox_to_anchor=(0.01, y))
    fig.subplots_adjust(left=0.08, right=0.99, bottom=0.12 + y, top=0.96, wspace=0.2,
                        hspace=0.12)
    _fit_left(fig)
    return _png(fig)


def _model_line(ax: Any, ts: np.ndarray, model: np.ndarray, max_points: int) -> Any:
    """Draw the model's prediction: black dashed (the bin means of a long series)."""
    tm, _, _, mean, _ = bins(ts, model, max_points)
    (line,) = ax.plot(tm, mean, color=style.REFERENCE, lw=1.6, ls="--", zorder=4)
    return line


def _fig_residual(plt: Any, vd: Any, ts: np.ndarray, t0: int, scale: float, unit: str,
                  shade: Shading, max_points: int, euler: Any) -> bytes:
    """Residual per mag axis against time (bands) and against heading (mean and spread)."""
    fig, (ax, axh) = plt.subplots(1, 2, figsize=(12, 4.6),
                                  gridspec_kw={"width_ratios": [3, 2]})
    keys = shade.draw(ax)
    # drawn from residual_figure_data: the numbers of the <mag>/residual channel
    t_res_s, r_res = residual_figure_data(vd)
    r = vd.residual_nT
    entries = []
    k_bin = 1
    for k, c in enumerate("xyz"):
        hk, k_bin = band(ax, t_res_s / scale, r_res[:, k], style.AXIS[k], c,
                         max_bins=max_points, alpha=0.2)
        entries.append((hk, f"mag {c}"))
    ax.set_xlabel(_time_label(t0, unit))
    ax.set_ylabel("residual, mag frame (nT)")
    ax.set_title("measured minus predicted by the fitted model")
    v = vd.valid & np.isfinite(r).all(axis=1)
    if np.count_nonzero(v) > 10:
        h = np.degrees(euler(vd.q_enu_body[v])[0])
        edges = np.linspace(-180, 180, 37)
        idx = np.clip(np.digitize(h, edges) - 1, 0, 35)
        mid = 0.5 * (edges[:-1] + edges[1:])
        cnt = np.bincount(idx, minlength=36)
        has = cnt > 0
        for k, c in enumerate("xyz"):
            x = r[v, k]
            s1 = np.bincount(idx, x, minlength=36)
            s2 = np.bincount(idx, x * x, minlength=36)
            mean = np.where(has, s1 / np.maximum(cnt, 1), np.nan)
            sd = np.sqrt(np.maximum(np.where(has, s2 / np.maximum(cnt, 1), np.nan) - mean**2,
                                    0))
            axh.fill_between(mid, mean - sd, mean + sd, color=style.AXIS[k], alpha=0.2, lw=0)
            axh.plot(mid, mean, "o-", ms=3, color=style.AXIS[k], lw=1.2, label=c)
        axh.set_xlim(-180, 180)
        axh.set_xticks(np.arange(-180, 181, 90))
    axh.set_xlabel("heading (deg)")
    axh.set_ylabel("residual (nT)")
    axh.set_title("against heading: mean and \u00b11 sd per 10\u00b0")
    y = _segment_key(fig, keys)
    _legend(fig, entries, k_bin, loc="lower left", ncol=3, bbox_to_anchor=(0.01, y))
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.25 + y, top=0.92, wspace=0.25)
    _fit_left(fig)
    return _png(fig)


def sphere_histogram_range_nT(d_raw_nT: np.ndarray, d_cor_nT: np.ndarray
                              ) -> tuple[float, float]:
    """Return the one range both distance-from-the-sphere histograms are drawn on, nT.

    The raw and the corrected histograms share it so that what the calibration changes
    shows: each at its own scale they looked alike. It holds the 0.5 to 99.5 percentiles of
    the corrected series, the middle half of the raw one, and zero (the sphere itself), with
    a margin. Raw readings far off the sphere (a magnet near the sensor for a while) would
    otherwise stretch the range until every histogram is one bar; they are counted in the
    edge bins and their share (from 2 %) is written in the panel's title.

    Parameters
    ----------
    d_raw_nT, d_cor_nT : ndarray
        |reading| minus |B| of the raw and the corrected readings, nT.

    Returns
    -------
    lo_nT, hi_nT : float

    """
    lo, hi = 0.0, 0.0
    for d, q in ((np.asarray(d_raw_nT, float), (25.0, 75.0)),
                 (np.asarray(d_cor_nT, float), (0.5, 99.5))):
        d = d[np.isfinite(d)]
        if d.size:
            a, b = np.percentile(d, q)
            lo, hi = min(lo, float(a)), max(hi, float(b))
    pad = 0.05 * max(hi - lo, 1e-3)
    return lo - pad, hi + pad


def _fig_sphere(plt: Any, vd: Any, calibration: Any, max_points: int = 3000) -> bytes:
    """Plot the readings in the mag frame, raw and corrected, in three projections.

    Rotated through all attitudes a perfect sensor's readings lie on a sphere of radius
    |B| about the origin; hard iron moves the centre, soft iron makes it an ellipsoid.
    Equal axes, so that a sphere looks round; in microtesla, so that the tick labels stay
    short. The distance from the sphere is a histogram per series; the two
    histograms share one range (:func:`sphere_histogram_range_nT`), so that what the
    calibration changes shows.
    """
    raw = np.asarray(vd.raw_mag_nT, dtype=float) * 1e-3
    # the corrected reading in the mag frame: body_after = R_body_mag @ corrected
    corr = np.asarray(vd.body_after_nT, dtype=float) @ np.asarray(calibration.R_body_mag) * 1e-3
    good = np.isfinite(raw).all(axis=1) & np.isfinite(corr).all(axis=1)
    sel = np.flatnonzero(good)[_decimate(int(np.count_nonzero(good)), max_points)]
    radius = float(np.linalg.norm(vd.B_enu_nT)) * 1e-3
    fig = plt.figure(figsize=(12, 4.6))
    gs = fig.add_gridspec(2, 4, width_ratios=[1, 1, 1, 1.15], hspace=0.9, wspace=0.45)
    axes = [fig.add_subplot(gs[:, i]) for i in range(3)]
    th = np.linspace(0, 2 * np.pi, 361)
    for ax, (i, j) in zip(axes, ((0, 1), (0, 2), (1, 2)), strict=True):
        ax.plot(raw[sel, i], raw[sel, j], ".", ms=5, color=style.BEFORE, alpha=0.4,
                label="raw reading")
        ax.plot(corr[sel, i], corr[sel, j], ".", ms=1.5, color=style.AFTER, alpha=0.6,
                label="corrected (model's offset and soft iron removed)")
        ax.plot(radius * np.cos(th), radius * np.sin(th), "--", color=style.REFERENCE, lw=1,
                label=f"|B| = {1e3 * radius:,.0f} nT".replace(",", "\u2009"))
        ax.plot([0], [0], "+", color=style.REFERENCE, ms=10)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{'xyz'[i]} (\u00b5T)")
        ax.set_ylabel(f"{'xyz'[j]} (\u00b5T)")
        ax.set_title(f"{'xyz'[i]}{'xyz'[j]} plane")
        ax.xaxis.set_major_locator(plt.MaxNLocator(5))
        ax.yaxis.set_major_locator(plt.MaxNLocator(5))
    # distance from the sphere: what an offset of a few hundred nT does, invisible above
    d_raw = np.linalg.norm(raw[good], axis=1) * 1e3 - 1e3 * radius
    d_cor = np.linalg.norm(corr[good], axis=1) * 1e3 - 1e3 * radius
    lo_nT, hi_nT = sphere_histogram_range_nT(d_raw, d_cor)
    edges = np.linspace(lo_nT, hi_nT, 61)
    for row, (d, colour, name) in enumerate(((d_raw, style.BEFORE, "raw"),
                                             (d_cor, style.AFTER, "corrected"))):
        ax = fig.add_subplot(gs[row, 3])
        beyond = 0.0
        if d.size:
            ax.hist(np.clip(d, lo_nT, hi_nT), bins=edges, color=colour,
                    alpha=0.7 if row == 0 else 0.9)
            beyond = float(np.mean((d < lo_nT) | (d > hi_nT)))
        ax.set_xlim(lo_nT, hi_nT)
        ax.axvline(0, color=style.REFERENCE, ls="--", lw=1)
        # in the title, not over the bars: the share counted in the edge bars
        note = f"\n{100 * beyond:.0f} % off scale (edge bars)" if beyond >= 0.02 else ""
        ax.set_title(f"{name}: |reading| \u2212 |B|{note}", fontsize=10 if note else 11)
        ax.set_xlabel("nT")
        ax.set_ylabel("samples")
        ax.xaxis.set_major_locator(plt.MaxNLocator(4))
        ax.yaxis.set_major_locator(plt.MaxNLocator(3))
    h, lab = axes[0].get_legend_handles_labels()
    fig.legend(h, lab, loc="lower center", ncol=3, frameon=False, markerscale=4)
    fig.suptitle("readings in the magnetometer frame: a sphere of radius |B| about the origin "
                 "when the sensor is calibrated", fontsize=12)
    fig.subplots_adjust(left=0.07, right=0.99, bottom=0.2, top=0.86)
    _fit_left(fig)
    return _png(fig)


def _fig_attitude(plt: Any, vd: Any, ts: np.ndarray, t0: int, unit: str, shade: Shading,
                  max_points: int, euler: Any) -> bytes:
    """Heading, pitch and roll (Li 2020 Euler angles) with the segments shaded."""
    fig, ax = plt.subplots(figsize=(12, 4.2))
    keys = shade.draw(ax)
    sel = _decimate(len(vd.t_s), 6 * max_points)
    v = vd.valid[sel]
    h, p, r = euler(vd.q_enu_body[sel])
    for ang, name in ((h, "heading"), (p, "pitch"), (r, "roll")):
        ax.plot(ts[sel][v], np.degrees(ang[v]), ".", ms=1.5, color=style.ANGLE[name],
                label=name)
    ax.set_xlabel(_time_label(t0, unit))
    ax.set_ylabel("angle (deg)")
    ax.set_yticks(np.arange(-180, 181, 90))
    ax.set_title("attitude (Li 2020 Euler angles) and motion segments")
    h_, lab = ax.get_legend_handles_labels()
    y = _segment_key(fig, keys)
    fig.legend(h_, lab, loc="lower left", ncol=3, frameon=False, markerscale=8,
               bbox_to_anchor=(0.01, y))
    fig.subplots_adjust(left=0.07, right=0.99, bottom=0.2 + y, top=0.92)
    _fit_left(fig)
    return _png(fig)


def _fmt(x: Any, nd: int = 3) -> str:
    if x is None:
        return "&ndash;"
    if isinstance(x, float | np.floating):
        return "&infin;" if not np.isfinite(x) else minus(f"{x:.{nd}f}")
    return html.escape(str(x))


def _vec(a: Any, nd: int = 3) -> str:
    if a is None:
        return "&ndash;"
    return "[" + ", ".join(_fmt(float(x), nd) for x in np.asarray(a, dtype=float).ravel()) + "]"


def _img(data: bytes, alt: str, key: str = "") -> str:
    """Return a figure that zooms to its full resolution when clicked (CSS only, works offline)."""
    b64 = base64.b64encode(data).decode("ascii")
    key = html.escape(key or alt.replace(".", "-").replace(" ", "-"))
    return (f'<figure><input type=checkbox class=zoom id="zoom-{key}">'
            f'<label for="zoom-{key}" title="click to zoom in or out">'
            f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{b64}"></label>'
            "</figure>")


def _n(x: int) -> str:
    """Return an integer with thin spaces between thousands (53 240)."""
    return f"{int(x):,}".replace(",", "\u2009")


def counts_sentence(restored: RestoreResult, calibration: Any,
                    totals: RestoreTotals | None = None) -> str:
    """Where every magnetometer sample went, in one sentence whose counts add up.

    Received = without a usable attitude + restored; restored = sample-and-hold repeats +
    new readings (when the sensor repeats its readings); then what uses which: the metrics
    and the residual every restored sample (the before/after comparison those that also have
    an attitude at their own stamp), the fit the new readings outside excluded windows.
    ``totals``: the counts of every sample when ``restored`` holds only some rows of them.
    """
    totals = totals if totals is not None else RestoreTotals.of(restored)
    total = int(totals.n_total)
    n_valid = int(totals.n_valid)
    n_without = total - n_valid
    n_stamp = int(totals.n_valid - totals.n_used)
    checks = getattr(calibration, "checks", None) or {}
    fs = checks.get("fit_samples") if isinstance(checks.get("fit_samples"), dict) else None
    held = getattr(calibration, "sample_hold", None)
    parts = [f"Of {_n(total)} magnetometer samples received, {_n(n_without)} "
             f"{_have(n_without)} no usable attitude and {_n(n_valid)} are restored"]
    n_rep: int | None = None
    if held:
        if totals.n_total != len(restored.t_ns):
            frac = float(held.get("repeated_fraction") or 0.0)
            n_rep = round(frac * n_valid)
            parts.append(f"; about {_n(n_rep)} of these ({100 * frac:.0f} %) repeat the "
                         "previous reading (the sensor converts slower than it sends: "
                         "sample-and-hold)")
        else:
            rep = repeated(np.asarray(restored.raw_mag_nT)) & np.asarray(restored.valid)
            n_rep = int(np.count_nonzero(rep))
            parts.append(f" = {_n(n_rep)} repeats of the previous reading (the sensor "
                         f"converts slower than it sends: sample-and-hold) + "
                         f"{_n(n_valid - n_rep)} new readings")
    use = (". The metrics and the residual use every restored sample"
           + (f" (the before/after comparison {_n(n_valid - n_stamp)}: {_n(n_stamp)} "
              f"{_have(n_stamp)} no attitude at their own stamp, only at their sensing time "
              "t \u2212 \u03c4)" if n_stamp else ""))
    parts.append(use)
    n_excl = int(checks.get("excluded_samples") or 0)
    n_fit = int(fs["of"]) if fs and fs.get("of") else int(getattr(calibration, "n_samples", 0))
    # the repeats are left out of the fit only when it used no more than the new readings (a
    # diagnosis that kept its model on every message fitted them too)
    skipped = bool(held) and n_rep is not None and n_fit <= n_valid - n_rep - n_excl
    fit = ["the repeats"] if skipped else []
    if n_excl:
        fit.append(f"the {_n(n_excl)} samples in the excluded windows")
    base = (n_valid - n_rep if skipped and n_rep is not None else n_valid) - n_excl
    what = "new readings" if skipped else "restored samples"
    # the fit in a sentence of its own: its count is of other samples than the metrics'
    text = "".join(parts) + f". The calibration's fit used {_n(n_fit)}"
    notes = []
    if fit:
        notes.append(" and ".join(fit) + " are left out of the fit only")
    seen = analysed_samples(calibration)
    if 0 < n_fit < base:
        text += f" of the {_n(base)} {what}"
        if seen is not None:
            # a long recording: the analysis saw windows of it, the restore every sample
            n_seen = int(seen["n"])
            notes.append(f"the analysis of a long recording sees {_n(n_seen)} magnetometer "
                         f"samples in {int(seen.get('windows', 0))} windows of it; "
                         "every sample is restored and measured")
            base = min(base, n_seen)
        if n_fit < base:
            notes.append(f"the {_n(base - n_fit)} others lie too close to the attitude's start "
                         "or end to be predicted, or have no position")
    else:
        text += f" {what}" if n_fit != 1 else " sample"
    if fs and int(fs.get("stride", 1) or 1) > 1:
        k = int(fs["stride"])
        nth = {2: "2nd", 3: "3rd"}.get(k, f"{k}th")
        notes.append(f"the diagnosis fitted every {nth} of them, {_n(int(fs['n']))}")
    if notes:
        text += " (" + "; ".join(notes) + ")"
    return text + "."


def _have(n: int) -> str:
    """Return the verb for a count of samples: "has" for one, "have" otherwise."""
    return "has" if int(n) == 1 else "have"


def counts_text(metrics: Any) -> str:
    """Where every magnetometer sample went, in words; the named counts add up to the total.

    Used + without a usable attitude at ``t - tau`` + without an attitude at the stamp itself
    (restored but not compared with the uncalibrated field) = every sample. No sample is
    dropped otherwise (sample-and-hold repeats are restored like the others).
    """
    n_stamp = int(getattr(metrics, "n_without_attitude_at_stamp", 0))
    text = (f"{metrics.n_used} of {metrics.n_samples} samples used; "
            f"{metrics.n_without_attitude} without a usable attitude")
    if n_stamp:
        text += (f"; {n_stamp} with an attitude at the sensing time t \u2212 \u03c4 but none "
                 "at their own stamp (restored, not compared with the uncalibrated field)")
    return text


def analysed_samples(cal: Any) -> dict | None:
    """Return ``checks.analysed_samples`` when the analysis saw only windows of the recording.

    ``{n, of, windows}`` (pipeline.run.runner); None when it saw every sample.
    """
    seen = (getattr(cal, "checks", None) or {}).get("analysed_samples")
    if not isinstance(seen, dict) or int(seen.get("n", 0)) >= int(seen.get("of", 0)):
        return None
    return seen


def analysed_words(cal: Any) -> str:
    """Return where a long recording's analysis looked, or "" when it saw every sample."""
    seen = analysed_samples(cal)
    if seen is None:
        return ""
    return (f" in the {int(seen.get('windows', 0))} analysed windows, "
            f"{int(seen['n'])} of the recording's {int(seen['of'])} magnetometer samples")


def samples_text(cal: Any) -> str:
    """Return the calibration's ``n_samples`` with what it counts (the samples fitted)."""
    n = int(cal.n_samples)
    fs = (getattr(cal, "checks", None) or {}).get("fit_samples")
    where = analysed_words(cal)
    if isinstance(fs, dict) and fs.get("stride", 1) and int(fs.get("stride", 1)) > 1:
        k = int(fs["stride"])
        nth = {2: "2nd", 3: "3rd"}.get(k, f"{k}th")
        return (f"{n} (every {nth} of {int(fs.get('of', 0))} samples with an attitude{where}, "
                f"decimated for the diagnosis fit{fs.get('note', '')})")
    if isinstance(fs, dict):
        return f"{n} (every sample with an attitude{where}{fs.get('note', '')})"
    held = getattr(cal, "sample_hold", None)
    if held:
        return f"{n} (samples with an attitude, sample-and-hold repeats left out)"
    return f"{n} (samples with an attitude fitted by the estimator)"


def _t(t0_ns: int, t_s: float) -> str:
    """Relative time in seconds with the UTC time beside it."""
    return f"{t_s:.1f} s <small>{utc(t0_ns, t_s)}</small>"


def _metrics_html(metrics: Any, t0_ns: int = 0) -> str:
    if metrics is None:
        return "<p>No metrics.</p>"
    rows: list[str] = []
    scope_rows: list[list[str]] = []
    for s in metrics.scopes:
        rows = []
        scope_rows.append(rows)
        for i, c in enumerate(("x", "y", "z")):
            comp = s.components[c]
            cal, unc, r = comp["calibrated"], comp["uncalibrated"], comp["ratio_pct"]
            head = ""
            if i == 0:
                name = "whole recording" if s.scope == "all" else html.escape(s.scope)
                head = (f"<td rowspan=3 class=l>{name}</td>"
                        f"<td rowspan=3 class=l>{html.escape(s.kind)}</td>"
                        f"<td rowspan=3>{_t(t0_ns, s.start_s)}</td>"
                        f"<td rowspan=3>{_t(t0_ns, s.end_s)}</td>"
                        f"<td rowspan=3>{s.n_samples}</td>")
            rows.append(
                f"<tr class={'first' if i == 0 else 'next'}>{head}"
                f"<td>{ENU_LABELS[i]}</td>"
                + "".join(
                    f"<td>{_fmt(unc[k], 1)}</td><td>{_fmt(cal[k], 1)}</td>"
                    f"<td>{_fmt(r[k], 1)}</td>"
                    for k in ("fluctuation_range_nT", "absolute_deviation_nT", "std_nT")
                )
                + "</tr>"
            )
    head = (
        "<tr><th rowspan=2>scope</th><th rowspan=2>kind</th><th rowspan=2>start</th>"
        "<th rowspan=2>end</th><th rowspan=2>samples</th><th rowspan=2>ENU</th>"
        "<th colspan=3>fluctuation range (nT)</th>"
        "<th colspan=3>absolute deviation (nT)</th><th colspan=3>standard deviation (nT)</th>"
        "</tr><tr>" + "<th>before</th><th>after</th><th>ratio %</th>" * 3 + "</tr>"
    )
    extra = (
        f"<p>{html.escape(counts_text(metrics))}. Ratio: after / before "
        "&times; 100 (smaller is better). Segments end before the next starts: [start, end).</p>"
    )
    if metrics.heading_error:
        he = metrics.heading_error
        keys = list(he["calibrated"])
        extra += (
            "<h3>Heading error (Tang 2016, Table 2)</h3><table><tr><th></th>"
            + "".join(f"<th>{html.escape(k)}</th>" for k in keys) + "</tr>"
            + "".join(
                f"<tr><td>{w}</td>" + "".join(f"<td>{_fmt(he[w][k], 3)}</td>" for k in keys)
                + "</tr>" for w in ("uncalibrated", "calibrated")
            ) + "</table>"
        )
    table = f"<table class=metrics>{head}{''.join(scope_rows[0])}"
    segs = scope_rows[1:]
    if len(segs) > MAX_SEGMENT_ROWS:
        # hours of data hold hundreds of segments: the whole recording stays in view, the
        # segments fold away (every row is also in metrics.json / metrics.parquet)
        table += (f"</table><details><summary>{len(segs)} segments (click to show)</summary>"
                  f"<table class=metrics>{head}{''.join(r for rs in segs for r in rs)}"
                  "</table></details>")
    else:
        table += f"{''.join(r for rs in segs for r in rs)}</table>"
    return f"{table}{extra}"


#: segments shown in the metrics table before it folds them away
MAX_SEGMENT_ROWS = 20


def _pm(a: Any, sg: Any, nd: int) -> str:
    return "&ndash;" if a is None else html.escape(pm_vec(a, sg, nd))


def estimator_text(cal: Any, estimator: str | None = None,
                   calibration_path: str | None = None) -> str:
    """Say which estimator made the rotation, in words (not the stage's internal name).

    ``estimator``: the one asked for (None: the default); ``calibration_path``: the
    calibration was loaded from there.
    """
    name = str(estimator or "ml")
    if calibration_path:
        return f"loaded from {Path(calibration_path).name} (not estimated here)"
    est = str(cal.estimator)
    base = f"{name}: {DESCRIPTIONS.get(name, '')}".rstrip(": ")
    if est == "diagnose" or cal.effects:
        return base + "; then refitted by the diagnosis with its final model (the terms it " \
            "found, above)"
    if est != name:
        return f"{est}"
    return base


def _calibration_html(cal: Any, estimator: str | None = None,
                      calibration_path: str | None = None) -> str:
    rv = np.asarray(cal.rotvec_body_mag_deg, float)
    rows = [
        ("estimator", html.escape(estimator_text(cal, estimator, calibration_path))),
        ("rotation vector of R_body_mag (deg, body x, y, z)",
         _pm(rv, cal.sigma_rotvec_deg, 3)),
        ("misalignment angle |rotation| (deg)", _fmt(float(np.linalg.norm(rv)), 3)),
    ]
    if cal.rotvec_from_nominal_deg is not None:
        rows.append(("from nominal (deg)", _pm(cal.rotvec_from_nominal_deg, None, 3)))
    rows += [
        ("offset o (nT, mag x, y, z)", _pm(cal.offset_nT, cal.sigma_offset_nT, 1)),
        ("soft iron D", "&ndash;" if cal.D is None else
         "<br>".join(_pm(r, None, 4) for r in np.asarray(cal.D, float))),
        ("time offset &tau; (ms)", "&ndash;" if cal.time_offset_s is None else
         html.escape(minus(f"{1e3 * cal.time_offset_s:.2f}")
                     + ("" if cal.sigma_time_offset_s is None
                        else f" \u00b1 {1e3 * cal.sigma_time_offset_s:.2f}"))),
        ("background field B (nT, east, north, up)", _pm(cal.B_enu_nT, cal.sigma_B_enu_nT, 1)),
        ("|B| (nT)", _fmt(float(np.linalg.norm(cal.B_enu_nT)), 1)),
        ("residual rms (nT)", _fmt(float(cal.residual_rms_nT), 2)
         + html.escape(" (the fitted samples below; every sample's: Residuals)"
                       if analysed_words(cal) else "")),
        ("samples", html.escape(samples_text(cal))),
        ("rotation axes not determined (body)", _undetermined_axes(cal)),
    ]
    body = "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows)
    return f"<table class=kv>{body}</table>"


def _undetermined_axes(cal: Any) -> str:
    """Return the axes the motion leaves undetermined, and those it determines poorly.

    Poorly: a sigma over the verdict's threshold (:data:`stages.estimate.POOR_AXIS_SIGMA_DEG`);
    never a bare "none" beside a sigma of degrees.
    """
    out = ", ".join(_vec(a, 3) for a in cal.unobservable_axes_body) or "none"
    sig = np.asarray(cal.sigma_rotvec_deg, float)
    poor = [f"{ax} (\u00b1 {s:.1f}\u00b0)" for ax, s in zip("xyz", sig, strict=True)
            if np.isfinite(s) and s > POOR_AXIS_SIGMA_DEG]
    if poor:
        out += (f"; poorly determined (sigma over {POOR_AXIS_SIGMA_DEG:g}\u00b0): "
                + ", ".join(poor))
    return out


_VERDICT_COLOUR = {"OK": "#d4edda", "QUESTIONABLE": "#fff3cd", "REFUSED": "#f8d7da"}


def _residual_html(totals: RestoreTotals | None) -> str:
    if totals is None:
        return ""
    rms = f"<span id=residual_rms_nT>{totals.residual_rms_nT:.7g}</span>"
    return (f"<p>Residual of the final model (every term of the calibration, diagnosed effects "
            f"included): {rms} nT RMS over {totals.n_valid} samples "
            "with a usable attitude.</p>")


def _verdict_html(cal: Any) -> str:
    """Return the verdict box for the top of the report: one-line summary and reason."""
    v = getattr(cal, "verdict", None)
    status = "not judged" if v is None else v.status.value
    colour = _VERDICT_COLOUR.get(status, "#eee")
    reason = "" if v is None else f"<p>{html.escape(minus(v.reason))}</p>"
    ne = "".join(f"<li>{html.escape(d['term'])}: {html.escape(d['reason'])}</li>"
                 for d in getattr(cal, "not_estimated", ()))
    ne = f"<p>Not estimated:</p><ul>{ne}</ul>" if ne else ""
    neff = getattr(cal, "n_eff", None)
    neff_html = "" if neff is None else (
        f"<p>Uncertainties (\u00b1, 1 sigma) from {neff:.0f} effective independent samples of "
        f"{int(cal.n_samples)} (the residuals are correlated in time).</p>")
    line = minus(verdict_line(cal, with_status=False).replace("+-", "\u00b1"))
    # every doubt and refusal of the checks, in plain words (the reason gives the first)
    checks = getattr(cal, "checks", None) or {}
    texts = list(checks.get("refusals", ())) + list(checks.get("doubts", ()))
    items = []
    for t in texts:
        cause, advice = plain_words(str(t))
        cause = cause[:1].upper() + cause[1:] + "."
        items.append(f"<li id=doubt>{html.escape(minus(cause))}"
                     + (f" What to do: {html.escape(advice)}." if advice else "") + "</li>")
    doubts = (f"<p>What the checks found:</p><ul>{''.join(items)}</ul>"
              if len(items) > 1 else "")
    return (f"<div class=verdict id=verdict style='background:{colour}'>"
            f"<b>Verdict: {html.escape(status)}</b> &mdash; "
            f"{html.escape(line)}{reason}{doubts}{ne}{neff_html}</div>")


def _diagnosis_html(diagnosis: Any, t0_ns: int = 0, calibration_path: str | None = None,
                    mag: VectorSeries | None = None) -> tuple[str, list[tuple[str, bytes]]]:
    if diagnosis is None:
        given = calibration_path
        if given:
            return ("<p>Not diagnosed: this recording was restored with the calibration from "
                    f"{html.escape(Path(given).name)} (of "
                    f"{html.escape(Path(given).parent.name)}); the diagnosis is in the report "
                    "of the recording that calibration was estimated from.</p>"), []
        return "<p>Not diagnosed.</p>", []
    d = diagnosis.to_dict() if hasattr(diagnosis, "to_dict") else dict(diagnosis)
    parts = [rows_html(d, t0_ns)]
    b, f = d.get("baseline") or {}, d.get("final") or {}
    held = ("Held-out: data the model was not fitted to, so an improvement there is not "
            "overfitting. Evidence: how strongly the data ask for the term (the Laplace "
            "evidence: the fit against what its parameters cost).")
    if d.get("findings"):
        parts.append(
            "<p>Without these terms the model leaves "
            f"{_fmt(b.get('residual_rms_nT'), 1)} nT rms ({_fmt(b.get('heldout_rms_nT'), 1)} nT "
            f"on held-out data); with them {_fmt(f.get('residual_rms_nT'), 1)} nT "
            f"({_fmt(f.get('heldout_rms_nT'), 1)} nT held-out). {held}</p>")
    else:  # one model: the final one, whose residual every other place reports
        parts.append(
            f"<p>The model leaves {_fmt(f.get('residual_rms_nT'), 1)} nT rms "
            f"({_fmt(f.get('heldout_rms_nT'), 1)} nT on held-out data). {held}</p>")
    ni = d.get("not_identifiable") or []
    if ni:
        parts.append(
            "<p>Cannot be told from this recording:</p><ul>"
            + "".join(f"<li>{html.escape(str(x.get('effect')).replace('_', ' '))}: "
                      f"{html.escape(str(x.get('reason')))}</li>" for x in ni)
            + "</ul>"
        )
    figs: list[tuple[str, bytes]] = []
    if not isinstance(diagnosis, dict):
        figs = finding_figures(diagnosis, t0_ns, mag=mag)
    return "".join(parts), figs


def finding_figures(diagnosis: Any, t0_ns: int, dpi: int = 100, *,
                    mag: VectorSeries | None = None) -> list[tuple[str, bytes]]:
    """One figure per diagnosis finding: its signature in the residual (PNG).

    In the diagnosis' order (the order its evidence was measured, as the findings table and
    diagnosis.json): each figure shows the residual the terms before it left. The time axis
    is the report's (seconds, minutes or hours from the first sample's UTC time); keys are
    under the axes, never over the data. A sample-and-hold finding has no term in the
    residual: its figure shows the repeated messages themselves (needs ``mag``).

    Parameters
    ----------
    diagnosis : Diagnosis
        Its findings, with their signatures.
    t0_ns : int
        First magnetometer stamp, ns since the epoch.
    dpi : int
        Resolution of the PNGs.
    mag : VectorSeries, optional
        The recording's magnetometer messages, for the sample-and-hold figure.

    Returns
    -------
    list of (title, png bytes)

    """
    findings = [f for f in getattr(diagnosis, "findings", ())
                if f.signature is not None or (f.effect == "sample_hold" and mag is not None
                                               and len(mag) > 10)]
    if not findings:
        return []
    plt = _plt()

    # the diagnosis' order (the order its evidence was measured), as the findings table
    ordered = findings
    dur = float(getattr(diagnosis, "duration_s", 0.0) or 0.0)
    scale, unit = _time_scale(dur)
    out = []
    for f in ordered:
        s = f.signature
        if s is None:  # sample and hold: the messages show it, not a residual
            with plt.rc_context(style.rc() | {"savefig.dpi": dpi, "figure.dpi": dpi}):
                assert mag is not None
                out.append(("sample hold", _png(_sample_hold_figure(plt, f, mag))))
            continue
        frame = f.where.get("frame", "")
        with plt.rc_context(style.rc() | {"savefig.dpi": dpi, "figure.dpi": dpi}):
            t = np.asarray(s.t_s, dtype=float) / scale
            names = _axis_names(frame)
            # a term far smaller than the residual it was fitted to is flat at the
            # residual's scale: a second panel shows it at its own
            own = (s.regressor is None and f.effect not in EVENT_EFFECTS
                   and needs_own_scale(np.asarray(s.residual_before_nT, float),
                                       np.asarray(s.contribution_nT, float)))
            if own:
                fig, (ax, ax_term) = plt.subplots(2, 1, figsize=(12, 6.4), sharex=True,
                                                  gridspec_kw={"height_ratios": [3, 2]})
            else:
                fig, ax = plt.subplots(figsize=(12, 4.2))
            if s.regressor is not None:
                for i, c in enumerate(names):
                    ax.plot(s.regressor[:, i], s.residual_before_nT[:, i], ".", ms=2,
                            alpha=0.4, color=style.AXIS[i], label=f"residual {c}")
                for i, c in enumerate(names):
                    # the fitted term against the same rate: the line the points should follow
                    order = np.argsort(s.regressor[:, i])
                    ax.plot(s.regressor[order, i], s.contribution_nT[order, i], lw=1.8,
                            color=style.AXIS[i], label=f"fitted term {c}")
                ax.set_xlabel(f"rate of change of the reading ({_frame_words(frame)}, nT/s)")
                ax.set_ylabel("residual before the term (nT)")
            elif f.effect in EVENT_EFFECTS:
                ax.plot(t, np.linalg.norm(s.residual_before_nT, axis=1), lw=0.7,
                        color=style.BEFORE, label="|residual| before this term")
                ax.plot(t, np.linalg.norm(s.contribution_nT, axis=1), lw=1.6,
                        color=style.AFTER, label="|fitted term|")
                for a, b in f.where.get("windows_s") or []:
                    ax.axvspan(a / scale, b / scale, facecolor=style.EVENT, alpha=0.55,
                               edgecolor=style.EVENT_EDGE, lw=1.0, zorder=0,
                               label="window found" if a == f.where["windows_s"][0][0]
                               else None)
                ax.set_xlabel(_time_label(t0_ns, unit))
                ax.set_ylabel("nT")
            else:
                for i, c in enumerate(names):
                    ax.plot(t, s.residual_before_nT[:, i], lw=0.5, alpha=0.35,
                            color=style.AXIS[i], label=f"residual {c}")
                    ax.plot(t, s.contribution_nT[:, i], lw=1.6, color=style.AXIS[i],
                            label=f"fitted term {c}")
                ax.set_ylabel(f"nT ({_frame_words(frame)})")
                if own:
                    for i in range(3):
                        ax_term.plot(t, s.contribution_nT[:, i], lw=1.6, color=style.AXIS[i])
                    _term_limits(ax_term, np.asarray(s.contribution_nT, float))
                    ax_term.set_ylabel("fitted term (nT)")
                    ax_term.set_title("the fitted term alone, at its own scale", fontsize=11)
                    ax_term.set_xlabel(_time_label(t0_ns, unit))
                else:
                    ax.set_xlabel(_time_label(t0_ns, unit))
            title = _finding_title(f)
            ax.set_title(title)
            h, lab = ax.get_legend_handles_labels()
            fig.legend(h, lab, loc="lower left", ncol=6, frameon=False, markerscale=5,
                       bbox_to_anchor=(0.01, 0.0))
            fig.subplots_adjust(left=0.07, right=0.99, bottom=0.18 if own else 0.27,
                                top=0.93 if own else 0.9, hspace=0.3)
            _fit_left(fig)
            out.append((title, _png(fig)))
    return out


#: messages in the sample-and-hold figure's close-up
HOLD_WINDOW_MESSAGES = 48


def _sample_hold_figure(plt: Any, f: Any, mag: VectorSeries) -> Any:
    """Draw a sample-and-hold finding: repeated messages in a close-up, and run lengths.

    Left: the magnetometer axis that changes most, over a few dozen messages where the field
    changes fastest (a repeat is only visible while the field moves); new conversions filled,
    repeats of the previous reading open and red. Right: how many messages carry each
    conversion.
    """
    t_ns = np.asarray(mag.t_ns, dtype=np.int64)
    v_nT = np.asarray(mag.values, dtype=float)
    rep = repeated(v_nT)
    n = len(t_ns)
    w = min(HOLD_WINDOW_MESSAGES, n)
    axis = int(np.argmax(np.nanstd(np.diff(v_nT, axis=0), axis=0))) if n > 1 else 0
    change = np.r_[0.0, np.abs(np.diff(v_nT[:, axis]))]
    change = np.where(np.isfinite(change), change, 0.0)
    # the window where the field moves most and messages repeat
    score = np.convolve(change * 1.0, np.ones(w), "valid") * (
        np.convolve(rep.astype(float), np.ones(w), "valid") > 0)
    i0 = int(np.argmax(score)) if score.size else 0
    sl = slice(i0, i0 + w)
    t_ms = (t_ns[sl] - t_ns[i0]) * 1e-6
    y = v_nT[sl, axis]
    r = rep[sl]
    fig, (ax, axr) = plt.subplots(1, 2, figsize=(12, 4.2), gridspec_kw={"width_ratios": [3, 2]})
    ax.step(t_ms, y, where="post", color=style.REFERENCE, lw=0.8, alpha=0.6)
    ax.plot(t_ms[~r], y[~r], "o", ms=5, color=style.AFTER, label="new conversion")
    ax.plot(t_ms[r], y[r], "o", ms=6, mfc="none", mec=style.EVENT_EDGE, mew=1.5,
            label="message repeating the previous reading")
    ax.set_xlabel(f"time from {utc_text(int(t_ns[i0]))} UTC (ms)")
    ax.set_ylabel(f"mag {'xyz'[axis]} (nT)")
    ax.set_title(f"{w} consecutive messages where the field changes fastest", fontsize=11)
    run_id = np.cumsum(~rep) - 1
    lengths = np.bincount(np.bincount(run_id))[1:] if n else np.zeros(0, int)
    k = np.arange(1, len(lengths) + 1)
    shown = k <= 8
    axr.bar(k[shown], lengths[shown], color=style.AFTER, width=0.7)
    axr.set_xticks(k[shown])
    axr.set_xlabel("messages carrying one conversion")
    axr.set_ylabel("conversions")
    axr.set_title("how long each reading is held", fontsize=11)
    p = f.params or {}
    fig.suptitle(f"sample hold: the sensor converts at {float(p.get('native_rate_hz', 0)):.1f} "
                 f"Hz; {100 * float(p.get('repeated_fraction', 0)):.1f} % of the messages "
                 "repeat a reading", fontsize=12)
    h, lab = ax.get_legend_handles_labels()
    fig.legend(h, lab, loc="lower left", ncol=2, frameon=False, bbox_to_anchor=(0.01, 0.0))
    fig.subplots_adjust(left=0.08, right=0.99, bottom=0.25, top=0.84, wspace=0.25)
    _fit_left(fig)
    return fig


def _term_limits(ax: Any, term_nT: np.ndarray) -> None:
    """Set y limits that hold the fitted term with a margin, and zero.

    A constant term (an offset) would otherwise get matplotlib's tiny default span about its
    value, which hides its size; with zero in the range the lines show how far from zero each
    component is.
    """
    v = term_nT[np.isfinite(term_nT)]
    if not v.size:
        return
    lo, hi = min(float(v.min()), 0.0), max(float(v.max()), 0.0)
    pad = 0.15 * max(hi - lo, 1e-6)
    ax.set_ylim(lo - pad, hi + pad)


def _axis_names(frame: str) -> tuple[str, str, str]:
    """Return the names of a finding's components in its frame (east, north, up in ENU)."""
    return ("east", "north", "up") if frame == "enu" else ("x", "y", "z")


def _frame_words(frame: str) -> str:
    """Return the frame of a finding's figure in words."""
    return {"enu": "east, north, up", "mag": "magnetometer axes",
            "body": "body axes"}.get(frame, f"{frame} frame")


def _finding_title(f: Any) -> str:
    """Return a figure title in words: the effect, and its windows for an event."""
    name = str(f.effect).replace("_", " ")
    w = (f.where or {}).get("windows_s") or []
    if f.effect in EVENT_EFFECTS and w:
        return minus(f"{name}: " + ", ".join(f"{float(a):.1f} to {float(b):.1f} s"
                                            for a, b in w))
    return name


CSS = """
body{font-family:sans-serif;margin:1.5em auto;max-width:1250px;color:#222;padding:0 1em;
 font-size:15px;line-height:1.4}
table{border-collapse:collapse;margin:.5em 0;font-size:14px}
td,th{border:1px solid #bbb;padding:3px 7px;text-align:right;vertical-align:top}
th{background:#eee} table.kv th{text-align:left;font-weight:normal} td.l{text-align:left}
table.kv td{text-align:left} table.findings th{text-align:left}
table.findings td{text-align:left} table.metrics tr.first td{border-top:2px solid #888}
td small{color:#555}
figure{margin:.5em 0;overflow:auto} img{max-width:100%;cursor:zoom-in;display:block}
input.zoom{display:none} input.zoom:checked+label img{max-width:none;width:200%;
 cursor:zoom-out}
.verdict{border:1px solid #999;padding:.5em 1em;font-size:16px}
.warn{background:#fff3cd;border:1px solid #e0c36c;padding:.4em .8em}
.caption{color:#444;font-size:14px;margin-top:0}
dl.prov dt{float:left;clear:left;width:9em;color:#555} dl.prov dd{margin-left:10em}
"""


def provenance(recording: Recording, *, command: str | None = None) -> dict[str, str]:
    """Return what made this report: magalign version, command line, input sha256, date.

    Parameters
    ----------
    recording : Recording
        Its file is hashed.
    command : str, optional
        The command line; the ``MAGALIGN_COMMAND`` environment variable (set by the
        ``magalign`` program) or this process's arguments otherwise.

    """
    cmd = command or os.environ.get("MAGALIGN_COMMAND") or shlex.join(sys.argv)
    try:
        digest = sha256_file(recording.path)
    except OSError:
        digest = "unreadable"
    return {
        "magalign": package_version(),
        "command": cmd,
        "input": Path(recording.path).name,
        "input sha256": digest,
        "written": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC"),
    }


def render_html(
    recording: Recording,
    calibration: Any,
    metrics: Any,
    diagnosis: Any,
    figures: dict[str, bytes],
    restored: RestoreResult | None = None,
    *,
    totals: RestoreTotals | None = None,
    estimator: str | None = None,
    calibration_path: str | None = None,
    prov: dict[str, str] | None = None,
    survey: str = "",
) -> str:
    """Return the self-contained report text (figures inline as base64).

    ``restored``: the restored rows the figures show (every row, or every k-th of a long
    recording); ``totals``: the counts and residual of every sample (default: those of
    ``restored``). The final-model residual RMS is quoted by the residual figure (the same
    number as ``diagnosis.json``'s final residual when diagnosed). ``estimator`` and
    ``calibration_path``: what was asked for (:func:`estimator_text`).

    Order: the verdict and the headline first, then what the diagnosis found (one row per
    physical event, in sentences with units and UTC times), the field before and after,
    the metrics, the calibration, the remaining figures, the recording and provenance.
    """
    stem = Path(recording.path).stem
    t0 = int(recording.mag.t_ns[0]) if len(recording.mag.t_ns) else 0
    # the calibration's warnings: what reading the recording met (gaps, excluded stretches)
    # and what its fit did (sample-and-hold repeats, a rotation the motion leaves undetermined)
    warn = "".join(f"<li>{html.escape(minus(w))}</li>" for w in calibration.warnings)
    if calibration.unobservable_axes_body:
        warn += "<li>rotation about " + ", ".join(
            _vec(a, 3) for a in calibration.unobservable_axes_body
        ) + " (body) is not determined by this recording</li>"
    probs = "".join(
        f"<li>{html.escape(p.code)}: {html.escape(p.message)}</li>" for p in recording.problems
    )
    diag_html, diag_figs = _diagnosis_html(diagnosis, t0, calibration_path, recording.mag)
    if totals is None and restored is not None:
        totals = RestoreTotals.of(restored)
    channels = "".join(
        f"<tr><td class=l>{html.escape(c.topic)}</td><td class=l>{html.escape(c.type)}</td>"
        f"<td class=l>{html.escape(str(getattr(c.role, 'value', c.role)))}</td>"
        f"<td>{c.count}</td><td>{_fmt(c.rate_hz, 2)}</td></tr>"
        for c in recording.channels
    )
    fig_html = {k: _img(v, k) for k, v in figures.items()}
    prov = prov if prov is not None else provenance(recording)
    prov_html = "".join(f"<dt>{html.escape(k)}</dt><dd><code>{html.escape(v)}</code></dd>"
                        for k, v in prov.items())
    start = utc(t0, 0.0)
    day = dt.datetime.fromtimestamp(t0 / 1e9, tz=dt.timezone.utc).strftime("%Y-%m-%d")
    headline = _headline(calibration, metrics, diagnosis)
    counts = ("" if restored is None else
              f"<p id=counts>{html.escape(counts_sentence(restored, calibration, totals))}</p>")
    map_html = _map_html(fig_html.get("fig_map.png"), recording, diagnosis) + survey
    enu_caption_end = _enu_caption_end(recording, calibration, restored, diagnosis)
    # the counts of every sample (a long recording's figures show every k-th row)
    n_samples = metrics.n_samples if metrics is not None else len(recording.mag)
    duration_s = metrics.whole.end_s if metrics is not None else recording.duration_s
    sampled = ""
    if restored is not None and totals is not None and totals.n_total != len(restored.t_ns):
        k = max(2, round(totals.n_total / max(len(restored.t_ns), 1)))
        nth = f"{k}{'nd' if k == 2 else 'rd' if k == 3 else 'th'}"
        sampled = (f" The recording was processed in chunks: the figures show every {nth} "
                   f"sample ({len(restored.t_ns)} of {totals.n_total}); every number is "
                   "over all samples.")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>magalign: {html.escape(stem)}</title>
<style>{CSS}</style></head><body>
<h1>magalign report: {html.escape(stem)}</h1>
{_verdict_html(calibration)}
<p class=headline id=headline>{headline}</p>
<p>Recording <code>{html.escape(Path(recording.path).name)}</code> of {day}, from {start} UTC,
{duration_s:.1f} s, {n_samples} magnetometer samples. Times below count from its first
magnetometer sample, with the UTC time beside them. Click a figure to zoom.{sampled}</p>
{counts}
<h2>What the diagnosis found</h2>
{diag_html}
<h2>Field before and after calibration</h2>
{fig_html.get('fig_enu.png', '')}
<p class=caption>Amber: the reading turned into east, north, up by the attitude alone
(axes taken as aligned); purple: after calibration; black dashed: the field the fitted model
predicts where and when the sensor was (the background field plus the field terms the
diagnosis found: a gradient or map in space, a located source, a drift, a disturbance; a
straight line when it found none). Purple on the black line means the calibration explains
the rotation. The bottom row, |B|, does not depend on the heading or the misalignment: where
purple |B| steps or wanders and the black line follows, that is the field changing from place
to place or in time, not a calibration error; where purple departs from black, the offsets or
soft iron are wrong or the model lacks a term (the check of MATLAB magcal and ArduPilot
MagFit).{enu_caption_end}</p>
{map_html}
<h2>Metrics (Li et al. 2020, Table 4)</h2>
{_metrics_html(metrics, t0)}
<h2>Calibration</h2>
{_calibration_html(calibration, estimator, calibration_path)}
{f'<div class=warn><b>Warnings on the recording and fit</b><ul>{warn}</ul></div>' if warn else ''}
<h2>Residuals</h2>
{_residual_html(totals)}
{fig_html.get('fig_residual.png', '')}
<p class=caption>What the fitted model leaves unexplained, per magnetometer axis. Against
heading (right): a residual that repeats with the heading is a calibration term the model
lacks (a once-per-turn wave: an offset; twice per turn: soft iron).</p>
<h2>Readings in the magnetometer frame</h2>
{fig_html.get('fig_sphere.png', '')}
<p class=caption>Each reading in the magnetometer's own axes, in microtesla: calibrated, they
lie on the dashed circle of radius |B| about the cross. The histograms (right, on one scale)
give each reading's distance from that sphere, raw above and corrected below.</p>
<h2>Attitude and segments</h2>
{fig_html.get('fig_attitude.png', '')}
{'<h2>Diagnosis: each finding in the residual</h2>' if diag_figs else ''}
{''.join(f'<h3>{html.escape(t.split(":")[0].replace("_", " "))}</h3>'
         + _img(b, t, f'finding-{i}') for i, (t, b) in enumerate(diag_figs))}
<h2>Recording</h2>
<table><tr><th>topic</th><th>type</th><th>role</th><th>count</th><th>rate (Hz)</th></tr>
{channels}</table>
{f'<div class=warn><b>Problems handled while reading</b><ul>{probs}</ul></div>' if probs else ''}
<h2>Provenance</h2>
<dl class=prov>{prov_html}</dl>
</body></html>
"""


def _positions(recording: Recording, restored: Any) -> np.ndarray | None:
    """Return the positions at the restored rows (N, 3), or None without positions."""
    pos = getattr(recording, "position", None)
    if pos is None or not len(pos) or restored is None:
        return None
    return pos.at(np.asarray(restored.t_ns, dtype=np.int64))


def _enu_caption_end(recording: Recording, calibration: Any, restored: Any,
                     diagnosis: Any) -> str:
    """Return the ENU caption's sentences on shading and the closer scale, as drawn.

    Only what the figure has: the diagnosed events are named when there are any, the closer
    scale when a row has one.
    """
    words = []
    has_events = bool(event_windows(diagnosis, recording.duration_s or None))
    words.append(" Shading: motion segments" + (
        ", and in red the events the diagnosis found" if has_events else "")
        + " (key under the figure).")
    if restored is not None and len(restored.t_ns):
        vd = view_data(restored, calibration.R_body_mag)
        if any(closer_scale_rows(vd)):
            words.append(" Right: after calibration alone at a closer scale, which holds "
                         "nearly every sample; triangles on its edge mark the few beyond it.")
    return "".join(words)


def _map_html(fig: str | None, recording: Recording, diagnosis: Any = None) -> str:
    """Return the plan view's section (empty for a recording without positions).

    The caption names the marks the map has: sources and event stars only when diagnosed.
    """
    if not fig:
        return ""
    pos = recording.position
    frame = str(getattr(pos.frame, "value", pos.frame)) if pos is not None else ""
    where = ("east and north about the first position fix" if frame == "enu" else
             "the horizontal axes of the attitude source's own frame (a motion-capture "
             "room: they need not point east and north)")
    marks = ""
    if sources(diagnosis):
        marks += "Crosses: located sources with their 1-sigma ellipse. "
    if any(e != "local_source" for _, _, e in event_windows(diagnosis, recording.duration_s
                                                           or None)):
        marks += "Stars: where the sensor was during a diagnosed event. "
    return (f"<h2 id=map>Where the sensor went</h2>{fig}<p class=caption>The path seen from "
            f"above, in {where}, coloured by |B| minus its median: left the restored field, "
            "right the field the fitted model predicts there. Colours that repeat where the "
            "path comes back are the field in space; a colour on the left that the right "
            f"does not have is something the model leaves out. {marks}"
            "Open circle: start; filled square: end (inside the circle when the path ends "
            "where it began).</p>")


def percent_text(v: float) -> str:
    """Return a percentage as a reader takes it: whole numbers, two digits below 1 %.

    A calibration that leaves a few parts in ten thousand of the fluctuation reads
    "0.031 %", not "0 %" (nothing left at all).
    """
    return f"{v:.0f} %" if abs(v) >= 1.0 or v == 0.0 else f"{v:.2g} %"


def _headline(cal: Any, metrics: Any, diagnosis: Any) -> str:
    """Return the result in two sentences: the misalignment, what calibration did to the field."""
    rv = np.asarray(cal.rotvec_body_mag_deg, float)
    ang = float(np.linalg.norm(rv))
    parts = [f"The magnetometer is turned by <b>{ang:.2f}\u00b0</b> against the attitude "
             "source's axes."]
    if metrics is not None:
        try:
            r = metrics.ratio_pct()
            pct = {ENU_LABELS[i]: float(r[c]) for i, c in enumerate("xyz")
                   if r.get(c) is not None and np.isfinite(r[c])}
        except (AttributeError, KeyError, TypeError):
            pct = {}
        if pct:
            verb = "shrinks" if max(pct.values()) <= 100.0 else "changes"
            parts.append(f"Calibration {verb} the field's fluctuation to "
                         + ", ".join(f"{k} {percent_text(v)}" for k, v in pct.items())
                         + " of what it was.")
    if diagnosis is not None:
        d = diagnosis.to_dict() if hasattr(diagnosis, "to_dict") else dict(diagnosis)
        n = len(finding_rows(d, 0))
        parts.append("The diagnosis found nothing the model leaves out." if n == 0 else
                     f"The diagnosis found {n} effect{'s' if n > 1 else ''} beyond the "
                     "misalignment (below).")
    return " ".join(parts)


def write_report(
    out_dir: str | Path,
    recording: Recording,
    calibration: Any,
    metrics: Any = None,
    diagnosis: Any = None,
    segments: tuple[Segment, ...] | None = None,
    *,
    max_gap_s: float | None = None,
    restored: RestoreResult | None = None,
    totals: RestoreTotals | None = None,
    estimator: str | None = None,
    calibration_path: str | None = None,
    figures: dict[str, bytes] | None = None,
) -> Path:
    """Write the figures and ``report.html`` into ``out_dir``; returns the report's path.

    ``restored``: the restored rows (:class:`stages.restore.RestoreResult`); computed when
    not given. ``totals``: the counts of every sample when ``restored`` holds only some rows.
    ``figures``: :func:`make_figures` of the same arguments, when already drawn.
    """
    out = Path(out_dir)
    if restored is None:
        restored = restore_samples(recording, calibration, max_gap_s=max_gap_s)
    if figures is None:
        figures = make_figures(recording, calibration, segments, max_gap_s=max_gap_s,
                               restored=restored, diagnosis=diagnosis)
    for name, data in figures.items():
        with atomic_path(out / name, (recording.path,)) as tmp:
            tmp.write_bytes(data)
    md = report_map_data(recording, restored, calibration, diagnosis)
    if md is not None:  # the campaign summary draws every line's map from it
        write_map_json(out / "map.json", md)
    survey = survey_html(out, _positions(recording, restored), _img)  # "" without anomaly.nc
    text = render_html(recording, calibration, metrics, diagnosis, figures, restored=restored,
                       totals=totals, estimator=estimator, calibration_path=calibration_path,
                       survey=survey)
    # the words come from many modules, each formatting its own numbers
    return write_text_atomic(out / "report.html", unsigned_zeros(text))

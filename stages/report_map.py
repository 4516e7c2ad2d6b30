"""A plan view of where the sensor went, coloured by the restored field (report, summary, rerun).

More in docs/modules.md, ``stages.report_map``.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core import style
from pipeline.core.atomic import write_text_atomic

#: most points of a drawn path (runs of consecutive samples, averaged)
MAX_POINTS = 1500
#: effects that are events in time, marked on the path where the sensor was
EVENT_EFFECTS = ("disturbance", "hard_iron_step", "local_source")
#: a window covering more of the recording than this is no event (a term present throughout)
EVENT_MAX_FRACTION = 0.9
#: windows closer than this (s) are one event (``stages.report_text.EVENT_GAP_S``)
EVENT_GAP_S = 2.0
#: diverging colours for the field minus its median (blue below, red above)
CMAP = "RdBu_r"


def event_windows(diagnosis: Any, duration_s: float | None = None
                  ) -> list[tuple[float, float, str]]:
    """Return the diagnosed event windows ``(start_s, end_s, effect)``, in time order.

    From the windows of the ``disturbance``, ``hard_iron_step`` and ``local_source`` findings
    (seconds from the first magnetometer sample); a window that spans nearly the whole
    recording is a term present throughout, not an event, and is left out.
    """
    if diagnosis is None:
        return []
    d = diagnosis.to_dict() if hasattr(diagnosis, "to_dict") else dict(diagnosis)
    out: list[tuple[float, float, str]] = []
    for f in d.get("findings") or []:
        eff = str(f.get("effect"))
        if eff not in EVENT_EFFECTS:
            continue
        for w in (f.get("where") or {}).get("windows_s") or []:
            a, b = float(w[0]), float(w[1])
            if duration_s and b - a > EVENT_MAX_FRACTION * duration_s:
                continue
            out.append((a, b, eff))
    return sorted(out)


def merged_events(windows: list[tuple[float, float, str]], gap_s: float = EVENT_GAP_S
                  ) -> list[tuple[float, float, str]]:
    """Join windows closer than ``gap_s`` into one event, as the report's table does.

    A magnet brought near and taken away is found as several steps: one star on the map.
    The effects of a joined event are joined by ``+``.
    """
    out: list[tuple[float, float, str]] = []
    for a, b, e in sorted(windows):
        if out and a <= out[-1][1] + gap_s:
            a0, b0, e0 = out[-1]
            kinds = e0.split("+")
            out[-1] = (a0, max(b0, b), e0 if e in kinds else "+".join(sorted(kinds + [e])))
        else:
            out.append((a, b, e))
    return out


def sources(diagnosis: Any) -> list[dict[str, Any]]:
    """Return the located sources: ``{"position_m", "sigma_m", "moment_Am2"}`` per finding."""
    if diagnosis is None:
        return []
    d = diagnosis.to_dict() if hasattr(diagnosis, "to_dict") else dict(diagnosis)
    out = []
    for f in d.get("findings") or []:
        if f.get("effect") != "local_source":
            continue
        p = (f.get("params") or {}).get("position_m")
        if p is None:
            continue
        s = (f.get("sigma") or {}).get("position_m")
        sig = [float(x) if x is not None and math.isfinite(float(x)) else None
               for x in (s if s is not None else [None] * 3)]
        out.append({"position_m": [float(x) for x in p], "sigma_m": sig,
                    "moment_Am2": (f.get("params") or {}).get("moment_Am2")})
    return out


def _runs(n: int, max_points: int) -> np.ndarray:
    """Index of the run each of ``n`` samples belongs to (runs of equal sample count)."""
    k = max(1, int(math.ceil(n / max(1, max_points))))
    return np.arange(n) // k


def frame_axes(frame: str) -> tuple[str, str]:
    """Axis labels of a plan view in the positions' frame."""
    if frame == "enu":
        return "east (m)", "north (m)"
    return "x (m, attitude source's frame)", "y (m, attitude source's frame)"


def map_data(t_ns: np.ndarray, p_m: np.ndarray, field_nT: np.ndarray, model_nT: np.ndarray,
             *, frame: str, t0_ns: int, diagnosis: Any = None, origin: Any = None,
             max_points: int = MAX_POINTS) -> dict[str, Any] | None:
    """Gather the plan view's numbers (JSON-able), or None without two valid positions.

    Parameters
    ----------
    t_ns : ndarray (N,)
        Magnetometer stamps.
    p_m : ndarray (N, 3)
        Position at each stamp (NaN where lost), m, in ``frame``.
    field_nT, model_nT : ndarray (N,)
        Restored |B| and the |B| the model predicts at each sample (NaN without attitude).
    frame : str
        ``enu`` or ``attitude_source_local``.
    t0_ns : int
        First magnetometer stamp of the recording (event windows count from it).
    diagnosis : Diagnosis or dict, optional
        For the sources and events.
    origin : GeodeticOrigin, optional
        The geodetic point the ENU positions start from.
    max_points : int
        Most points of the path (runs of consecutive samples, averaged).

    Returns
    -------
    dict or None
        ``frame``, ``origin``, ``median_nT`` (of the restored |B| on the path), ``path``: rows
        ``[t_s, x, y, z, dB, dB_model]`` (run means, ``dB``: |B| minus the median, nT),
        ``sources`` (:func:`sources`), ``events``: ``{effect, start_s, end_s, x, y, z}`` (the
        sensor's mean position in the window).

    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    p = np.asarray(p_m, dtype=float).reshape(-1, 3)
    f = np.asarray(field_nT, dtype=float)
    fm = np.asarray(model_nT, dtype=float)
    ok = np.isfinite(p).all(axis=1) & np.isfinite(f)
    if np.count_nonzero(ok) < 2:
        return None
    t_s = (t_ns - int(t0_ns)) * 1e-9
    med = float(np.median(f[ok]))
    idx = np.flatnonzero(ok)
    run = _runs(len(idx), max_points)
    cnt = np.bincount(run).astype(float)

    def mean(v: np.ndarray) -> np.ndarray:
        return np.bincount(run, weights=v[idx]) / cnt

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        fm_ok = np.where(np.isfinite(fm), fm, f)
        path = np.column_stack([mean(t_s), mean(p[:, 0]), mean(p[:, 1]), mean(p[:, 2]),
                                mean(f) - med, mean(fm_ok) - med])
    events = []
    for a, b, eff in merged_events(event_windows(diagnosis,
                                                 float(t_s[-1]) if len(t_s) else None)):
        here = ok & (t_s >= a) & (t_s < b)
        if eff == "local_source" or not np.any(here):
            continue  # a source's passes: its cross on the map marks where they were
        c = p[here].mean(axis=0)
        events.append({"effect": eff, "start_s": a, "end_s": b,
                       "x": float(c[0]), "y": float(c[1]), "z": float(c[2])})
    org = None
    if origin is not None:
        org = origin.to_dict() if hasattr(origin, "to_dict") else dict(origin)
    return {"frame": str(getattr(frame, "value", frame)), "origin": org, "median_nT": med,
            "samples_per_point": int(math.ceil(len(idx) / max(1, max_points))),
            "path": [[float(x) for x in row] for row in path],
            "sources": sources(diagnosis), "events": events}


def write_map_json(path: str | Path, data: Mapping[str, Any]) -> Path:
    """Write ``map.json`` (atomically)."""
    return write_text_atomic(Path(path), json.dumps(data, allow_nan=False, default=_nan_safe))


def _nan_safe(x: Any) -> Any:  # numpy scalars that json does not know
    return float(x)


def read_map_json(path: str | Path) -> dict[str, Any] | None:
    """Read ``map.json``, or None when absent or unreadable."""
    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) and d.get("path") else None


def colour_limit(*maps: Mapping[str, Any]) -> float:
    """Symmetric colour limit (nT) for the field minus its median: the 98th percentile of |dB|."""
    vals = [abs(r[k]) for m in maps for r in m["path"] for k in (4, 5)
            if math.isfinite(r[k])]
    return max(float(np.percentile(vals, 98)) if vals else 1.0, 1.0)


def _plan(ax: Any, m: Mapping[str, Any], column: int, lim: float, *,
          labels: bool = True) -> Any:
    """Draw one path coloured by column ``column`` (4: restored, 5: model); return the mappable."""
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Ellipse

    path = np.asarray(m["path"], dtype=float)
    xy = path[:, 1:3]
    seg = np.stack([xy[:-1], xy[1:]], axis=1)
    lc = LineCollection(list(seg), cmap=CMAP, linewidths=2.5, zorder=2)
    lc.set_array(0.5 * (path[:-1, column] + path[1:, column]))
    lc.set_clim(-lim, lim)
    ax.add_collection(lc)
    # start an open ring larger than the filled end square: a path that ends where it
    # began shows both, the square inside the ring
    ax.plot(xy[0, 0], xy[0, 1], "o", ms=13, mfc="none", mec=style.REFERENCE, mew=2.0,
            zorder=3, label="start")
    ax.plot(xy[-1, 0], xy[-1, 1], "s", color=style.REFERENCE, ms=6, zorder=3.5, label="end")
    x0, x1, y0, y1 = extent(m)
    reach = 0.06 * max(x1 - x0, y1 - y0)  # about a label's height at the figure's size
    placed: list[tuple[float, float]] = []
    for i, s in enumerate(m.get("sources") or []):
        c = s["position_m"]
        sg = s.get("sigma_m") or [None, None, None]
        w = 2 * sg[0] if sg[0] else 0.0
        h = 2 * sg[1] if sg[1] else 0.0
        if w and h:
            ax.add_patch(Ellipse((c[0], c[1]), w, h, fill=False, ec=style.REFERENCE, lw=1.5,
                                 ls="--", zorder=4))
        ax.plot(c[0], c[1], "X", color=style.REFERENCE, ms=11, zorder=5,
                label="located source (dashed: 1 sigma)" if i == 0 else None)
        if labels:
            # sources a few centimetres apart in a room would print their names on each
            # other: each label goes a line below those of the sources already near it
            below = sum(math.hypot(c[0] - a, c[1] - b) < reach for a, b in placed)
            ax.annotate(f"source {i + 1}", (c[0], c[1]), textcoords="offset points",
                        xytext=(8, 6 - 13 * below), fontsize=10)
            placed.append((c[0], c[1]))
    for i, e in enumerate(m.get("events") or []):
        ax.plot(e["x"], e["y"], "*", color=style.EVENT, mec=style.REFERENCE, ms=16,
                zorder=6, label="sensor during a diagnosed event" if i == 0 else None)
        if labels:
            ax.annotate(f"{e['effect'].replace('_', ' ').replace('+', ' + ')} "
                        f"{e['start_s']:.0f}\u2013{e['end_s']:.0f} s", (e["x"], e["y"]),
                        textcoords="offset points", xytext=(8, -12), fontsize=10,
                        bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none",
                              "alpha": 0.8}, zorder=7)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal", adjustable="box")
    return lc


def extent(m: Mapping[str, Any], margin: float = 0.08) -> tuple[float, float, float, float]:
    """Return the plan's limits ``x0, x1, y0, y1``: the path, sources and events, square."""
    path = np.asarray(m["path"], dtype=float)
    xs = list(path[:, 1]) + [s["position_m"][0] for s in m.get("sources") or []]
    ys = list(path[:, 2]) + [s["position_m"][1] for s in m.get("sources") or []]
    cx, cy = 0.5 * (min(xs) + max(xs)), 0.5 * (min(ys) + max(ys))
    half = 0.5 * max(max(xs) - min(xs), max(ys) - min(ys), 1e-3) * (1 + 2 * margin)
    return cx - half, cx + half, cy - half, cy + half


def draw_map(m: Mapping[str, Any], dpi: int = 100) -> bytes:
    """Plan view for the report: restored |B| and the model's |B|, median taken off (PNG)."""
    plt = style.pyplot()
    lim = colour_limit(m)
    xl, yl = frame_axes(str(m.get("frame")))
    with plt.rc_context(style.rc() | {"savefig.dpi": dpi, "figure.dpi": dpi}):
        fig, axes = plt.subplots(1, 2, figsize=(12, 5.6))
        titles = ("restored |B| along the path", "|B| the fitted model predicts there")
        lc = None
        for ax, col, title in zip(axes, (4, 5), titles, strict=True):
            lc = _plan(ax, m, col, lim)
            ax.set_title(title)
            ax.set_xlabel(xl)
        axes[0].set_ylabel(yl)
        med = f"{m['median_nT']:,.0f}".replace(",", "\u2009")
        cb = fig.colorbar(lc, ax=list(axes), fraction=0.035, pad=0.02)
        cb.set_label(f"|B| \u2212 {med} nT (nT)")
        h, lab = axes[0].get_legend_handles_labels()
        n = m.get("samples_per_point") or 1
        fig.legend(h, lab, loc="lower left", ncol=4, frameon=False,
                   bbox_to_anchor=(0.01, 0.0),
                   title=None if n <= 1 else f"each point: mean of {n} consecutive samples",
                   title_fontsize=10, alignment="left")
        fig.subplots_adjust(left=0.08, right=0.86, bottom=0.24, top=0.93, wspace=0.12)
        return style.png(fig)


def draw_small_map(m: Mapping[str, Any], lim: float, title: str, dpi: int = 100) -> bytes:
    """One line's plan view for the campaign summary, on the campaign's colour scale (PNG)."""
    plt = style.pyplot()
    xl, yl = frame_axes(str(m.get("frame")))
    with plt.rc_context(style.rc() | {"savefig.dpi": dpi, "figure.dpi": dpi}):
        # laid out by matplotlib: fixed margins cut the colour bar's label off the right
        fig, ax = plt.subplots(figsize=(4.4, 4.2), layout="constrained")
        lc = _plan(ax, m, 4, lim, labels=False)  # too small for words: the stars say it
        ax.set_title(title, fontsize=11)
        ax.set_xlabel(xl.split(",")[0] + (")" if "," in xl else ""))
        ax.set_ylabel(yl.split(",")[0] + (")" if "," in yl else ""))
        cb = fig.colorbar(lc, ax=ax, fraction=0.05, pad=0.03)
        cb.set_label("|B| \u2212 median (nT)")
        return style.png(fig)


def draw_maps(maps: Sequence[tuple[str, Mapping[str, Any]]]) -> list[tuple[str, bytes]]:
    """Draw the summary's maps: one per recording with positions, on one colour scale."""
    if not maps:
        return []
    lim = colour_limit(*[m for _, m in maps])
    return [(name, draw_small_map(m, lim, name)) for name, m in maps]

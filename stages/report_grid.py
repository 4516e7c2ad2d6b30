"""The report's survey section: the anomaly grid with the path and targets, and the targets.

Drawn from the files :mod:`stages.write_survey` wrote (``anomaly.nc``, ``targets.csv``), so
the report shows exactly what was delivered.
"""

from __future__ import annotations

import csv
import html
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core import style
from pipeline.core.style import minus, num
from stages.report_map import CMAP, frame_axes
from stages.write_survey import MASK_PER_LINE, read_grid

#: columns of the report's target table: (targets.csv column, heading)
TABLE_COLUMNS = (
    ("id", "target"), ("east_m", "east (m)"), ("north_m", "north (m)"), ("up_m", "up (m)"),
    ("lat_deg", "latitude (deg)"), ("lon_deg", "longitude (deg)"),
    ("depth_below_sensor_m", "depth below sensor (m)"), ("sigma_east_m", "1σ east (m)"),
    ("sigma_north_m", "1σ north (m)"), ("sigma_up_m", "1σ up (m)"),
    ("moment_Am2", "moment (A m²)"), ("closest_approach_m", "closest pass (m)"),
    ("closest_approach_utc", "closest pass (UTC)"), ("peak_nT", "peak (nT)"),
    ("delta_bic", "evidence"),
)


def read_targets(path: str | Path) -> list[dict[str, str]]:
    """Return targets.csv's rows as dicts (empty when the file is absent)."""
    p = Path(path)
    if not p.exists():
        return []
    with open(p, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def draw_grid(grid: dict[str, Any], path_m: np.ndarray | None, targets: list[dict[str, str]],
              dpi: int = 100) -> bytes:
    """Plan view of the total-field anomaly (masked), the path and the targets (PNG)."""
    plt = style.pyplot()
    a = grid["attrs"]
    e, n = np.asarray(grid["easting"], float), np.asarray(grid["northing"], float)
    tfa = np.asarray(grid["total_field_anomaly_nT"], float)
    finite = tfa[np.isfinite(tfa)]
    lim = max(float(np.percentile(np.abs(finite), 99)) if finite.size else 1.0, 1.0)
    xl, yl = frame_axes(str(a.get("position_frame")))
    with plt.rc_context(style.rc() | {"savefig.dpi": dpi, "figure.dpi": dpi}):
        fig, ax = plt.subplots(figsize=(9.5, 7.5))
        s = float(a["spacing_m"])
        im = ax.imshow(np.ma.masked_invalid(tfa), origin="lower", cmap=CMAP, vmin=-lim,
                       vmax=lim, extent=(e[0] - s / 2, e[-1] + s / 2, n[0] - s / 2,
                                         n[-1] + s / 2), interpolation="nearest", zorder=1)
        if path_m is not None and len(path_m):
            ax.plot(path_m[:, 0], path_m[:, 1], "-", color=style.REFERENCE, lw=0.6, alpha=0.6,
                    zorder=2, label="path")
        for i, t in enumerate(targets):
            x, y = float(t["east_m"]), float(t["north_m"])
            ax.plot(x, y, "X", color=style.REFERENCE, mec="white", ms=12, zorder=4,
                    label="target" if i == 0 else None)
            ax.annotate(t["id"], (x, y), textcoords="offset points", xytext=(7, 5),
                        fontsize=11, zorder=5,
                        bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none",
                              "alpha": 0.8})
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_title(f"total-field anomaly at {num(float(a['height_m']), '.2f')} m, "
                     f"{num(s, '.3g')} m cells")
        cb = fig.colorbar(im, ax=ax, fraction=0.04, pad=0.02)
        cb.set_label("|B| − |background| (nT)")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="upper right", framealpha=0.85)
        fig.tight_layout()
        return style.png(fig)


def survey_html(out_dir: str | Path, path_m: np.ndarray | None,
                img: Callable[[bytes, str], str]) -> str:
    """Return the report's survey section, or "" when ``out_dir`` has no anomaly.nc.

    ``path_m``: the sensor's positions (N, 3) to draw over the grid; ``img``: how the report
    embeds a PNG.
    """
    nc = Path(out_dir) / "anomaly.nc"
    if not nc.exists():
        return ""
    grid = read_grid(nc)
    a = grid["attrs"]
    targets = read_targets(Path(out_dir) / "targets.csv")
    fig = img(draw_grid(grid, path_m, targets), "fig_anomaly.png")
    head = "".join(f"<th>{html.escape(h)}</th>" for _, h in TABLE_COLUMNS)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(minus(r.get(c) or '–'))}</td>"
                         for c, _ in TABLE_COLUMNS) + "</tr>" for r in targets)
    table = (f"<table id=targets><tr>{head}</tr>{body}</table>" if targets else
             "<p id=targets>No buried or nearby object was located: targets.csv holds its "
             "header only.</p>")
    bg = ", ".join(num(float(v), ".0f") for v in np.asarray(a["background_B_enu_nT"]).ravel())
    return (
        f"<h2 id=survey>The survey: anomaly grid and targets</h2>{fig}"
        f"<p class=caption>The restored field gridded at the sensor's mean height "
        f"({num(float(a['height_m']), '.2f')} m) on {num(float(a['spacing_m']), '.3g')} m "
        f"cells (at most a quarter of the path's line spacing, "
        f"{num(float(a['mask_distance_m']) / MASK_PER_LINE, '.3g')} m), "
        f"shown as the total-field anomaly: |B| minus the magnitude of the background field "
        f"[{bg}] nT (east, north, up). Cells farther than "
        f"{num(float(a['mask_distance_m']), '.3g')} m from the path are left blank: no "
        f"measurement supports them. Crosses: the targets below. The grid is anomaly.nc "
        f"(NetCDF-4), made by {html.escape(str(a['method']))}.</p>"
        f"<h3>Targets</h3>{table}<p class=caption>One row per located object (targets.csv), "
        "the strongest evidence first (evidence: how much better the model with the object "
        "explains the data, as the fall of -2 log of the Laplace evidence). Depth: "
        "below the sensor's mean height within 5 m of the object.</p>")


def grid_points(out_dir: str | Path) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Return the unmasked cells of ``out_dir/anomaly.nc`` for a 3D view, or None without it.

    ``(xyz (P, 3) m at the grid's height, rgb (P, 3) uint8 coloured by the total-field
    anomaly as the report's figure is, radius m)``.
    """
    import matplotlib

    nc = Path(out_dir) / "anomaly.nc"
    if not nc.exists():
        return None
    grid = read_grid(nc)
    a = grid["attrs"]
    ee, nn = np.meshgrid(np.asarray(grid["easting"], float), np.asarray(grid["northing"], float))
    tfa = np.asarray(grid["total_field_anomaly_nT"], float)
    ok = np.isfinite(tfa)
    if not ok.any():
        return None
    lim = max(float(np.percentile(np.abs(tfa[ok]), 99)), 1.0)
    rgb = (np.asarray(matplotlib.colormaps[CMAP](np.clip(0.5 + 0.5 * tfa[ok] / lim, 0, 1)))
           [:, :3] * 255).astype(np.uint8)
    xyz = np.column_stack([ee[ok], nn[ok], np.full(np.count_nonzero(ok), float(a["height_m"]))])
    return xyz, rgb, 0.5 * float(a["spacing_m"])

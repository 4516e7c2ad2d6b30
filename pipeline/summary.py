"""Campaign summary: one row per recording, ``summary.parquet`` and ``summary.html``.

Rows are built from each recording's own output files (``calibration.json``,
``metrics.json``, ``diagnosis.json``: CONVENTIONS formats) plus the campaign's status, so the
summary does not depend on how the per-recording pipeline lays out its return value.
"""

from __future__ import annotations

import html
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from .atomic import atomic_path, write_text_atomic

AXES = ("x", "y", "z")


def read_json(path: Path) -> dict[str, Any] | None:
    """Read a JSON object from ``path``, or None when absent or unreadable."""
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None


def flatten_numbers(d: Any, prefix: str = "") -> dict[str, float]:
    """Every numeric leaf of nested dicts/lists as ``{"a.b.0": value}``."""
    out: dict[str, float] = {}
    if isinstance(d, Mapping):
        for k, v in d.items():
            out.update(flatten_numbers(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(d, list | tuple):
        for i, v in enumerate(d):
            out.update(flatten_numbers(v, f"{prefix}.{i}"))
    elif isinstance(d, bool):
        pass
    elif isinstance(d, int | float):
        out[prefix] = float(d)
    return out


def _f(x: Any) -> float | None:
    if isinstance(x, bool) or not isinstance(x, int | float):
        return None
    return float(x) if math.isfinite(float(x)) else None


def row_for(out_dir: Path, result: Mapping[str, Any]) -> dict[str, Any]:
    """Build the summary row of one recording.

    Parameters
    ----------
    out_dir : Path
        The campaign output folder.
    result : mapping
        What :func:`pipeline.campaign.run_task` returned (``name``, ``status``, ``error``,
        ``row``, ...), plus optional ``calibration_from``.

    Returns
    -------
    dict
        Flat, JSON-able: name, role, status, error, calibration_from, rotvec_deg_x..z,
        sigma_deg_x..z, residual_rms_nT, time_offset_s, offset_nT_x..z, B_enu_nT_x..z,
        ratio_pct_x..z, findings (comma-separated effect names), report (relative link), rrd.

    """
    name = str(result["name"])
    folder = out_dir / name
    row: dict[str, Any] = {
        "name": name,
        "status": result.get("status"),
        "role": result.get("role"),
        "calibration_from": result.get("calibration_from"),
    }
    ok = result.get("status") in ("ok", "reused")
    row["report"] = f"{name}/report.html" if ok and (folder / "report.html").is_file() else None
    row["rrd"] = f"{name}/{name}.rrd" if ok and (folder / f"{name}.rrd").is_file() else None
    cal = (read_json(folder / "calibration.json") if ok else None) or {}
    for key, col in (("rotvec_body_mag_deg", "rotvec_deg"), ("sigma_rotvec_deg", "sigma_deg"),
                     ("offset_nT", "offset_nT"), ("B_enu_nT", "B_enu_nT")):
        vec = cal.get(key) or [None] * 3
        for i, a in enumerate(AXES):
            row[f"{col}_{a}"] = _f(vec[i]) if i < len(vec) else None
    row["residual_rms_nT"] = _f(cal.get("residual_rms_nT"))
    row["time_offset_s"] = _f(cal.get("time_offset_s"))
    row["estimator"] = cal.get("estimator")
    # ratio_pct (fluctuation range, whole recording) as the per-recording pipeline reports it;
    # else the first ratio_pct of metrics.json for that component.
    prow = result.get("row") if isinstance(result.get("row"), Mapping) else {}
    flat = None
    for a in AXES:
        v = _f(prow.get(f"ratio_pct_{a}"))
        if v is None and ok:
            if flat is None:
                flat = flatten_numbers(read_json(folder / "metrics.json") or {})
            vals = [x for k, x in flat.items()
                    if "ratio_pct" in k and f".{a}." in f".{k}."]
            v = vals[0] if vals else None
        row[f"ratio_pct_{a}"] = v
    diag = (read_json(folder / "diagnosis.json") if ok else None) or {}
    finds = [str(f.get("effect")) for f in diag.get("findings", []) or []
             if isinstance(f, Mapping)]
    row["findings"] = ",".join(finds)
    row["elapsed_s"] = _f(result.get("elapsed_s"))
    row["error"] = result.get("error")
    row["input_path"] = result.get("input_path")
    return row


def _column(values: list[Any]) -> pa.Array:
    kinds = {type(v) for v in values if v is not None}
    if kinds and kinds <= {int, float}:
        return pa.array([None if v is None else float(v) for v in values], pa.float64())
    return pa.array([None if v is None else str(v) for v in values], pa.string())


def write_summary(out_dir: str | Path, rows: Sequence[Mapping[str, Any]],
                  title: str = "magalign campaign") -> tuple[Path, Path]:
    """Write ``summary.parquet`` and ``summary.html`` (atomically) in ``out_dir``."""
    out = Path(out_dir)
    for stale in out.glob(".summary.*.tmp"):  # left by a run killed while writing these
        stale.unlink(missing_ok=True)
    cols: list[str] = []
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    table = pa.table({c: _column([r.get(c) for r in rows]) for c in cols})
    pq_path = out / "summary.parquet"
    with atomic_path(pq_path) as tmp:
        pq.write_table(table, tmp)
    html_path = write_text_atomic(out / "summary.html", render_html(rows, cols, title))
    return pq_path, html_path


def _cell(c: str, v: Any) -> str:
    if v is None:
        return "<td></td>"
    if c in ("report", "rrd"):
        href = html.escape(str(v), quote=True)
        return f'<td><a href="{href}">{html.escape(Path(str(v)).name)}</a></td>'
    if isinstance(v, float):
        txt = f"{v:.4g}"
    else:
        txt = str(v)
    cls = f' class="{html.escape(str(v))}"' if c == "status" else ""
    return f"<td{cls}>{html.escape(txt)}</td>"


def render_html(rows: Sequence[Mapping[str, Any]], cols: Sequence[str], title: str) -> str:
    """Render a self-contained HTML table, one row per recording, linking each report."""
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "\n".join("<tr>" + "".join(_cell(c, r.get(c)) for c in cols) + "</tr>" for r in rows)
    n_fail = sum(1 for r in rows if r.get("status") == "failed")
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; }}
table {{ border-collapse: collapse; font-size: 0.85em; }}
th, td {{ border: 1px solid #ccc; padding: 0.2em 0.5em; text-align: right; }}
th {{ background: #eee; }}
td.failed {{ background: #fdd; }} td.ok, td.reused {{ background: #dfd; }}
</style></head><body>
<h1>{html.escape(title)}</h1>
<p>{len(rows)} recording(s), {n_fail} failed. Angles in degrees (rotation vector of
R_body_mag, 1-sigma), fields in nT, ratio_pct = calibrated / uncalibrated x 100.</p>
<table><thead><tr>{head}</tr></thead><tbody>
{body}
</tbody></table></body></html>
"""

"""Campaign summary: one row per recording, ``summary.parquet`` and ``summary.html``.

Rows are built from each recording's own output files (``calibration.json``,
``metrics.json``, ``diagnosis.json``: CONVENTIONS formats) plus the campaign's status, so the
summary does not depend on how the per-recording pipeline lays out its return value.
"""

from __future__ import annotations

import base64
import html
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.core import style
from pipeline.core.atomic import atomic_path, write_text_atomic
from pipeline.core.style import minus, unsigned_zeros
from stages.report_map import draw_maps, read_map_json

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
        What :func:`pipeline.app.campaign.run_task` returned (``name``, ``status``, ``error``,
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
    verdict = cal.get("verdict")
    row["verdict"] = verdict.get("status") if isinstance(verdict, Mapping) else None
    row["verdict_reason"] = verdict.get("reason") if isinstance(verdict, Mapping) else None
    row["map"] = f"{name}/map.json" if ok and (folder / "map.json").is_file() else None
    # ratio_pct (fluctuation range, whole recording) as the per-recording pipeline reports it;
    # else the first ratio_pct of metrics.json for that component.
    row_ = result.get("row")
    prow: Mapping[str, Any] = row_ if isinstance(row_, Mapping) else {}
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
    html_path = write_text_atomic(out / "summary.html",
                                  unsigned_zeros(render_html(rows, cols, title, out)))
    return pq_path, html_path


def _num(v: Any, nd: int) -> str:
    """Return a number with ``nd`` decimals and a true minus sign ("" when missing)."""
    f = _f(v)
    return "" if f is None else minus(f"{f:.{nd}f}")


def _pm(v: Any, s: Any, nd: int) -> str:
    txt = _num(v, nd)
    sg = _f(s)
    if txt and sg is not None:
        small = 0.5 * 10 ** -nd
        txt += (f"<small> \u00b1 {sg:.{nd}f}</small>" if sg >= small
                else f"<small> \u00b1 &lt;{2 * small:.{nd}f}</small>")
    elif txt and s is None and v is not None:
        txt += "<small> \u00b1 \u221e</small>"
    return txt


def _link(v: Any, text: str) -> str:
    if not v:
        return ""
    return f'<a href="{html.escape(str(v), quote=True)}">{html.escape(text)}</a>'


#: the table's column groups: (group title, [(column title, cell function)])
def _groups() -> list[tuple[str, list[tuple[str, Any]]]]:
    def ax(col: str, nd: int, sig: str | None = None):
        return [(lab, (lambda r, a=a: _pm(r.get(f"{col}_{a}"), r.get(f"{sig}_{a}"), nd))
                 if sig else (lambda r, a=a: _num(r.get(f"{col}_{a}"), nd)))
                for a, lab in zip(AXES, ("x", "y", "z"), strict=True)]

    def enu(col: str, nd: int):
        return [(lab, (lambda r, a=a: _num(r.get(f"{col}_{a}"), nd)))
                for a, lab in zip(AXES, ("east", "north", "up"), strict=True)]

    def angle(r: Mapping[str, Any]) -> str:
        v = [_f(r.get(f"rotvec_deg_{a}")) for a in AXES]
        xs = [x for x in v if x is not None]
        return "" if len(xs) < len(v) else f"{math.sqrt(sum(x * x for x in xs)):.3f}"

    def tau(r: Mapping[str, Any]) -> str:
        t = _f(r.get("time_offset_s"))
        return "" if t is None else _num(1e3 * t, 2)

    def name(r: Mapping[str, Any]) -> str:
        txt = _link(r.get("report"), str(r.get("name"))) or html.escape(str(r.get("name")))
        rrd = _link(r.get("rrd"), "rerun recording")
        return txt + (f"<br><small>{rrd}</small>" if rrd else "")

    def status(r: Mapping[str, Any]) -> str:
        st, v = str(r.get("status") or ""), r.get("verdict")
        if st == "failed" or not v:
            return html.escape(st)
        return html.escape(str(v)) + (" <small>(reused)</small>" if st == "reused" else "")

    def role(r: Mapping[str, Any]) -> str:
        txt = html.escape(str(r.get("role") or ""))
        src = r.get("calibration_from")
        return txt + (f"<br><small>with {html.escape(str(src))}</small>" if src else "")

    return [
        ("recording", [("name", name), ("role", role), ("verdict", status)]),
        ("misalignment (deg, about body axes) \u00b1 1 sigma",
         ax("rotvec_deg", 3, "sigma_deg") + [("angle", angle)]),
        ("offset o (nT, mag)", ax("offset_nT", 1)),
        ("model: \u03c4, residual", [("\u03c4 (ms)", tau),
                   ("rms (nT)", lambda r: _num(r.get("residual_rms_nT"), 1))]),
        ("field B (nT)", enu("B_enu_nT", 0)),
        ("fluctuation, after / before (%)", enu("ratio_pct", 1)),
        ("diagnosis", [("findings", lambda r: html.escape(
            ", ".join(x.replace("_", " ") for x in str(r.get("findings") or "").split(",")
                      if x)))]),
        ("run", [("time (s)", lambda r: _num(r.get("elapsed_s"), 1))]),
    ]


#: columns the grouped table shows (the others only in summary.parquet)
SHOWN = {"name", "report", "role", "status", "verdict", "calibration_from", "rotvec_deg_x",
         "rotvec_deg_y", "rotvec_deg_z", "sigma_deg_x", "sigma_deg_y", "sigma_deg_z",
         "offset_nT_x", "offset_nT_y", "offset_nT_z", "time_offset_s", "residual_rms_nT",
         "estimator", "B_enu_nT_x", "B_enu_nT_y", "B_enu_nT_z", "ratio_pct_x", "ratio_pct_y",
         "ratio_pct_z", "findings", "rrd", "elapsed_s", "error", "input_path",
         "verdict_reason", "map"}
#: shown elsewhere in words: the estimator is in each report (the table's would read
#: "diagnose" for every diagnosed recording)
SHOWN.add("estimator")


def campaign_figure(rows: Sequence[Mapping[str, Any]]) -> bytes | None:
    """Plot the misalignment of every calibration run with 1-sigma error bars (PNG bytes).

    A calibration run is a recording whose rotation was estimated here (not restored with
    another's calibration). The figure compares runs: returns None when there are fewer
    than two (one run's rotation and sigmas are its row of the table; drawing them again
    would cost a one-recording ``process`` matplotlib's import).
    """
    runs = [r for r in rows if r.get("status") in ("ok", "reused")
            and not r.get("calibration_from")
            and all(_f(r.get(f"rotvec_deg_{a}")) is not None for a in AXES)]
    if len(runs) < 2:
        return None


    plt = style.pyplot()

    with plt.rc_context(style.rc()):
        fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), sharex=True)
        x = list(range(len(runs)))
        for k, (ax, a) in enumerate(zip(axes, AXES, strict=True)):
            v = [_f(r.get(f"rotvec_deg_{a}")) for r in runs]
            sg = [_f(r.get(f"sigma_deg_{a}")) for r in runs]
            ax.errorbar(x, v, yerr=[s if s is not None else 0.0 for s in sg], fmt="o",
                        color=style.AXIS[k], capsize=4, ms=6)
            for xi, s in zip(x, sg, strict=True):
                if s is None:  # not determined by that run's motion
                    ax.annotate("\u221e", (xi, v[xi]), textcoords="offset points",
                                xytext=(6, 4), color=style.AXIS[k])
            ax.set_title(f"about body {a} (deg)")
            ax.ticklabel_format(axis="y", useOffset=False)
            ax.set_xticks(x)
            ax.set_xticklabels([str(r.get("name")) for r in runs], rotation=30, ha="right")
        fig.suptitle("misalignment of each calibration run, \u00b1 1 sigma", fontsize=12)
        fig.tight_layout()
        return style.png(fig)


def maps_html(rows: Sequence[Mapping[str, Any]], out_dir: Path | None) -> str:
    """Return the plan views of the recordings with positions, side by side, each with its verdict.

    Each recording's ``map.json`` (written beside its report) is drawn on one colour scale
    for all, so that the same colour is the same field on every line.
    """
    if out_dir is None:
        return ""
    found = []
    for r in rows:
        rel = r.get("map")
        m = read_map_json(out_dir / str(rel)) if rel else None
        if m is not None:
            found.append((r, m))
    if not found:
        return ""
    pngs = draw_maps([(str(r.get("name")), m) for r, m in found])
    cells = []
    for (r, _), (_, png) in zip(found, pngs, strict=True):
        name = html.escape(str(r.get("name")))
        v = html.escape(str(r.get("verdict") or r.get("status") or ""))
        reason = html.escape(minus_text(str(r.get("verdict_reason") or "")))
        src = r.get("calibration_from")
        whose = (f"<br><small>restored with the calibration of {html.escape(str(src))}</small>"
                 if src else "")
        cells.append(
            f"<figure class=map id=\"map-{name}\"><img alt=\"map of {name}\" "
            f"src='data:image/png;base64,{base64.b64encode(png).decode('ascii')}'>"
            f"<figcaption><b>{_link(r.get('report'), str(r.get('name'))) or name}</b> "
            f"<span class=\"verdict v-{v}\">{v}</span>{whose}"
            f"<br><small class=reason>{reason}</small></figcaption></figure>")
    # the caption names only the marks some map has
    marks = ""
    if any(m.get("sources") for _, m in found):
        marks += " Crosses: located sources (dashed: 1 sigma)."
    if any(m.get("events") for _, m in found):
        marks += " Stars: where the sensor was during a diagnosed event."
    return ("<h2>Where each recording went</h2><p>Each path seen from above, coloured by its "
            "restored |B| minus that recording's median (one colour scale for all), with its "
            f"own verdict. Open circle: start; filled square: end.{marks}</p>"
            "<div class=maps>" + "".join(cells) + "</div>")


def minus_text(text: str) -> str:
    """Return ``text`` with a true minus sign and a plus-minus sign."""
    return minus(text)


def render_html(rows: Sequence[Mapping[str, Any]], cols: Sequence[str], title: str,
                out_dir: Path | None = None) -> str:
    """Render the self-contained summary: a figure of the calibration runs (from two) and a table.

    The table groups its columns (recording, misalignment, offset, model, field, effect of
    the calibration, diagnosis, files), one number format per quantity; each recording's
    name links to its report. A failed recording's error is a line under its row. Columns
    of ``cols`` the groups do not show are only in ``summary.parquet`` (``input_path``).
    """
    groups = _groups()
    extra = [c for c in cols if c not in SHOWN]
    n_cols = sum(len(g) for _, g in groups) + len(extra)
    top = "".join(f"<th colspan={len(g)} class=group>{html.escape(t)}</th>"
                  for t, g in groups) + (f"<th colspan={len(extra)} class=group>more</th>"
                                         if extra else "")
    sub = "".join(f"<th>{html.escape(c)}</th>" for _, g in groups for c, _ in g) + "".join(
        f"<th>{html.escape(c)}</th>" for c in extra)
    body = []
    for r in rows:
        st = str(r.get("status") or "")
        cells = []
        for _, g in groups:
            for i, (c, fn) in enumerate(g):
                cls = ' class="first"' if i == 0 else ""
                if c == "findings":
                    cls = ' class="first wrap"'
                if c == "verdict":
                    cls = (' class="failed"' if st == "failed" else
                           f' class="v-{html.escape(str(r.get("verdict") or ""))}"')
                cells.append(f"<td{cls}>{fn(r)}</td>")
        cells += [f"<td>{html.escape('' if r.get(c) is None else str(r.get(c)))}</td>"
                  for c in extra]
        body.append("<tr>" + "".join(cells) + "</tr>")
        if r.get("error"):
            body.append(f"<tr class=err><td colspan={n_cols}>{html.escape(str(r['error']))}"
                        "</td></tr>")
        elif r.get("verdict") not in (None, "OK") and r.get("verdict_reason"):
            # why a recording is not OK, under its row: the status alone does not say
            body.append(f"<tr class=why><td colspan={n_cols}>{html.escape(str(r['name']))} is "
                        f"{html.escape(str(r['verdict']))}: "
                        f"{html.escape(minus_text(str(r['verdict_reason'])))}</td></tr>")
    n_fail = sum(1 for r in rows if r.get("status") == "failed")
    png = campaign_figure(rows)
    fig = "" if png is None else (
        "<figure><img alt='misalignment of each calibration run' src='data:image/png;base64,"
        + base64.b64encode(png).decode("ascii") + "'></figure>")
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font-family: sans-serif; margin: 1em; color: #222; }}
table {{ border-collapse: collapse; font-size: 12.5px; }}
th, td {{ border: 1px solid #ccc; padding: 0.2em 0.35em; text-align: right;
  white-space: nowrap; }}
td:first-child {{ text-align: left; }}
th {{ background: #eee; font-weight: normal; }}
th.group {{ font-weight: bold; text-align: center; white-space: normal; }}
td.first, th.group {{ border-left: 2px solid #888; }}
td small {{ color: #666; }} td.wrap {{ white-space: normal; text-align: left;
  min-width: 9em; }}
td.failed {{ background: #fdd; }} td.ok, td.reused {{ background: #dfd; }}
td.v-OK {{ background: #d4edda; }} td.v-QUESTIONABLE {{ background: #fff3cd; }}
td.v-REFUSED {{ background: #f8d7da; }}
tr.err td {{ text-align: left; background: #fff0f0; white-space: normal; }}
tr.why td {{ text-align: left; background: #fffbea; white-space: normal; font-size: 12px; }}
img {{ max-width: 100%; }}
div.maps {{ display: flex; flex-wrap: wrap; gap: 0.8em; }}
figure.map {{ margin: 0; width: 440px; }} figure.map img {{ width: 440px; }}
figure.map figcaption {{ font-size: 13px; }}
span.verdict {{ padding: 0 0.3em; }} span.v-OK {{ background: #d4edda; }}
span.v-QUESTIONABLE {{ background: #fff3cd; }} span.v-REFUSED {{ background: #f8d7da; }}
</style></head><body>
<h1>{html.escape(title)}</h1>
<p>{len(rows)} recording(s), {n_fail} failed. Each name links to its report.
Misalignment: the rotation vector of R_body_mag in degrees about the body axes, &plusmn; 1 sigma
(&infin;: not determined by that recording's motion); fields in nT; &tau; in ms; fluctuation:
the range of the field after calibration as a percentage of before (Li et al. 2020, Table 4;
smaller is better).</p>
{fig}
<table><thead><tr>{top}</tr><tr>{sub}</tr></thead><tbody>
{chr(10).join(body)}
</tbody></table>
{maps_html(rows, out_dir)}
</body></html>
"""

"""Figures (PNG, matplotlib Agg) and a self-contained ``report.html`` per recording.

Figures, written beside the report:

- ``fig_enu.png`` (the main figure; Li 2020 Figs. 5 and 8): east, north and up components
  over time, before (attitude only) and after calibration; the right column shows the
  calibrated series alone at its own scale;
- ``fig_residual.png``: residual per mag axis over time, segments shaded;
- ``fig_trajectory.png`` (Li 2020 Fig. 7): the field in the body frame before and after
  calibration beside the ideal one (circles for rotations about one axis);
- ``fig_attitude.png``: heading, pitch and roll (Li 2020 Euler angles), segments shaded;
- one figure per diagnosis finding, when DIAGNOSE's ``stages.diagnose.finding_figures``
  exists (hook: ``finding_figures(diagnosis) -> list[(title, png bytes)]``).

``report.html`` embeds every figure as a base64 ``data:`` URI and carries no external
``src``/``href``: it opens offline as a single file. Sections: recording, metrics table
(Li 2020 Table 4), calibration with 1-sigma values, warnings (observability), diagnosis.
"""

from __future__ import annotations

import base64
import html
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from pipeline.atomic import atomic_path, write_text_atomic
from pipeline.recording import Context, Recording, Segment

BEFORE = "#e6781e"
AFTER = "#1e6edc"
IDEAL = "#28aa3c"
AXIS_COLORS = ("#dc3232", "#32b432", "#3c5ae6")
ENU_LABELS = ("east", "north", "up")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _png(fig: Any) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    _plt().close(fig)
    return buf.getvalue()


def _shade(ax: Any, segments: tuple[Segment, ...] | None, t0_ns: int) -> None:
    for i, s in enumerate(segments or ()):
        ax.axvspan((s.start_ns - t0_ns) * 1e-9, (s.end_ns - t0_ns) * 1e-9,
                   color="0.85" if i % 2 == 0 else "0.92", zorder=0, lw=0)


def _decimate(n: int, max_points: int) -> np.ndarray:
    return np.arange(0, n, max(1, int(np.ceil(n / max_points))))


def _envelope(t: np.ndarray, v: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Min/max per bin, interleaved, so a decimated line keeps the series' full range."""
    n = len(t)
    if n <= max_points:
        return t, v
    nb = max_points // 2
    edges = np.linspace(0, n, nb + 1).astype(int)
    starts = edges[:-1]
    with np.errstate(invalid="ignore"):
        lo = np.fmin.reduceat(v, starts)
        hi = np.fmax.reduceat(v, starts)
    tt = np.repeat(t[starts], 2)
    vv = np.stack([lo, hi], -1).ravel()
    return tt, vv


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
    dpi: int = 90,
    max_points: int = 8000,
    restored: Any = None,
) -> dict[str, bytes]:
    """Render the report's figures.

    Parameters
    ----------
    recording : Recording
        With ``attitude`` filled.
    calibration : Calibration
        The model to restore with.
    segments : tuple of Segment, optional
        Shaded in the time plots.
    max_gap_s : float or None
        Attitude gap bridged by interpolation.
    dpi : int
        Resolution of the PNGs.
    max_points : int
        Most points drawn per series (longer series: min/max envelope per bin, so the
        plotted range is the true fluctuation range).
    restored : RestoreResult, optional
        ``ctx.restored``; computed when not given.

    Returns
    -------
    dict of str to bytes
        File name (``fig_*.png``) -> PNG bytes.

    """
    from pipeline.geometry import quat_to_li2020_euler
    from stages.restore import restore_samples, view_data

    plt = _plt()
    if restored is None:
        restored = restore_samples(recording, calibration, max_gap_s=max_gap_s)
    vd = view_data(restored, calibration.R_body_mag)
    sel = _decimate(len(vd.t_s), max_points)
    t = vd.t_s[sel]
    t0 = int(vd.t_ns[0]) if len(vd.t_ns) else 0
    out: dict[str, bytes] = {}

    # Li 2020 Figs. 5 and 8: ENU components before and after calibration.
    fig, axes = plt.subplots(3, 2, figsize=(12, 7.5), dpi=dpi, sharex=True,
                             gridspec_kw={"width_ratios": [3, 2]})
    for k, name in enumerate(ENU_LABELS):
        a, b = axes[k]
        tu, unc = _envelope(vd.t_s, vd.uncalibrated_enu_nT[:, k], max_points)
        tc, cal = _envelope(vd.t_s, vd.calibrated_enu_nT[:, k], max_points)
        _shade(a, segments, t0)
        a.plot(tu, unc, color=BEFORE, lw=0.7, label="uncalibrated (attitude only)")
        a.plot(tc, cal, color=AFTER, lw=0.9, alpha=0.85, label="calibrated")
        a.set_ylabel(f"{name} (nT)")
        a.grid(alpha=0.3)
        _shade(b, segments, t0)
        b.plot(tc, cal, color=AFTER, lw=0.6)
        b.axhline(vd.B_enu_nT[k], color=IDEAL, lw=1.0, ls="--", label="reference B")
        b.grid(alpha=0.3)
        if k == 0:
            a.legend(loc="upper right", fontsize=8)
            b.legend(loc="upper right", fontsize=8)
            a.set_title("field in ENU: before and after calibration")
            b.set_title("after calibration (own scale)")
    axes[2, 0].set_xlabel("time (s)")
    axes[2, 1].set_xlabel("time (s)")
    fig.subplots_adjust(left=0.08, right=0.99, bottom=0.08, top=0.95, wspace=0.17, hspace=0.12)
    out["fig_enu.png"] = _png(fig)

    # Residuals per mag axis.
    fig, ax = plt.subplots(figsize=(12, 3.5), dpi=dpi)
    _shade(ax, segments, t0)
    t_res, r_res = residual_figure_data(vd)
    for k, c in enumerate("xyz"):
        ax.plot(*_envelope(t_res, r_res[:, k], max_points), color=AXIS_COLORS[k],
                lw=0.6, label=f"{c}")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("residual, mag frame (nT)")
    ax.set_title("measured minus predicted by the fitted model")
    ax.legend(loc="upper right", fontsize=8, ncol=3)
    ax.grid(alpha=0.3)
    fig.subplots_adjust(left=0.08, right=0.99, bottom=0.15, top=0.9)
    out["fig_residual.png"] = _png(fig)

    # Li 2020 Fig. 7: the field in the body frame, before / after / ideal.
    fig = plt.figure(figsize=(7, 6), dpi=dpi)
    ax3 = fig.add_subplot(projection="3d")
    sel3 = _decimate(len(vd.t_s), min(max_points, 4000))
    # The ideal goes first, broad and pale, so that "after" (on top of it when the
    # calibration is right) stays visible.
    for arr, color, label, ms, alpha in (
        (vd.body_ideal_nT, IDEAL, "ideal (C_body_enu B)", 5.0, 0.25),
        (vd.body_before_nT, BEFORE, "before (raw, axes taken as aligned)", 1.5, 0.8),
        (vd.body_after_nT, AFTER, "after calibration", 1.0, 0.9),
    ):
        p = arr[sel3]
        p = p[np.isfinite(p).all(axis=1)]
        ax3.plot(p[:, 0], p[:, 1], p[:, 2], ".", ms=ms, color=color, alpha=alpha, label=label)
    ax3.set_xlabel("x (nT)")
    ax3.set_ylabel("y (nT)")
    ax3.set_zlabel("z (nT)")
    ax3.set_title("field in the body frame")
    ax3.legend(loc="upper left", fontsize=8)
    fig.subplots_adjust(left=0.0, right=0.95, bottom=0.03, top=0.95)
    out["fig_trajectory.png"] = _png(fig)

    # Attitude.
    fig, ax = plt.subplots(figsize=(12, 3.5), dpi=dpi)
    _shade(ax, segments, t0)
    v = vd.valid[sel]
    h, p, r = quat_to_li2020_euler(vd.q_enu_body[sel])
    for ang, name, color in ((h, "heading", AXIS_COLORS[2]), (p, "pitch", AXIS_COLORS[0]),
                             (r, "roll", AXIS_COLORS[1])):
        ax.plot(t[v], np.degrees(ang[v]), ".", ms=1, color=color, label=name)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("deg")
    ax.set_title("attitude (Li 2020 Euler angles); segments shaded")
    ax.legend(loc="upper right", fontsize=8, ncol=3, markerscale=6)
    ax.grid(alpha=0.3)
    fig.subplots_adjust(left=0.08, right=0.99, bottom=0.15, top=0.9)
    out["fig_attitude.png"] = _png(fig)
    return out


def _fmt(x: Any, nd: int = 3) -> str:
    if x is None:
        return "&ndash;"
    if isinstance(x, float | np.floating):
        return "&infin;" if not np.isfinite(x) else f"{x:.{nd}f}"
    return html.escape(str(x))


def _vec(a: Any, nd: int = 3) -> str:
    if a is None:
        return "&ndash;"
    return "[" + ", ".join(_fmt(float(x), nd) for x in np.asarray(a, dtype=float).ravel()) + "]"


def _short(x: Any) -> str:
    """Compact JSON of finding params / windows: floats to 4 significant digits."""
    def r(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: r(w) for k, w in v.items()}
        if isinstance(v, list | tuple):
            return [r(w) for w in v]
        if isinstance(v, float):
            return float(f"{v:.4g}") if np.isfinite(v) else None
        return v

    return html.escape(json.dumps(r(x)))


def _img(data: bytes, alt: str) -> str:
    b64 = base64.b64encode(data).decode("ascii")
    return f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{b64}"></figure>'


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
        text += (f"; {n_stamp} with an attitude at the sensing time t - tau but none at their "
                 "own stamp (restored, not compared with the uncalibrated field)")
    return text


def samples_text(cal: Any) -> str:
    """Return the calibration's ``n_samples`` with what it counts (the samples fitted)."""
    n = int(cal.n_samples)
    fs = (getattr(cal, "checks", None) or {}).get("fit_samples")
    if isinstance(fs, dict) and fs.get("stride", 1) and int(fs.get("stride", 1)) > 1:
        k = int(fs["stride"])
        nth = {2: "2nd", 3: "3rd"}.get(k, f"{k}th")
        return (f"{n} (every {nth} of {int(fs.get('of', 0))} samples with an attitude, "
                f"decimated for the diagnosis fit{fs.get('note', '')})")
    if isinstance(fs, dict):
        return f"{n} (every sample with an attitude{fs.get('note', '')})"
    held = getattr(cal, "sample_hold", None)
    if held:
        return f"{n} (samples with an attitude, sample-and-hold repeats left out)"
    return f"{n} (samples with an attitude fitted by the estimator)"


def _metrics_html(metrics: Any) -> str:
    if metrics is None:
        return "<p>No metrics.</p>"
    rows = []
    for s in metrics.scopes:
        for c in ("x", "y", "z"):
            comp = s.components[c]
            cal, unc, r = comp["calibrated"], comp["uncalibrated"], comp["ratio_pct"]
            rows.append(
                "<tr>"
                f"<td>{html.escape(s.scope)}</td><td>{html.escape(s.kind)}</td>"
                f"<td>{c}</td><td>{s.n_samples}</td>"
                + "".join(
                    f"<td>{_fmt(unc[k], 1)}</td><td>{_fmt(cal[k], 2)}</td><td>{_fmt(r[k], 2)}</td>"
                    for k in ("fluctuation_range_nT", "absolute_deviation_nT", "std_nT")
                )
                + "</tr>"
            )
    head = (
        "<tr><th rowspan=2>scope</th><th rowspan=2>kind</th><th rowspan=2>ENU</th>"
        "<th rowspan=2>n</th><th colspan=3>fluctuation range (nT)</th>"
        "<th colspan=3>absolute deviation (nT)</th><th colspan=3>standard deviation (nT)</th>"
        "</tr><tr>" + "<th>before</th><th>after</th><th>ratio %</th>" * 3 + "</tr>"
    )
    extra = f"<p>{counts_text(metrics)}.</p>"
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
    return f"<table>{head}{''.join(rows)}</table>{extra}"


def _calibration_html(cal: Any) -> str:
    rows = [
        ("estimator", html.escape(str(cal.estimator))),
        ("rotation vector R_body_mag (deg)", _vec(cal.rotvec_body_mag_deg, 4)),
        ("1-sigma (deg)", _vec(cal.sigma_rotvec_deg, 4)),
        ("|rotation| (deg)", _fmt(float(np.linalg.norm(cal.rotvec_body_mag_deg)), 4)),
    ]
    if cal.rotvec_from_nominal_deg is not None:
        rows.append(("from nominal (deg)", _vec(cal.rotvec_from_nominal_deg, 4)))
    rows += [
        ("offset o (nT)", _vec(cal.offset_nT, 2)),
        ("1-sigma offset (nT)", _vec(cal.sigma_offset_nT, 2)),
        ("D", _vec(cal.D, 5)),
        ("time offset tau (s)", _fmt(cal.time_offset_s, 5)),
        ("1-sigma tau (s)", _fmt(cal.sigma_time_offset_s, 5)),
        ("B_enu (nT)", _vec(cal.B_enu_nT, 1)),
        ("1-sigma B_enu (nT)", _vec(cal.sigma_B_enu_nT, 2)),
        ("residual rms (nT)", _fmt(float(cal.residual_rms_nT), 3)),
        ("samples", html.escape(samples_text(cal))),
        ("unobservable axes (body)",
         ", ".join(_vec(a, 3) for a in cal.unobservable_axes_body) or "none"),
    ]
    if cal.effects:
        rows.append(("further effects", html.escape(", ".join(sorted(cal.effects)))))
    body = "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows)
    return f"<table class=kv>{body}</table>"


_VERDICT_COLOUR = {"OK": "#d4edda", "QUESTIONABLE": "#fff3cd", "REFUSED": "#f8d7da"}


def _residual_html(restored: Any) -> str:
    if restored is None:
        return ""
    rms = f"<span id=residual_rms_nT>{restored.residual_rms_nT:.7g}</span>"
    return (f"<p>Residual of the final model (every term of the calibration, diagnosed effects "
            f"included): {rms} nT RMS over {int(np.count_nonzero(restored.valid))} samples "
            "with a usable attitude.</p>")


def _verdict_html(cal: Any) -> str:
    """Return the verdict box for the top of the report: one-line summary and reason."""
    from stages.estimate import verdict_line

    v = getattr(cal, "verdict", None)
    status = "not judged" if v is None else v.status.value
    colour = _VERDICT_COLOUR.get(status, "#eee")
    reason = "" if v is None else f"<p>{html.escape(v.reason)}</p>"
    ne = "".join(f"<li>{html.escape(d['term'])}: {html.escape(d['reason'])}</li>"
                 for d in getattr(cal, "not_estimated", ()))
    ne = f"<p>Not estimated:</p><ul>{ne}</ul>" if ne else ""
    neff = getattr(cal, "n_eff", None)
    neff_html = "" if neff is None else (
        f"<p>Sigmas from {neff:.0f} effective independent samples of {int(cal.n_samples)} "
        "(residuals correlated in time; block sandwich and split-half check).</p>")
    return (f"<div class=verdict style='background:{colour};border:1px solid #999;"
            f"padding:.5em 1em;font-size:15px'><b>Verdict: {html.escape(status)}</b> &mdash; "
            f"{html.escape(verdict_line(cal))}{reason}{ne}{neff_html}</div>")


def _diagnosis_html(diagnosis: Any) -> tuple[str, list[tuple[str, bytes]]]:
    if diagnosis is None:
        return "<p>Not diagnosed.</p>", []
    d = diagnosis.to_dict() if hasattr(diagnosis, "to_dict") else dict(diagnosis)
    parts = []
    for key in ("baseline", "final"):
        b = d.get(key) or {}
        parts.append(
            f"<p><b>{key}</b>: effects {html.escape(', '.join(b.get('effects', [])) or 'none')}; "
            f"residual rms {_fmt(b.get('residual_rms_nT'), 3)} nT; held-out rms "
            f"{_fmt(b.get('heldout_rms_nT'), 3)} nT</p>"
        )
    rows = []
    for f in d.get("findings", []):
        ev = f.get("evidence") or {}
        where = f.get("where") or {}
        rows.append(
            f"<tr><td>{html.escape(str(f.get('effect')))}</td>"
            f"<td>{_short(f.get('params'))}</td>"
            f"<td>{_fmt(ev.get('delta_bic'), 1)}</td>"
            f"<td>{_fmt(ev.get('rms_before_nT'), 3)} &rarr; {_fmt(ev.get('rms_after_nT'), 3)}</td>"
            f"<td>{_fmt(ev.get('heldout_rms_before_nT'), 3)} &rarr; "
            f"{_fmt(ev.get('heldout_rms_after_nT'), 3)}</td>"
            f"<td>{_short(where.get('windows_s') or [])}</td>"
            f"<td>{html.escape(str(f.get('explanation', '')))}</td></tr>"
        )
    if rows:
        parts.append(
            "<table><tr><th>effect</th><th>params</th><th>&Delta;BIC</th><th>rms (nT)</th>"
            "<th>held-out rms (nT)</th><th>windows (s)</th><th>explanation</th></tr>"
            + "".join(rows) + "</table>"
        )
    else:
        parts.append("<p>No finding: the model explains the data.</p>")
    ni = d.get("not_identifiable") or []
    if ni:
        parts.append(
            "<p>Not identifiable from this motion: "
            + "; ".join(html.escape(f"{x.get('effect')}: {x.get('reason')}") for x in ni)
            + "</p>"
        )
    figs: list[tuple[str, bytes]] = []
    try:
        from stages.diagnose import finding_figures
    except ImportError:
        finding_figures = None
    if finding_figures is not None and not isinstance(diagnosis, dict):
        figs = list(finding_figures(diagnosis))
    return "".join(parts), figs


CSS = """
body{font-family:sans-serif;margin:1.5em;max-width:1250px;color:#222}
table{border-collapse:collapse;margin:.5em 0;font-size:13px}
td,th{border:1px solid #bbb;padding:2px 6px;text-align:right}
th{background:#eee} table.kv th{text-align:left}
figure{margin:.5em 0} img{max-width:100%}
.warn{background:#fff3cd;border:1px solid #e0c36c;padding:.4em .8em}
"""


def render_html(
    recording: Recording,
    calibration: Any,
    metrics: Any,
    diagnosis: Any,
    figures: dict[str, bytes],
    restored: Any = None,
) -> str:
    """Return the self-contained report text (figures inline as base64).

    ``restored``: the restore result; its final-model residual RMS is quoted by the residual
    figure (the same number as ``diagnosis.json``'s final residual when diagnosed).
    """
    stem = Path(recording.path).stem
    warn = "".join(f"<li>{html.escape(w)}</li>" for w in calibration.warnings)
    if calibration.unobservable_axes_body:
        warn += "<li>rotation about " + ", ".join(
            _vec(a, 3) for a in calibration.unobservable_axes_body
        ) + " (body) is not determined by this recording</li>"
    probs = "".join(
        f"<li>{html.escape(p.code)}: {html.escape(p.message)}</li>" for p in recording.problems
    )
    diag_html, diag_figs = _diagnosis_html(diagnosis)
    channels = "".join(
        f"<tr><td>{html.escape(c.topic)}</td><td>{html.escape(c.type)}</td>"
        f"<td>{html.escape(str(getattr(c.role, 'value', c.role)))}</td><td>{c.count}</td>"
        f"<td>{_fmt(c.rate_hz, 2)}</td></tr>"
        for c in recording.channels
    )
    fig_html = {k: _img(v, k) for k, v in figures.items()}
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>magalign: {html.escape(stem)}</title>
<style>{CSS}</style></head><body>
<h1>magalign report: {html.escape(stem)}</h1>
{_verdict_html(calibration)}
<p>Recording <code>{html.escape(Path(recording.path).name)}</code>,
{recording.duration_s:.1f} s, {len(recording.mag)} magnetometer samples on
<code>{html.escape(recording.mag_topic)}</code>, attitude on
<code>{html.escape(str(recording.attitude_topic))}</code>.</p>
<table><tr><th>topic</th><th>type</th><th>role</th><th>count</th><th>rate (Hz)</th></tr>
{channels}</table>
{f'<div class=warn><b>Problems handled while reading</b><ul>{probs}</ul></div>' if probs else ''}
<h2>Field before and after calibration</h2>
{fig_html.get('fig_enu.png', '')}
<h2>Metrics (Li et al. 2020, Table 4)</h2>
{_metrics_html(metrics)}
<h2>Calibration</h2>
{_calibration_html(calibration)}
{f'<div class=warn><b>Warnings</b><ul>{warn}</ul></div>' if warn else '<p>No warning.</p>'}
<h2>Residuals</h2>
{_residual_html(restored)}
{fig_html.get('fig_residual.png', '')}
<h2>Field in the body frame (Li 2020, Fig. 7)</h2>
{fig_html.get('fig_trajectory.png', '')}
<h2>Attitude and segments</h2>
{fig_html.get('fig_attitude.png', '')}
<h2>Diagnosis</h2>
{diag_html}
{''.join(f'<h3>{html.escape(t)}</h3>' + _img(b, t) for t, b in diag_figs)}
</body></html>
"""


def write_report(
    out_dir: str | Path,
    recording: Recording,
    calibration: Any,
    metrics: Any = None,
    diagnosis: Any = None,
    segments: tuple[Segment, ...] | None = None,
    *,
    max_gap_s: float | None = None,
    restored: Any = None,
) -> Path:
    """Write the figures and ``report.html`` into ``out_dir``; returns the report's path.

    ``restored``: the :class:`stages.restore.RestoreResult` (``ctx.restored``); computed when
    not given.
    """
    from stages.restore import restore_samples

    out = Path(out_dir)
    if restored is None:
        restored = restore_samples(recording, calibration, max_gap_s=max_gap_s)
    figures = make_figures(recording, calibration, segments, max_gap_s=max_gap_s,
                           restored=restored)
    for name, data in figures.items():
        with atomic_path(out / name, (recording.path,)) as tmp:
            tmp.write_bytes(data)
    text = render_html(recording, calibration, metrics, diagnosis, figures, restored=restored)
    return write_text_atomic(out / "report.html", text)


@dataclass(frozen=True)
class Report:
    """Stage: PNG figures and ``report.html`` in ``out_dir`` (module docstring).

    Parameters
    ----------
    out_dir : str
    max_gap_s : float or None
        Attitude gap bridged by interpolation.

    """

    out_dir: str
    max_gap_s: float | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"outputs"})

    def run(self, ctx: Context) -> Context:
        """Write the report and list it in ``ctx.outputs``."""
        p = write_report(self.out_dir, ctx.recording, ctx.calibration, ctx.metrics,
                         ctx.diagnosis, ctx.segments, max_gap_s=self.max_gap_s,
                         restored=ctx.restored)
        return ctx.replace(outputs=ctx.outputs + (("report.html", str(p)),))

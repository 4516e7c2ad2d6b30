"""Sentences for the report: what each diagnosis finding means, with units and times.

The report speaks to the person who made the recording: one row per physical event (the
windows of ``disturbance`` and ``hard_iron_step`` findings that touch are one event: a
magnet brought near and taken away is found as several steps), each as a sentence with its
size in units, its time from the start of the recording and in UTC, and how much better the
model fits data it was not fitted to (held-out). Nothing here computes a result: the numbers
are the diagnosis's own (``diagnosis.json``, CONVENTIONS "Output files").
"""

from __future__ import annotations

import datetime as dt
import html
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.core.style import minus

#: the effects that live in time windows (one row per event)
LOCAL = ("disturbance", "hard_iron_step")
#: windows closer than this (s) belong to the same event
EVENT_GAP_S = 2.0


def utc(t0_ns: int, t_s: float) -> str:
    """Return ``HH:MM:SS`` (UTC) of ``t_s`` seconds after ``t0_ns``."""
    t = dt.datetime.fromtimestamp(round(t0_ns / 1e9 + float(t_s)), tz=dt.timezone.utc)
    return t.strftime("%H:%M:%S")


def span(t0_ns: int, a: float, b: float) -> str:
    """Return ``12.3 s to 18.9 s (14:02:11 to 14:02:17 UTC)``."""
    return f"{a:.1f} s to {b:.1f} s ({utc(t0_ns, a)} to {utc(t0_ns, b)} UTC)"


def num(x: float, nd: int = 1) -> str:
    """Return a number with ``nd`` decimals and a true minus sign."""
    return minus(f"{x:.{nd}f}")


def vec(a: Any, nd: int = 1) -> str:
    """Return ``[1.0, −2.0, 3.0]``."""
    return "[" + ", ".join(num(float(x), nd) for x in np.asarray(a, float).ravel()) + "]"


def pm_vec(a: Any, s: Any, nd: int = 1) -> str:
    """Return ``[1.0 ± 0.1, ...]`` (``±`` omitted where the sigma is missing)."""
    a = np.asarray(a, float).ravel()
    s = np.asarray(s if s is not None else np.full(a.shape, np.nan), float).ravel()
    parts = [num(x, nd) + (f" \u00b1 {sx:.{nd}f}" if np.isfinite(sx) else "")
             for x, sx in zip(a, s, strict=False)]
    return "[" + ", ".join(parts) + "]"


def per_metre(g_nT_per_m: float) -> str:
    """Return a field gradient in the unit that shows its value: ``3.47 µT/m``, ``2.0 nT/m``.

    Microtesla per metre from 1 µT/m up, nanotesla per metre below (a gradient of 2 nT/m
    must not read "0.00 µT/m").
    """
    g = abs(float(g_nT_per_m))
    if not np.isfinite(g):
        return "an unknown amount per metre"
    if g >= 1000.0:
        return f"{g / 1e3:.2f} \u00b5T/m"
    return f"{g:.0f} nT/m" if g >= 10.0 else f"{g:.1f} nT/m"


def evidence_words(delta_bic: float | None) -> str:
    """Plain words for a BIC drop (Kass and Raftery 1995): how strongly the data ask for it."""
    if delta_bic is None or not np.isfinite(delta_bic):
        return "not scored"
    d = -float(delta_bic)
    if d > 10:
        return "very strong"
    if d > 6:
        return "strong"
    if d > 2:
        return "positive"
    return "weak"


def what(f: dict[str, Any]) -> str:
    """Return the sentence saying what a (non-local) finding is, with its size and units."""
    e = f.get("effect")
    p = f.get("params") or {}
    s = f.get("sigma") or {}
    if e == "hard_iron":
        o = np.asarray(p["offset_nT"], float)
        return (f"A constant offset (hard iron: magnetised parts near the sensor, or its own "
                f"bias) of {pm_vec(o, s.get('offset_nT'))} nT along the magnetometer's x, y, "
                f"z ({np.linalg.norm(o):.0f} nT in all).")
    if e == "soft_iron":
        d = np.asarray(p["D"], float)
        gains = 100 * (np.diag(d) - 1)
        off = d[~np.eye(3, dtype=bool)]
        return (f"Soft iron or unequal axis gains: the gains differ from 1 by "
                f"{vec(gains, 2)} % (x, y, z) and the axes couple by up to "
                f"{100 * np.max(np.abs(off)):.2f} %.")
    if e == "time_offset":
        tau = 1e3 * float(p["time_offset_s"])
        st = s.get("time_offset_s")
        # the digits of the calibration table and the verdict line: one value everywhere
        sig = f" \u00b1 {1e3 * float(st):.2f}" if st is not None and np.isfinite(st) else ""
        late = "late" if tau > 0 else "early"
        return (f"The magnetometer's time stamps are {late} by {abs(tau):.2f}{sig} ms against "
                f"the attitude (\u03c4 = {num(tau, 2)} ms).")
    if e == "eddy_current":
        ed = 1e3 * np.diag(np.asarray(p["E_s"], float))
        return (f"Eddy currents: the reading lags changes of the field by {vec(ed, 2)} ms "
                f"(x, y, z).")
    if e == "field_drift":
        return (f"The background field drifted during the recording by "
                f"{vec(p['peak_to_peak_nT'])} nT peak to peak (east, north, up).")
    if e == "axis_tilt":
        return (f"The turntable's axis is tilted by {float(p['tilt_deg']):.3f}\u00b0 towards "
                f"azimuth {float(p['azimuth_deg']):.0f}\u00b0.")
    if e == "field_gradient":
        g = float(np.linalg.norm(np.asarray(p["G_nT_per_m"], float)))
        frame = ("the attitude source's own frame" if p.get("position_frame")
                 == "attitude_source_local" else "local east, north, up")
        return (f"The field varies from place to place: a gradient of {per_metre(g)} (all "
                f"directions together) as the sensor moves (positions in {frame}).")
    if e == "heading_drift":
        return (f"The attitude source's heading drifts by {num(float(p['rate_deg_per_h']), 2)}"
                f"\u00b0/h ({float(p['peak_to_peak_deg']):.2f}\u00b0 peak to peak).")
    if e == "local_source":
        pos = np.asarray(p["position_m"], float)
        sp = s.get("position_m")
        frame = ("the motion-capture room's frame" if p.get("position_frame")
                 == "attitude_source_local" else "local east, north, up")
        where = ""
        if p.get("closest_approach_m") is not None:
            where = (f"; the sensor passed {100 * float(p['closest_approach_m']):.0f} cm from "
                     f"it at {float(p['closest_approach_s']):.1f} s")
        where_at = vec(pos, 3) + " m"
        if sp is not None and np.all(np.isfinite(sp)):
            # the sigma in cm with the digits it has (a located source is often sub-cm)
            sc = 100 * np.asarray(sp, float)
            nd = 1 if float(np.min(sc)) >= 0.1 else 2
            where_at += " \u00b1 " + vec(sc, nd) + " cm"
        return (f"A magnetised object fixed in the surroundings (not on the sensor): located "
                f"at {where_at} in {frame}, moment "
                f"{float(np.linalg.norm(p['moment_Am2'])):.3g} A m²{where}. The restored "
                "field keeps it.")
    if e == "field_map":
        p2p = np.asarray(p["peak_to_peak_nT"], float)
        return (f"Beyond the linear gradient the field varies smoothly over the area the "
                f"sensor covered, by {vec(p2p)} nT peak to peak (east, north, up), mapped with "
                f"{int(p['n_basis'])} basis functions (length scale "
                f"{float(p['length_scale_m']):.2f} m). The restored field keeps it.")
    if e == "lever_arm":
        lv = 100 * np.asarray(p["lever_arm_body_m"], float)
        sl = s.get("lever_arm_body_m")
        return (f"The magnetometer sits {np.linalg.norm(lv):.1f} cm from the tracked point: "
                f"{pm_vec(lv, None if sl is None else 100 * np.asarray(sl, float), 1)} cm "
                "along the body's x, y, z.")
    if e == "sample_hold":
        return (f"The sensor samples at {float(p['native_rate_hz']):.1f} Hz, slower than its "
                f"messages: {100 * float(p['repeated_fraction']):.1f} % of them repeat a "
                "sample.")
    return f"{e}."


@dataclass
class Row:
    """One row of the findings table: a global effect, or one physical event in time."""

    sentence: str
    when: str
    fit: str
    evidence: str
    effects: list[str] = field(default_factory=list)
    explanation: str = ""


def _fit_text(first: dict[str, Any], last: dict[str, Any]) -> str:
    a, b = first.get("evidence") or {}, last.get("evidence") or {}
    hb, ha = a.get("heldout_rms_before_nT"), b.get("heldout_rms_after_nT")
    fb, fa = a.get("rms_before_nT"), b.get("rms_after_nT")
    parts = []
    if hb is not None and ha is not None:
        parts.append(f"on held-out data from {hb:.1f} to {ha:.1f} nT")
    if fb is not None and fa is not None:
        parts.append(f"(fitted data {fb:.1f} to {fa:.1f} nT)")
    return " ".join(parts) or "\u2013"


def _when(f: dict[str, Any]) -> str:
    """When a finding acted: "whole recording", or the passes of a source fixed nearby.

    A term present throughout has one ``where`` window from the first sample on; a source
    fixed in the surroundings acts where the sensor passes it (its ``where`` windows).
    """
    wins = (f.get("where") or {}).get("windows_s") or []
    if f.get("effect") != "local_source" or not wins or (
            len(wins) == 1 and float(wins[0][0]) == 0.0):
        return "whole recording"
    spans = ", ".join(f"{float(a):.1f}\u2013{float(b):.1f}" for a, b in wins)
    return f"{'passes' if len(wins) > 1 else 'pass'} at {spans} s"


def rows(diagnosis: dict[str, Any], t0_ns: int) -> list[Row]:
    """Return the findings as table rows: local windows that touch are one event.

    The rows follow the diagnosis (``diagnosis.json``'s findings, the order the evidence
    was measured in): an event stands where its first finding does, so that each row's
    improvement starts where the one before it ended.

    Parameters
    ----------
    diagnosis : dict
        ``diagnosis.json`` content.
    t0_ns : int
        Stamp of the first magnetometer sample (the windows count from it).

    """
    findings = list(diagnosis.get("findings") or [])
    placed: list[tuple[int, Row]] = []
    local: list[tuple[float, float, dict[str, Any]]] = []
    for k, f in enumerate(findings):
        if f.get("effect") in LOCAL:
            for a, b in (f.get("params") or {}).get("windows_s") or []:
                local.append((float(a), float(b), f))
            continue
        ev = f.get("evidence") or {}
        placed.append((k, Row(what(f), _when(f), _fit_text(f, f),
                              evidence_words(ev.get("delta_bic")), [str(f.get("effect"))],
                              str(f.get("explanation", "")))))
    local.sort(key=lambda x: x[0])
    events: list[list[tuple[float, float, dict[str, Any]]]] = []
    for w in local:
        if events and w[0] <= max(x[1] for x in events[-1]) + EVENT_GAP_S:
            events[-1].append(w)
        else:
            events.append([w])

    def index(f: dict[str, Any]) -> int:
        return next(i for i, g in enumerate(findings) if g is f)

    for ev in events:
        a, b = min(x[0] for x in ev), max(x[1] for x in ev)
        fs: list[dict[str, Any]] = []
        for _, _, f in ev:
            if not any(f is g for g in fs):
                fs.append(f)
        fs.sort(key=index)
        kinds = sorted({str(f.get("effect")) for f in fs})
        if kinds == ["disturbance"]:
            peak = max(float((f.get("params") or {}).get("peak_nT", np.nan)) for f in fs)
            head = f"A passing disturbance of {peak:.0f} nT (an external field: a vehicle, a " \
                   "person with steel, a lift)"
        else:
            offs = [np.asarray((f.get("params") or {}).get("offset_nT", [np.nan] * 3), float)
                    for f in fs if f.get("effect") == "hard_iron_step"]
            size = max(float(np.linalg.norm(o)) for o in offs) if offs else float("nan")
            head = (f"A magnet or magnetised object near the sensor, up to {size:.0f} nT "
                    f"(an offset that turns with the sensor)")
            if "disturbance" in kinds:
                head += " together with an external disturbance"
            if len(ev) > 1:
                head += f", found as {len(ev)} steps"
        edges = "; ".join(f"{x[0]:.1f}\u2013{x[1]:.1f} s" for x in ev) if len(ev) > 1 else ""
        when = span(t0_ns, a, b) + (f"; edges {edges}" if edges else "")
        bics = [x for x in ((f.get("evidence") or {}).get("delta_bic") for f in fs)
                if x is not None]
        placed.append((index(fs[0]), Row(
            f"{head} between {a:.1f} s and {b:.1f} s.", when, _fit_text(fs[0], fs[-1]),
            evidence_words(sum(bics) if bics else None), kinds,
            str(fs[0].get("explanation", "")))))
    placed.sort(key=lambda x: x[0])
    return [r for _, r in placed]


def rows_html(diagnosis: dict[str, Any], t0_ns: int) -> str:
    """Return the findings table (or a sentence when there is none)."""
    rs = rows(diagnosis, t0_ns)
    if not rs:
        return ("<p>No finding: the data ask for no term beyond the calibration's (the "
                "verdict above compares what is left with the sensor noise).</p>")
    body = "".join(
        "<tr>"
        f"<td class=l>{html.escape(r.sentence)}"
        f"<br><small title='{html.escape(r.explanation)}'>in diagnosis.json: "
        f"{html.escape(', '.join(r.effects))}</small></td>"
        f"<td class=l>{html.escape(r.when)}</td>"
        f"<td class=l>{html.escape(r.fit)}</td>"
        f"<td class=l>{html.escape(r.evidence)}</td></tr>"
        for r in rs
    )
    return ("<table class=findings><tr><th>what was found</th><th>when</th>"
            "<th>the fit improves</th><th>evidence</th></tr>" + body + "</table>")

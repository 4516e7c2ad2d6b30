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

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects import EFFECTS, kin_words

#: the effects that live in time windows (one row per event)
LOCAL = frozenset(k.value for k, e in EFFECTS.items() if e.event)
#: the effects' names, CONVENTIONS spelling
_NAMES = frozenset(k.value for k in EffectKind)
#: windows closer than this (s) belong to the same event
EVENT_GAP_S = 2.0


def utc(t0_ns: int, t_s: float) -> str:
    """Return ``HH:MM:SS`` (UTC) of ``t_s`` seconds after ``t0_ns``."""
    t = dt.datetime.fromtimestamp(round(t0_ns / 1e9 + float(t_s)), tz=dt.timezone.utc)
    return t.strftime("%H:%M:%S")


def span(t0_ns: int, a: float, b: float) -> str:
    """Return ``12.3 s to 18.9 s (14:02:11 to 14:02:17 UTC)``."""
    return f"{a:.1f} s to {b:.1f} s ({utc(t0_ns, a)} to {utc(t0_ns, b)} UTC)"


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
    """Return the sentence saying what a (non-local) finding is: its effect's own.

    (:meth:`pipeline.model.effects.base.Effect.sentence`); a name no effect has is read out.
    """
    e = str(f.get("effect"))
    if e not in _NAMES:
        return f"{e}."
    return EFFECTS[EffectKind(e)].sentence(f.get("params") or {}, f.get("sigma") or {})


def kin_sentences(findings: list[dict[str, Any]]) -> dict[int, str]:
    """Return what a finding's sentence adds about the others of its effect, by index.

    The effect's own words (:func:`pipeline.model.effects.kin_words`): several dipoles the
    data do not resolve apart are one object.
    """
    words = kin_words([str(f.get("effect")) for f in findings],
                      [f.get("params") or {} for f in findings], short=True)
    return {i: w for i, w in enumerate(words) if w}


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
    kin = kin_sentences(findings)
    placed: list[tuple[int, Row]] = []
    local: list[tuple[float, float, dict[str, Any]]] = []
    for k, f in enumerate(findings):
        if f.get("effect") in LOCAL:
            for a, b in (f.get("params") or {}).get("windows_s") or []:
                local.append((float(a), float(b), f))
            continue
        ev = f.get("evidence") or {}
        placed.append((k, Row(what(f) + kin.get(k, ""), _when(f), _fit_text(f, f),
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

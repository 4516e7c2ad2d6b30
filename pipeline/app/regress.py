"""Regression runs: compare a results folder with a stored baseline, within tolerances.

Both folders hold one sub-folder per recording with ``calibration.json``, ``metrics.json``
and ``diagnosis.json`` (CONVENTIONS formats). In RESULTS a recording counts only when its
done-marker is present (a run killed midway is never compared as finished); a BASELINE is a
results folder or a copy of one reduced to these small JSON files (``make golden``).

Tolerances per quantity are in :class:`Tolerances` (documented in ``docs/campaigns.md``);
a baseline folder may override them with a ``tolerances.toml`` holding a ``[tolerances]``
table of the same names (data only).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from pipeline.app.campaign import DONE_MARKER
from pipeline.app.summary import flatten_numbers
from pipeline.core.config import TomlDoc
from pipeline.core.errors import InputError
from pipeline.core.geometry import angle_between_deg
from pipeline.core.validate import check_calibration_dict, check_diagnosis_dict, check_metrics_dict

OK = "ok"
REGRESSION = "REGRESSION"
NEW = "new"


@dataclass(frozen=True)
class Tolerances:
    """Allowed differences between results and baseline, per quantity.

    Attributes
    ----------
    rotation_deg : float
        Angle of ``R_result @ R_baseline.T`` (deg).
    sigma_rel : float
        Relative change of each ``sigma_rotvec_deg`` component; an axis that becomes
        (un)observable (sigma null on one side only) is a regression.
    offset_nT, B_enu_nT : float
        Absolute, per component (nT).
    D : float
        Absolute, per element of the soft-iron matrix.
    time_offset_s : float
        Absolute (s).
    residual_rms_rel, residual_rms_nT : float
        ``residual_rms_nT`` may differ by ``max(rel * baseline, abs)``.
    metric_nT, metric_rel : float
        Every ``*_nT`` metric may differ by ``max(metric_nT, metric_rel * |baseline|)``.
    ratio_pct : float
        Every ``ratio_pct`` metric, absolute percentage points.
    finding_rel : float
        Relative tolerance of finding params without an absolute one below (also the
        relative part for ``*_nT`` params).
    finding_offset_nT, finding_D, finding_time_offset_s, finding_E_s, finding_windows_s,
    finding_tilt_deg, finding_azimuth_deg : float
        Absolute tolerances of the CONVENTIONS finding params of those names (``_nT``
        params: ``finding_offset_nT`` or the relative part, whichever is larger).

    """

    rotation_deg: float = 0.1
    sigma_rel: float = 0.25
    offset_nT: float = 5.0
    B_enu_nT: float = 20.0
    D: float = 0.01
    time_offset_s: float = 0.002
    residual_rms_rel: float = 0.10
    residual_rms_nT: float = 0.5
    metric_nT: float = 2.0
    metric_rel: float = 0.05
    ratio_pct: float = 2.0
    finding_rel: float = 0.20
    finding_offset_nT: float = 5.0
    finding_D: float = 0.01
    finding_time_offset_s: float = 0.002
    finding_E_s: float = 0.002
    finding_windows_s: float = 1.0
    finding_tilt_deg: float = 0.1
    finding_azimuth_deg: float = 5.0

    @classmethod
    def load(cls, path: str | Path) -> Tolerances:
        """Defaults overridden by the ``[tolerances]`` table of a TOML file."""
        doc = TomlDoc.load(path)
        doc.check_keys(doc.data, {"tolerances"})
        tab = doc.get("tolerances", {})
        names = {f.name for f in dataclasses.fields(cls)}
        doc.check_keys(tab, names, "tolerances")
        kw = {k: doc.number(f"tolerances.{k}", lo=0.0) for k in tab}
        return cls(**kw)


@dataclass(frozen=True)
class Diff:
    """One compared quantity (a row of the diff table)."""

    recording: str
    quantity: str
    baseline: str
    result: str
    diff: str
    tolerance: str
    status: str


def _fmt(x: Any) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:.6g}"
    if isinstance(x, list | tuple):
        return "[" + ", ".join(_fmt(v) for v in x) + "]"
    return str(x)


def _load(path: Path, check: Any = None) -> dict[str, Any] | None:
    """Read a result file: None when absent; checked by ``check(d, path)`` when given."""
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"not valid JSON: {exc}", path=path,
                         hint="regenerate the results (or the baseline with make golden)") from exc
    if not isinstance(d, dict):
        raise InputError("not a JSON object", path=path)
    if check is not None:
        check(d, path)
    return d


def recordings_in(folder: Path, *, need_marker: bool) -> list[str]:
    """Names of the finished recordings in a results or baseline folder."""
    out = []
    for sub in sorted(p for p in folder.iterdir() if p.is_dir()):
        if not (sub / "calibration.json").is_file():
            continue
        if need_marker and not (sub / DONE_MARKER).is_file():
            continue
        out.append(sub.name)
    return out


class _Cmp:
    def __init__(self, rec: str):
        self.rec = rec
        self.rows: list[Diff] = []

    def add(self, q: str, b: Any, r: Any, d: Any, tol: str, ok: bool) -> None:
        self.rows.append(Diff(self.rec, q, _fmt(b), _fmt(r), _fmt(d), tol,
                              OK if ok else REGRESSION))

    def abs_vec(self, q: str, b: Any, r: Any, tol: float) -> None:
        if b is None and r is None:
            return
        if b is None or r is None:
            self.add(q, b, r, None, f"both present: {tol:g}", False)
            return
        bb, rr = np.asarray(b, dtype=float), np.asarray(r, dtype=float)
        if bb.shape != rr.shape:
            self.add(q, b, r, None, "same shape", False)
            return
        d = float(np.max(np.abs(rr - bb))) if bb.size else 0.0
        self.add(q, b, r, d, f"<= {tol:g}", d <= tol)


def _compare_calibration(c: _Cmp, b: dict, r: dict, tol: Tolerances) -> None:
    try:
        Rb, Rr = np.asarray(b["R_body_mag"], float), np.asarray(r["R_body_mag"], float)
        ang = float(angle_between_deg(Rr, Rb))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"calibration of {c.rec} has no usable R_body_mag: {exc}") from exc
    c.add("rotation_deg", b.get("rotvec_body_mag_deg"), r.get("rotvec_body_mag_deg"), ang,
          f"<= {tol.rotation_deg:g} deg", ang <= tol.rotation_deg)
    sb = b.get("sigma_rotvec_deg") or [None] * 3
    sr = r.get("sigma_rotvec_deg") or [None] * 3
    for i, a in enumerate("xyz"):
        x0, x1 = sb[i], sr[i]
        if x0 is None or x1 is None:
            c.add(f"sigma_rotvec_deg.{a}", x0, x1, None, "both null or both finite",
                  x0 is None and x1 is None)
            continue
        rel = abs(x1 - x0) / max(abs(x0), 1e-12)
        c.add(f"sigma_rotvec_deg.{a}", x0, x1, rel, f"rel <= {tol.sigma_rel:g}",
              rel <= tol.sigma_rel)
    c.abs_vec("offset_nT", b.get("offset_nT"), r.get("offset_nT"), tol.offset_nT)
    c.abs_vec("D", b.get("D"), r.get("D"), tol.D)
    c.abs_vec("time_offset_s", b.get("time_offset_s"), r.get("time_offset_s"), tol.time_offset_s)
    c.abs_vec("B_enu_nT", b.get("B_enu_nT"), r.get("B_enu_nT"), tol.B_enu_nT)
    rb, rr = b.get("residual_rms_nT"), r.get("residual_rms_nT")
    if isinstance(rb, int | float) and isinstance(rr, int | float):
        lim = max(tol.residual_rms_rel * abs(rb), tol.residual_rms_nT)
        c.add("residual_rms_nT", rb, rr, abs(rr - rb), f"<= {lim:.3g}", abs(rr - rb) <= lim)


def _metric_values(d: dict) -> dict[str, float]:
    """Numeric metrics to compare: the whole-recording scope of ``magalign.metrics/1``.

    Per-segment scopes depend on the segmentation and are not compared; a metrics file
    without scopes is compared leaf by leaf.
    """
    scopes = d.get("scopes")
    if isinstance(scopes, list):
        keep = {str(s.get("scope")): s.get("components") for s in scopes
                if isinstance(s, Mapping) and s.get("scope") == "all"}
        return flatten_numbers(keep)
    return flatten_numbers(d)


def _compare_metrics(c: _Cmp, b: dict | None, r: dict | None, tol: Tolerances) -> None:
    if b is None:
        return
    if r is None:
        c.add("metrics.json", "present", "missing", None, "present", False)
        return
    fb, fr = _metric_values(b), _metric_values(r)
    for k, vb in fb.items():
        if "ratio_pct" in k:
            lim = tol.ratio_pct
        elif k.split(".")[-1].endswith("_nT") or "_nT." in k + ".":
            lim = max(tol.metric_nT, tol.metric_rel * abs(vb))
        else:
            continue
        vr = fr.get(k)
        if vr is None:
            c.add(f"metrics.{k}", vb, None, None, "present", False)
            continue
        d = abs(vr - vb)
        ok = d <= lim or (math.isnan(vb) and math.isnan(vr))
        c.add(f"metrics.{k}", vb, vr, d, f"<= {lim:.3g}", ok)


def _param_tol(key: str, vb: float, tol: Tolerances) -> float:
    absolute = {
        "offset_nT": tol.finding_offset_nT,
        "D": tol.finding_D,
        "time_offset_s": tol.finding_time_offset_s,
        "E_s": tol.finding_E_s,
        "windows_s": tol.finding_windows_s,
        "tilt_deg": tol.finding_tilt_deg,
        "azimuth_deg": tol.finding_azimuth_deg,
    }
    if key in absolute:
        lim = absolute[key]
        if key == "offset_nT":
            lim = max(lim, tol.finding_rel * abs(vb))
        return lim
    if key.endswith("_nT"):
        return max(tol.finding_offset_nT, tol.finding_rel * abs(vb))
    return max(tol.finding_rel * abs(vb), 1e-9)


def _compare_findings(c: _Cmp, b: dict | None, r: dict | None, tol: Tolerances) -> None:
    if b is None:
        return
    if r is None:
        c.add("diagnosis.json", "present", "missing", None, "present", False)
        return

    def by_effect(d: dict) -> dict[str, dict]:
        out: dict[str, dict] = {}
        for f in d.get("findings") or []:
            if isinstance(f, Mapping) and "effect" in f:
                out.setdefault(str(f["effect"]), dict(f.get("params") or {}))
        return out

    eb, er = by_effect(b), by_effect(r)
    sb, sr = sorted(eb), sorted(er)
    c.add("findings", ",".join(sb) or "none", ",".join(sr) or "none",
          None, "same set of effects", sb == sr)
    for eff in sorted(set(eb) & set(er)):
        for key, pb in eb[eff].items():
            pr = er[eff].get(key)
            q = f"findings.{eff}.{key}"
            fb, fr = flatten_numbers(pb), flatten_numbers(pr)
            if set(fb) != set(fr):
                c.add(q, pb, pr, None, "same shape", False)
                continue
            worst, ok, lim_txt = 0.0, True, ""
            for sub, vb in fb.items():
                lim = _param_tol(key, vb, tol)
                d = abs(fr[sub] - vb)
                worst = max(worst, d)
                ok &= d <= lim
                lim_txt = f"<= {lim:.3g}"
            if fb:
                c.add(q, pb, pr, worst, lim_txt, ok)


def compare(results: str | Path, baseline: str | Path,
            tolerances: Tolerances | None = None) -> list[Diff]:
    """Compare every baseline recording with its result.

    Returns
    -------
    list of Diff
        One row per compared quantity; ``status`` is ``ok``, ``REGRESSION`` or ``new`` (a
        recording the baseline does not have, not a regression).

    Raises
    ------
    InputError
        A folder is missing, the baseline holds no recording, or a file is not valid JSON.

    """
    res, base = Path(results), Path(baseline)
    for p, what in ((res, "results"), (base, "baseline")):
        if not p.is_dir():
            raise InputError(f"{what} folder not found", path=p,
                             hint="give the --out folder of magalign process")
    if tolerances is None:
        tf = base / "tolerances.toml"
        tolerances = Tolerances.load(tf) if tf.is_file() else Tolerances()
    base_recs = recordings_in(base, need_marker=False)
    if not base_recs:
        raise InputError("baseline holds no recording (no <name>/calibration.json)", path=base,
                         hint="regenerate it (make golden) or point at a results folder")
    res_recs = set(recordings_in(res, need_marker=True))
    rows: list[Diff] = []
    for name in base_recs:
        c = _Cmp(name)
        if name not in res_recs:
            c.add("recording", "finished", "missing or unfinished", None, "present", False)
            rows += c.rows
            continue
        bd, rd = base / name, res / name
        # recordings_in lists only folders with a calibration.json
        _compare_calibration(
            c, cast("dict[str, Any]", _load(bd / "calibration.json", check_calibration_dict)),
            cast("dict[str, Any]", _load(rd / "calibration.json", check_calibration_dict)),
            tolerances)
        _compare_metrics(c, _load(bd / "metrics.json", check_metrics_dict),
                         _load(rd / "metrics.json", check_metrics_dict), tolerances)
        _compare_findings(c, _load(bd / "diagnosis.json", check_diagnosis_dict),
                          _load(rd / "diagnosis.json", check_diagnosis_dict), tolerances)
        rows += c.rows
    for name in sorted(res_recs - set(base_recs)):
        rows.append(Diff(name, "recording", "-", "finished", "-", "-", NEW))
    return rows


def format_table(rows: list[Diff], *, failures_only: bool = False) -> str:
    """Format the diff table as aligned text."""
    shown = [r for r in rows if not failures_only or r.status != OK]
    head: tuple[str, ...] = ("recording", "quantity", "baseline", "result", "diff",
                             "tolerance", "status")
    cells = [head] + [(r.recording, r.quantity, r.baseline, r.result, r.diff, r.tolerance,
                       r.status) for r in shown]
    cells = [tuple(c if len(c) <= 48 else c[:45] + "..." for c in row) for row in cells]
    w = [max(len(row[i]) for row in cells) for i in range(len(head))]
    lines = ["  ".join(c.ljust(w[i]) for i, c in enumerate(row)).rstrip() for row in cells]
    lines.insert(1, "  ".join("-" * x for x in w))
    n_bad = sum(r.status == REGRESSION for r in rows)
    recs = {r.recording for r in rows}
    lines.append(f"{len(rows)} quantities over {len(recs)} recording(s): "
                 f"{n_bad} regression(s)")
    return "\n".join(lines)

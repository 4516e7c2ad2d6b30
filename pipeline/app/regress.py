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
from pipeline.core.geometry import angle_between_deg, matrix_to_quat, quat_to_rotvec
from pipeline.core.validate import check_calibration_dict, check_diagnosis_dict, check_metrics_dict

OK = "ok"
REGRESSION = "REGRESSION"
NEW = "new"


@dataclass(frozen=True)
class Tolerances:
    """Allowed differences between results and baseline, per quantity.

    A quantity that carries a sigma (``sigma_rotvec_deg``, ``sigma_offset_nT``,
    ``sigma_D``, ``sigma_time_offset_s``, ``sigma_B_enu_nT``, a finding's ``sigma``) may
    move by ``sigmas`` of its own sigma, never less than a floor for numerical noise: the
    larger of the absolute floor of its name below and ``rel_floor`` of its value. The
    sigma used is the smaller of the baseline's and the result's, so a change that inflates
    its own uncertainty does not widen its tolerance (the sigma itself is held to
    ``sigma_rel``). A deterministic rerun on another machine moves results by far less
    than the floors (about 1e-12 of their value); a regression of a few sigmas is far more.

    Attributes
    ----------
    sigmas : float
        Tolerance in the quantity's own sigmas.
    rel_floor : float
        Numerical-noise floor relative to the baseline value.
    rotation_deg : float
        Floor of each component of the rotation vector of ``R_result @ R_baseline.T``
        (deg, body frame, compared with ``sigma_rotvec_deg``); the whole tolerance about an
        axis whose sigma is null (unobservable).
    sigma_rel : float
        Relative change of each ``sigma_rotvec_deg`` component; an axis that becomes
        (un)observable (sigma null on one side only) is a regression.
    offset_nT, B_enu_nT, D, time_offset_s : float
        Absolute floors, per component (nT, -, s); without a sigma on either side the whole
        tolerance.
    residual_rms_rel, residual_rms_nT : float
        ``residual_rms_nT`` may differ by ``max(rel * baseline, abs)``.
    metric_nT, metric_rel : float
        Every ``*_nT`` metric may differ by ``max(metric_nT, metric_rel * |baseline|)``.
    ratio_pct : float
        Every ``ratio_pct`` metric, absolute percentage points.
    finding_rel : float
        Relative tolerance of finding params that carry no sigma and no absolute tolerance
        below (also the relative part for ``*_nT`` params without a sigma).
    finding_offset_nT, finding_D, finding_time_offset_s, finding_E_s, finding_windows_s,
    finding_tilt_deg, finding_azimuth_deg : float
        Absolute tolerances of the CONVENTIONS finding params of those names when the
        finding carries no sigma for them (``windows_s`` never does; ``_nT`` params:
        ``finding_offset_nT`` or the relative part, whichever is larger).

    """

    sigmas: float = 3.0
    rel_floor: float = 1e-6
    rotation_deg: float = 1e-4
    sigma_rel: float = 0.25
    offset_nT: float = 0.05
    B_enu_nT: float = 0.05
    D: float = 1e-5
    time_offset_s: float = 1e-6
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


def _sigma_array(x: Any, shape: tuple[int, ...]) -> np.ndarray:
    """Return a sigma as floats of ``shape``, NaN where absent (null, missing, bad shape)."""
    if x is None:
        return np.full(shape, np.nan)
    try:
        a = np.array(x, dtype=float)  # null items become NaN
    except (TypeError, ValueError):
        return np.full(shape, np.nan)
    return a if a.shape == shape else np.full(shape, np.nan)


def _limits(vb: np.ndarray, sb: Any, sr: Any, floor: float, tol: Tolerances) -> np.ndarray:
    """Per element: ``sigmas`` of the smaller sigma, never below the numerical floors."""
    s = np.fmin(_sigma_array(sb, vb.shape), _sigma_array(sr, vb.shape))
    base = np.maximum(floor, tol.rel_floor * np.abs(vb))
    return np.where(np.isfinite(s), np.maximum(tol.sigmas * s, base), base)


class _Cmp:
    def __init__(self, rec: str, tol: Tolerances):
        self.rec = rec
        self.tol = tol
        self.rows: list[Diff] = []

    def add(self, q: str, b: Any, r: Any, d: Any, tol: str, ok: bool) -> None:
        self.rows.append(Diff(self.rec, q, _fmt(b), _fmt(r), _fmt(d), tol,
                              OK if ok else REGRESSION))

    def sig_vec(self, q: str, b: Any, r: Any, sb: Any, sr: Any, floor: float) -> None:
        """Max abs difference per element, each within its own sigmas (or the floor)."""
        if b is None and r is None:
            return
        if b is None or r is None:
            self.add(q, b, r, None, "both present", False)
            return
        bb, rr = np.asarray(b, dtype=float), np.asarray(r, dtype=float)
        if bb.shape != rr.shape:
            self.add(q, b, r, None, "same shape", False)
            return
        if not bb.size:
            self.add(q, b, r, 0.0, "empty", True)
            return
        d = np.abs(rr - bb)
        lim = _limits(bb, sb, sr, floor, self.tol)
        worst = int(np.argmax(d / lim))
        self.add(q, b, r, float(d.flat[worst]),
                 f"<= {lim.flat[worst]:.3g} ({self.tol.sigmas:g} sigma or floor)",
                 bool(np.all(d <= lim)))


def _compare_calibration(c: _Cmp, b: dict, r: dict, tol: Tolerances) -> None:
    try:
        Rb, Rr = np.asarray(b["R_body_mag"], float), np.asarray(r["R_body_mag"], float)
        ang = float(angle_between_deg(Rr, Rb))
        dv = np.degrees(quat_to_rotvec(matrix_to_quat(Rr @ Rb.T)))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"calibration of {c.rec} has no usable R_body_mag: {exc}") from exc
    sb = b.get("sigma_rotvec_deg") or [None] * 3
    sr = r.get("sigma_rotvec_deg") or [None] * 3
    # each body axis within its own sigmas; the floor is the numerical noise of a rerun
    lim = _limits(np.zeros(3), sb, sr, tol.rotation_deg, tol)
    c.add("rotation_deg", b.get("rotvec_body_mag_deg"), r.get("rotvec_body_mag_deg"), ang,
          "per axis <= " + _fmt([float(x) for x in lim]) + f" deg ({tol.sigmas:g} sigma)",
          bool(np.all(np.abs(dv) <= lim)))
    for i, a in enumerate("xyz"):
        x0, x1 = sb[i], sr[i]
        if x0 is None or x1 is None:
            c.add(f"sigma_rotvec_deg.{a}", x0, x1, None, "both null or both finite",
                  x0 is None and x1 is None)
            continue
        rel = abs(x1 - x0) / max(abs(x0), 1e-12)
        c.add(f"sigma_rotvec_deg.{a}", x0, x1, rel, f"rel <= {tol.sigma_rel:g}",
              rel <= tol.sigma_rel)
    for key, floor in (("offset_nT", tol.offset_nT), ("D", tol.D),
                       ("time_offset_s", tol.time_offset_s), ("B_enu_nT", tol.B_enu_nT)):
        c.sig_vec(key, b.get(key), r.get(key), b.get(f"sigma_{key}"), r.get(f"sigma_{key}"),
                  floor)
    rb, rr = b.get("residual_rms_nT"), r.get("residual_rms_nT")
    if isinstance(rb, int | float) and isinstance(rr, int | float):
        lim_rms = max(tol.residual_rms_rel * abs(rb), tol.residual_rms_nT)
        c.add("residual_rms_nT", rb, rr, abs(rr - rb), f"<= {lim_rms:.3g}",
              abs(rr - rb) <= lim_rms)


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

    def by_effect(d: dict) -> dict[str, tuple[dict, dict]]:
        out: dict[str, tuple[dict, dict]] = {}
        for f in d.get("findings") or []:
            if isinstance(f, Mapping) and "effect" in f:
                sig = f.get("sigma")
                out.setdefault(str(f["effect"]), (dict(f.get("params") or {}),
                                                   dict(sig) if isinstance(sig, Mapping) else {}))
        return out

    eb, er = by_effect(b), by_effect(r)
    sb, sr = sorted(eb), sorted(er)
    c.add("findings", ",".join(sb) or "none", ",".join(sr) or "none",
          None, "same set of effects", sb == sr)
    for eff in sorted(set(eb) & set(er)):
        (params_b, sig_b), (params_r, sig_r) = eb[eff], er[eff]
        for key, pb in params_b.items():
            pr = params_r.get(key)
            q = f"findings.{eff}.{key}"
            fb, fr = flatten_numbers(pb), flatten_numbers(pr)
            if set(fb) != set(fr):
                c.add(q, pb, pr, None, "same shape", False)
                continue
            if not fb:
                continue
            subs = sorted(fb)
            vb = np.array([fb[k] for k in subs])
            d = np.abs(np.array([fr[k] for k in subs]) - vb)
            s0, s1 = flatten_numbers(sig_b.get(key)), flatten_numbers(sig_r.get(key))
            if set(s0) == set(fb) and set(s1) == set(fb):
                # the finding's own sigma; floor: the numerical noise of a rerun
                lim = _limits(vb, [s0[k] for k in subs], [s1[k] for k in subs], 0.0, tol)
            else:
                lim = np.array([_param_tol(key, v, tol) for v in vb])
            worst = int(np.argmax(d / np.maximum(lim, 1e-300)))
            c.add(q, pb, pr, float(d[worst]), f"<= {lim[worst]:.3g}", bool(np.all(d <= lim)))


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
    if not res_recs and not recordings_in(res, need_marker=False):
        # nothing was processed into it: a wrong folder, not a regression of every recording
        raise InputError("results folder holds no recording (no <name>/calibration.json)",
                         path=res, hint="give the --out folder of magalign process")
    rows: list[Diff] = []
    for name in base_recs:
        c = _Cmp(name, tolerances)
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

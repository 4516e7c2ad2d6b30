"""The diagnosis result and configuration.

What a diagnosis finds (``Signature``, ``Finding``, ``Diagnosis``, format
``magalign.diagnosis/1``) and how it is configured (``DiagnoseConfig``).
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass, field
from typing import Any

import numpy as np

FORMAT = "magalign.diagnosis/1"


@dataclass(frozen=True)
class Signature:
    """Data for the figure of one finding (decimated; not part of diagnosis.json).

    Attributes
    ----------
    t_s : ndarray (M,)
    residual_before_nT : ndarray (M, 3)
        Residual before the term was added, in the finding's frame.
    contribution_nT : ndarray (M, 3)
        The fitted term's contribution, same frame.
    regressor : ndarray (M, 3) or None
        What the residual should be proportional to (e.g. the reading's rate of change for
        a time offset), nT/s.

    """

    t_s: np.ndarray
    residual_before_nT: np.ndarray
    contribution_nT: np.ndarray
    regressor: np.ndarray | None = None


@dataclass(frozen=True)
class Finding:
    """One effect added to the model, with its evidence (CONVENTIONS diagnosis.json)."""

    effect: str
    params: dict[str, Any]
    sigma: dict[str, Any]
    evidence: dict[str, float]
    where: dict[str, Any]
    explanation: str
    signature: Signature | None = field(default=None, compare=False, repr=False)
    #: words on what told this finding from its look-alikes (appended to the explanation)
    told_apart: str = field(default="", compare=False, repr=False)

    def to_dict(self) -> dict[str, Any]:
        """Return the finding object of diagnosis.json."""
        return {
            "effect": self.effect,
            "params": self.params,
            "sigma": self.sigma,
            "evidence": self.evidence,
            "where": self.where,
            "explanation": self.explanation,
        }


@dataclass(frozen=True)
class Diagnosis:
    """What the diagnosis found.

    Attributes
    ----------
    baseline, final : dict
        ``{effects, residual_rms_nT, heldout_rms_nT}``.
    findings : tuple of Finding
        In the order they were added.
    not_identifiable : tuple of (effect, reason)
    duration_s : float

    """

    baseline: dict[str, Any]
    final: dict[str, Any]
    findings: tuple[Finding, ...]
    not_identifiable: tuple[tuple[str, str], ...]
    duration_s: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """Return the diagnosis.json object (CONVENTIONS, ``magalign.diagnosis/1``)."""
        return {
            "format": FORMAT,
            "baseline": self.baseline,
            "final": self.final,
            "findings": [f.to_dict() for f in self.findings],
            "not_identifiable": [{"effect": e, "reason": r} for e, r in self.not_identifiable],
        }

    @property
    def effects(self) -> frozenset[str]:
        """Names of the effects found."""
        return frozenset(f.effect for f in self.findings)

    def table(self, width: int = 100) -> str:
        """Return the printed table, no line longer than ``width`` characters.

        Effect, estimate, score statistic, dBIC and held-out RMS before > after; the
        explanations are in diagnosis.json and the report.
        """
        head = (f"{'effect':<15} {'estimate (1 sigma)':<40} {'stat':>8} {'dBIC':>8} "
                f"{'held-out nT':>17}")
        lines = [head, "-" * len(head)]
        b = self.baseline
        lines.append(f"{'baseline':<15} {', '.join(b['effects']) or 'R_body_mag, B_enu':<40} "
                     f"{'':>8} {'':>8} {b['heldout_rms_nT']:>17.1f}")
        for fd in self.findings:
            ev = fd.evidence
            est = _estimate_text(fd)
            if len(est) > 40:
                est = est[:39] + "~"
            held = f"{ev['heldout_rms_before_nT']:.1f} > {ev['heldout_rms_after_nT']:.1f}"
            lines.append(f"{fd.effect:<15} {est:<40} {ev['statistic']:>8.1f} "
                         f"{ev['delta_bic']:>8.1f} {held:>17}")
        if not self.findings:
            lines.append("(no findings: the baseline model explains the recording)")
        for e, r in self.not_identifiable:
            lines += textwrap.wrap(f"not identifiable: {e}: {r}", width,
                                   subsequent_indent="    ")
        return "\n".join(line[:width] for line in lines)


def _estimate_text(fd: Finding) -> str:
    p, s = fd.params, fd.sigma
    if fd.effect in ("hard_iron", "hard_iron_step"):
        o, so = p["offset_nT"], s["offset_nT"]
        txt = "o=[" + ", ".join(f"{a:.1f}+-{b:.1f}" for a, b in zip(o, so, strict=True)) + "] nT"
        if fd.effect == "hard_iron_step":
            txt += " in " + _windows_text(p["windows_s"])
        return txt
    if fd.effect == "time_offset":
        return f"tau={p['time_offset_s'] * 1e3:.2f}+-{s['time_offset_s'] * 1e3:.2f} ms"
    if fd.effect == "soft_iron":
        d = np.asarray(p["D"])
        return "diag(D)=[" + ", ".join(f"{x:.4f}" for x in np.diag(d)) + "]"
    if fd.effect == "eddy_current":
        e = np.asarray(p["E_s"]) * 1e3
        return "diag(E_s)=[" + ", ".join(f"{x:.2f}" for x in np.diag(e)) + "] ms"
    if fd.effect == "field_drift":
        return "p2p=[" + ", ".join(f"{x:.1f}" for x in p["peak_to_peak_nT"]) + "] nT ENU"
    if fd.effect == "heading_drift":
        return (f"{p['rate_deg_per_h']:.3g}+-{s.get('rate_deg_per_h', 0.0):.2g} deg/h, "
                f"p2p {p['peak_to_peak_deg']:.3g} deg")
    if fd.effect == "disturbance":
        return f"peak {p['peak_nT']:.0f} nT in " + _windows_text(p["windows_s"])
    if fd.effect == "axis_tilt":
        return f"tilt {p['tilt_deg']:.3f} deg az {p['azimuth_deg']:.0f} deg"
    if fd.effect == "field_gradient":
        g = float(np.linalg.norm(np.asarray(p["G_nT_per_m"]))) / 1e3
        sg = float(np.linalg.norm(np.asarray(s.get("G_nT_per_m", 0.0)))) / 1e3
        return f"|G|={g:.2f}+-{sg:.2f} uT/m ({p['position_frame']})"
    if fd.effect == "field_map":
        return ("p2p=[" + ", ".join(f"{x:.0f}" for x in p["peak_to_peak_nT"])
                + f"] nT ENU, {p['n_basis']} functions")
    if fd.effect == "sample_hold":
        return (f"native {p['native_rate_hz']:.1f} Hz, "
                f"{100 * p['repeated_fraction']:.1f} % repeats")
    return str(p)


def _windows_text(w: list[list[float]]) -> str:
    return ", ".join(f"[{a:.1f}, {b:.1f}) s" for a, b in w)


@dataclass(frozen=True)
class DiagnoseConfig:
    """Thresholds of the detection and selection (calibrated on null simulations).

    Attributes
    ----------
    n_folds : int
        Cross-validation folds; fold ``j`` holds out the time blocks ``j, j+n, j+2n, ...``.
    block_s : float
        Length of one contiguous held-out block, s.
    bic_margin : float
        Required decrease of the (correlation-discounted) BIC.
    heldout_margin : float
        Required relative decrease of the held-out RMS.
    max_findings : int
        Most rounds of the forward search that name a term. A bound on the work, not a
        prior: the BIC and the held-out blocks decide what is named. Set above what the
        real recordings need (at most 5 terms from the search), so that an event added to
        a recording cannot push out its last term: pieces of a magnet named while the map
        was still missing are merged and dropped once the map is in.
    n_refit : int
        How many of the strongest score-test candidates are refitted per round.
    max_samples : int
        Longer recordings are decimated to this many samples (the attitude track is kept at
        full rate, so rates of change stay exact).
    scan_smooth_s : float
        Width of the moving window of the residual-norm scan, s.
    scan_sigma : float
        Excess of the smoothed residual norm over its median, in robust sigmas, that opens a
        window.

    """

    n_folds: int = 5
    block_s: float = 1.0
    bic_margin: float = 20.0
    heldout_margin: float = 0.002
    max_findings: int = 10
    max_samples: int = 12000
    n_refit: int = 3
    scan_smooth_s: float = 0.5
    scan_sigma: float = 8.0

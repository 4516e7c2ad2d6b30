"""The diagnosis result and configuration.

What a diagnosis finds (``Signature``, ``Finding``, ``Diagnosis``, format
``magalign.diagnosis/1``) and how it is configured (``DiagnoseConfig``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.core.style import minus, num, terminal_width, wrap
from stages.report_text import rows

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

    def table(self, width: int | None = None) -> str:
        """Return what the diagnosis found in words, no line longer than ``width``.

        One paragraph per finding in the order its evidence was measured (as diagnosis.json
        and the report): the report's sentence with its size and units, then how much the
        error on held-out data fell and how strongly the data ask for it; then the terms
        this recording cannot determine. ``width``: the terminal's (80 when unknown).
        Lines break between words, never inside a number.
        """
        # the report's sentences (report_text.rows): one wording of each finding everywhere
        w = terminal_width() if width is None else width
        b = self.baseline
        lines = wrap(f"Without further terms (misalignment and field only) the model's error on "
                     f"held-out data is {num(b['heldout_rms_nT'], '.1f')} nT.", "", "", w)
        rs = rows(self.to_dict(), 0)
        if rs:
            lines.append("Found, in the order the evidence was measured:")
        for k, r in enumerate(rs, 1):
            lead = f"{k}. "
            lines += wrap(f"{', '.join(r.effects)}: {r.sentence} Error {r.fit}; evidence "
                          f"{r.evidence}.", lead, " " * len(lead), w)
        if not rs:
            lines.append("No finding: the baseline model explains the recording.")
        for e, why in self.not_identifiable:
            lines += wrap(f"Cannot be told from this recording: {e.replace('_', ' ')}: {why}",
                          "", "    ", w)
        return "\n".join(minus(line) for line in lines)


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
        Required decrease of ``-2 log`` of the (correlation-discounted) Laplace evidence
        (the BIC's name kept: without priors it is the BIC).
    heldout_margin : float
        Required relative decrease of the held-out RMS.
    max_findings : int
        Most rounds of the forward search that name a term. A bound on the work, not a
        prior: the evidence and the held-out blocks decide what is named. Set above what the
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

"""Diagnose: find the physics the fitted model left out, name it, model it, verify it.

Starting from the baseline model (misalignment ``R_body_mag`` and field ``B_enu`` only), every
candidate effect of :mod:`pipeline.effects` is tested with a score (Lagrange multiplier) test
at the current fit: the gradient and the information of the added parameters at zero, with
the parameters already in the model profiled out (Schur complement), no refit. The strongest
candidate is refitted and kept only if it lowers the BIC (with the sample count discounted
for residual correlation) **and** the error on held-out time blocks; then the loop repeats
until nothing qualifies. Effects local in time (``disturbance``, ``hard_iron_step``) are
located first by a scan of the robust residual norm; their windows become candidate terms.
Terms the motion cannot determine go to ``not_identifiable`` with the reason.
"""

from __future__ import annotations

import dataclasses
import io
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from pipeline import progress
from pipeline.calibration import Calibration
from pipeline.effects import (
    CONFOUND_RATIO,
    EFFECTS,
    LOCAL_KINDS,
    AttitudeTrack,
    EffectKind,
    FitData,
    FitResult,
    ModelState,
    Term,
    estimate_noise_model,
    evaluate,
    explanation,
    fit,
    gradient_matrix,
    gram,
    identifiability_reason,
    interpolation_error_nT,
    interpolation_error_proxy,
    motion_stats,
    sample_weights,
    term_params,
    term_sigma,
    wahba_init,
)
from pipeline.errors import EstimationError
from pipeline.geometry import quat_to_matrix
from pipeline.recording import AlignedSeries, Context, Recording
from pipeline.sample_hold import SampleHold, detect_sample_hold

FORMAT = "magalign.diagnosis/1"

GLOBAL_KINDS = (
    EffectKind.HARD_IRON,
    EffectKind.SOFT_IRON,
    EffectKind.TIME_OFFSET,
    EffectKind.EDDY_CURRENT,
    EffectKind.FIELD_DRIFT,
    EffectKind.AXIS_TILT,
    EffectKind.FIELD_GRADIENT,
    EffectKind.HEADING_DRIFT,
)

#: Nested pairs: the simpler term (value) is a special case of the other (key) and is
#: reported when it explains the data as well (within the BIC margin). A heading drift is a
#: field drift along ``(-B_N, B_E, 0)`` (the field turned about Up); a time offset is the
#: isotropic eddy term ``E_s = -tau I``.
NESTED_SIMPLER = {
    EffectKind.EDDY_CURRENT: EffectKind.TIME_OFFSET,
    EffectKind.FIELD_DRIFT: EffectKind.HEADING_DRIFT,
}

#: Largest time offset the search is built for, s (issue 15: lags up to +-100 ms).
MAX_LAG_S = 0.1

#: Yaw grid of the search for a position frame rotated about Up (``field_gradient``), deg.
YAW_GRID_DEG = np.arange(0.0, 360.0, 10.0)


# ----------------------------------------------------------------------------- values


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
        import textwrap

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
    if fd.effect == "sample_hold":
        return (f"native {p['native_rate_hz']:.1f} Hz, "
                f"{100 * p['repeated_fraction']:.1f} % repeats")
    return str(p)


def _windows_text(w: list[list[float]]) -> str:
    return ", ".join(f"[{a:.1f}, {b:.1f}) s" for a, b in w)


# ----------------------------------------------------------------------------- configuration


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
    max_findings: int = 6
    max_samples: int = 12000
    n_refit: int = 3
    scan_smooth_s: float = 0.5
    scan_sigma: float = 8.0


# ----------------------------------------------------------------------------- statistics


def robust_sigma(r: np.ndarray) -> float:
    """Robust noise scale of residual components: 1.4826 MAD, nT."""
    x = np.asarray(r).ravel()
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) + 1e-12


def inflation(r: np.ndarray, t_s: np.ndarray, block_s: float = 0.5) -> float:
    """Variance inflation of the mean from residual correlation (>= 1).

    Attitude noise that is correlated in time makes neighbouring residuals alike; the
    information per sample is then smaller than white-noise theory says. The ratio of the
    variance of block means to the variance expected for independent samples measures it.
    """
    n = len(t_s)
    if n < 20:
        return 1.0
    dt = float(np.median(np.diff(t_s)))
    L = max(2, int(round(block_s / max(dt, 1e-9))))
    nb = n // L
    if nb < 5:
        return 1.0
    x = np.asarray(r)[: nb * L].reshape(nb, L, -1)
    v = np.var(np.asarray(r)[: nb * L], axis=0)
    vb = np.var(x.mean(axis=1), axis=0)
    ratio = float(np.sum(vb * L) / max(np.sum(v), 1e-30))
    return max(1.0, ratio)


@dataclass(frozen=True)
class ScoreTest:
    """Score (Lagrange multiplier) test of a candidate term at the current fit.

    Attributes
    ----------
    term : Term
    statistic : float
        ``g' I_eff^-1 g / sigma^2`` (chi-square with ``k`` dof under the null, white noise).
    efficiency : float
        Smallest generalised eigenvalue of ``I_eff`` vs the term's own information (0: fully
        confounded with parameters already in the model).
    k : int
    rot_efficiency : float
        The same fraction for the rotation ``R_body_mag`` once the term is in the model, when
        the term at least halves it (else 1): a term that leaves the rotation confounded
        (below ``CONFOUND_RATIO``) is not admitted, however well it fits.
    interp_statistic : float
        The same statistic for the attitude's interpolation error alone
        (``FitData.interp_error_nT``): a term whose statistic is not well beyond it
        (``INTERP_MARGIN``) could be the interpolation error and is not named.

    """

    term: Term
    statistic: float
    efficiency: float
    k: int
    rot_efficiency: float = 1.0
    interp_statistic: float = 0.0


def gradient_candidate(cur: FitResult, data: FitData, sigma: float) -> ScoreTest:
    """Return the ``field_gradient`` term with the best position-frame yaw and its score test.

    Positions in ENU: yaw 0. Positions in the attitude source's frame (rotated about Up by an
    unknown angle): the Jacobian columns are ``cos(a) A + sin(a) B + C`` in the yaw ``a``, so
    three evaluations give them for every yaw; the score statistic is maximised over a
    10-degree grid and refined by a parabola through the best grid point. The yaw is then
    held (like the window of a local term); the search costs about one degree of freedom,
    well inside the BIC margin.
    """
    if data.position_frame != "attitude_source_local":
        return score_test(cur, Term(EffectKind.FIELD_GRADIENT), data, sigma)
    p0 = cur.state.n_params()
    cols = []
    for yaw in (0.0, np.pi / 2, np.pi):
        ev = evaluate(cur.state.with_term(Term(EffectKind.FIELD_GRADIENT, yaw_rad=yaw)), data)
        J = ev.J if ev.sqrt_w is None else ev.J * ev.sqrt_w[:, None, None]
        cols.append(J.reshape(-1, J.shape[-1]))
    Jb = cols[0][:, :p0]
    C = 0.5 * (cols[0][:, p0:] + cols[2][:, p0:])
    A = 0.5 * (cols[0][:, p0:] - cols[2][:, p0:])
    Bm = cols[1][:, p0:] - C

    def at(deg: float) -> ScoreTest:
        a = np.radians(deg)
        J = np.concatenate([Jb, np.cos(a) * A + np.sin(a) * Bm + C], axis=1)
        return _score_from_J(cur, Term(EffectKind.FIELD_GRADIENT, yaw_rad=float(a)), J, data,
                             sigma)

    tests = [at(d) for d in YAW_GRID_DEG]
    stats = np.array([t.statistic for t in tests])
    i = int(np.argmax(stats))
    s_m, s_0, s_p = stats[i - 1], stats[i], stats[(i + 1) % len(stats)]
    den = s_m - 2 * s_0 + s_p
    step = float(YAW_GRID_DEG[1] - YAW_GRID_DEG[0])
    shift = 0.5 * (s_m - s_p) / den * step if den < 0 else 0.0
    best = at(float(YAW_GRID_DEG[i]) + float(np.clip(shift, -step, step)))
    return best if best.statistic >= tests[i].statistic else tests[i]


def score_test(cur: FitResult, term: Term, data: FitData, sigma: float) -> ScoreTest:
    """Score test of adding ``term`` to the model of ``cur`` (no refit)."""
    st = cur.state.with_term(term)
    ev = evaluate(st, data)
    J = ev.J if ev.sqrt_w is None else ev.J * ev.sqrt_w[:, None, None]
    return _score_from_J(cur, term, J.reshape(-1, J.shape[-1]), data, sigma)


def _score_from_J(
    cur: FitResult, term: Term, J: np.ndarray, data: FitData, sigma: float
) -> ScoreTest:
    """Score test from the Jacobian (3N, P) of the model with ``term`` appended."""
    r = cur.residual_nT.reshape(-1)
    p0 = cur.state.n_params()
    if data.B_known_enu_nT is not None:
        keep = np.r_[0:3, 6:p0]
    else:
        keep = np.arange(p0)
    Jb, Jc = J[:, keep], J[:, p0:]
    Hbb, Hbc, Hcc = gram(Jb, Jb), gram(Jb, Jc), gram(Jc, Jc)
    g = gram(Jc, r[:, None])[:, 0]
    gb = gram(Jb, r[:, None])[:, 0]  # ~0 at a converged fit; kept for exactness
    sb = np.sqrt(np.clip(np.diag(Hbb), 1e-30, None))
    Hbb_n = Hbb / np.outer(sb, sb)
    try:
        X = np.linalg.lstsq(Hbb_n + 1e-12 * np.eye(len(sb)), (Hbc / sb[:, None]), rcond=None)[0]
        xb = np.linalg.lstsq(Hbb_n + 1e-12 * np.eye(len(sb)), gb / sb, rcond=None)[0]
    except np.linalg.LinAlgError:
        return ScoreTest(term, 0.0, 0.0, term.n_params())
    Ieff = Hcc - (Hbc / sb[:, None]).T @ X
    geff = g - (Hbc / sb[:, None]).T @ xb
    sc = np.sqrt(np.clip(np.diag(Hcc), 1e-30, None))
    In = Ieff / np.outer(sc, sc)
    In = 0.5 * (In + In.T)
    ev_all = np.linalg.eigvalsh(In)
    Hn = Hcc / np.outer(sc, sc)
    try:
        Lc = np.linalg.cholesky(0.5 * (Hn + Hn.T) + 1e-12 * np.eye(len(sc)))
        Li = np.linalg.inv(Lc)
        effs = np.linalg.eigvalsh(Li @ In @ Li.T)
    except np.linalg.LinAlgError:
        effs = ev_all
    # e.g. a tilted turntable axis with a known field (see EffectInfo.identifiable_in_part)
    partial = EFFECTS[term.kind].identifiable_in_part
    eff = float(effs[-1] if partial else effs[0])
    # pseudo-inverse with a relative floor: confounded directions carry no evidence
    w, V = np.linalg.eigh(In)
    good = w > 1e-8 * max(float(w[-1]), 1e-30)
    z = V.T @ (geff / sc)
    stat = float(np.sum(z[good] ** 2 / w[good])) / sigma**2
    stat_int = 0.0
    if data.interp_error_nT is not None:
        # the same statistic for what the interpolation error alone leaves (weighted as r)
        sw = sample_weights(data, cur.state.tau_s())
        e = data.interp_error_nT if sw is None else data.interp_error_nT * np.sqrt(sw)[:, None]
        e = e.reshape(-1)
        ge = gram(Jc, e[:, None])[:, 0]
        gbe = gram(Jb, e[:, None])[:, 0]
        xbe = np.linalg.lstsq(Hbb_n + 1e-12 * np.eye(len(sb)), gbe / sb, rcond=None)[0]
        ze = V.T @ ((ge - (Hbc / sb[:, None]).T @ xbe) / sc)
        stat_int = float(np.sum(ze[good] ** 2 / w[good])) / sigma**2
    k = int(np.count_nonzero(good)) if partial else term.n_params()
    rot_with = _rot_efficiency(np.concatenate([Jb, Jc], 1))
    rot_base = _rot_efficiency(Jb)
    # what the term itself costs the rotation: below 1 when it trades against R
    rot_eff = rot_with if rot_with < 0.5 * rot_base else 1.0
    return ScoreTest(term, stat, max(eff, 0.0), max(k, 1), rot_eff, stat_int)


#: A term is named only when its score statistic exceeds this factor squared times the one
#: of the attitude's interpolation error alone (its amplitude three times that error's).
INTERP_MARGIN = 3.0


def _interp_reason(data: FitData) -> str:
    """Why a term the interpolation error could produce is not named, in words."""
    rate = 1.0 / max(data.track.step_s, 1e-9)
    rms = float(np.sqrt(np.mean(np.asarray(data.interp_error_nT) ** 2)))
    return (f"the attitude at {rate:.3g} Hz is too slow for this motion: its own "
            f"interpolation error (about {rms:.3g} nT RMS at the magnetometer) could produce "
            "this term; record the attitude faster or move more slowly")


def _rot_efficiency(J: np.ndarray) -> float:
    """Fraction of the rotation's weakest information left with the other columns free."""
    from stages.estimators.base import RELATIVE_INFO_THRESHOLD, analyse

    lam = analyse(gram(J, J), {"rot": slice(0, 3)}).block_ratio["rot"]
    live = lam[lam >= RELATIVE_INFO_THRESHOLD]
    return float(np.min(live)) if live.size else 1.0


# ----------------------------------------------------------------------------- location


def scan_windows(
    residual_nT: np.ndarray, t_s: np.ndarray, cfg: DiagnoseConfig
) -> list[tuple[float, float]]:
    """Windows where the robust residual norm stands out (likelihood-ratio-style scan).

    The squared residual norm is normalised by a robust noise scale, smoothed over
    ``scan_smooth_s``, and compared with its own median plus ``scan_sigma`` robust sigmas of
    the smoothed series (so correlated noise raises the bar). A window opens where the
    smoothed statistic crosses that level and is widened to where it falls back to the
    half-way level; windows closer than one smoothing width are merged.

    Returns
    -------
    list of (start_s, end_s)
        Half-open windows, s from the first magnetometer sample.

    """
    n = len(t_s)
    if n < 50:
        return []
    dt = float(np.median(np.diff(t_s)))
    w = max(3, int(round(cfg.scan_smooth_s / dt)))
    sig = robust_sigma(residual_nT)
    z = np.sum(residual_nT**2, axis=1) / (3 * sig * sig)
    # robust to single spikes: moving median would be ideal; a trimmed value keeps it cheap
    z = np.minimum(z, np.percentile(z, 99.9) * 4)
    c = np.cumsum(np.concatenate([[0.0], z]))
    s = np.empty(n)
    half = w // 2
    lo = np.clip(np.arange(n) - half, 0, n)
    hi = np.clip(np.arange(n) + half + 1, 0, n)
    s = (c[hi] - c[lo]) / (hi - lo)
    med = float(np.median(s))
    mad = float(1.4826 * np.median(np.abs(s - med))) + 1e-12
    level = med + cfg.scan_sigma * mad
    # a window needs a real excess, not just a little above a very quiet median
    level = max(level, med + 2.0)
    above = s > level
    if not above.any():
        return []
    lower = med + 0.5 * (level - med)
    low_mask = s > lower
    out: list[tuple[int, int]] = []
    idx = np.flatnonzero(np.diff(np.concatenate([[0], low_mask.astype(int), [0]])))
    for a, b in zip(idx[0::2], idx[1::2], strict=True):
        if above[a:b].any():
            out.append((a, b))
    merged: list[list[int]] = []
    for a, b in out:
        if merged and a - merged[-1][1] < w:
            merged[-1][1] = b
        else:
            merged.append([a, b])
    wins = []
    for a, b in merged:
        start = float(t_s[a])
        end = float(t_s[min(b, n - 1)])
        if end - start < 2 * dt:
            continue
        if end - start > 0.5 * (t_s[-1] - t_s[0]):
            continue  # not local: a global term's job
        wins.append((start, end))
    return wins


def refine_step(
    w: tuple[float, float], residual_nT: np.ndarray, t_s: np.ndarray, reach_s: float = 1.0
) -> tuple[float, float]:
    """Change-point refinement of an offset window: maximise the explained residual energy.

    For a constant offset in ``[a, b)`` the least-squares gain is ``|sum r|^2 / n``; both
    edges are searched within ``reach_s`` of the scan's window using cumulative sums.
    """
    n = len(t_s)
    c = np.vstack([np.zeros(3), np.cumsum(residual_nT, axis=0)])
    ia = np.flatnonzero((t_s >= w[0] - reach_s) & (t_s <= w[0] + reach_s))
    ib = np.flatnonzero((t_s >= w[1] - reach_s) & (t_s <= w[1] + reach_s)) + 1
    if ia.size == 0 or ib.size == 0:
        return w
    ia = ia[:: max(1, ia.size // 150)]
    ib = ib[:: max(1, ib.size // 150)]
    S = c[ib][None, :, :] - c[ia][:, None, :]
    cnt = (ib[None, :] - ia[:, None]).astype(float)
    gain = np.where(cnt > 0, np.sum(S * S, axis=-1) / np.maximum(cnt, 1.0), -np.inf)
    i, j = np.unravel_index(int(np.argmax(gain)), gain.shape)
    a = float(t_s[ia[i]])
    b = float(t_s[ib[j]]) if ib[j] < n else float(t_s[-1]) + 1e-6
    return (a, b) if b > a else w


# ----------------------------------------------------------------------------- cross-validation


def fold_of(t_s: np.ndarray, cfg: DiagnoseConfig) -> np.ndarray:
    """Fold index of each sample: contiguous blocks of ``block_s`` dealt round-robin."""
    blocks = np.floor((t_s - t_s[0]) / cfg.block_s).astype(np.int64)
    return blocks % cfg.n_folds


def heldout_rms(state: ModelState, data: FitData, cfg: DiagnoseConfig) -> float:
    """RMS prediction error on held-out time blocks, nT.

    Each fold is refitted from the current state with the values of local terms reset to
    zero (so a window's amplitude is learnt only from training samples), then predicts the
    held-out blocks. Random samples are never held out: neighbouring samples share
    attitude noise and would leak.
    """
    folds = fold_of(data.t_s, cfg)
    sq, cnt = 0.0, 0
    start = dataclasses.replace(
        state,
        values=tuple(
            np.zeros_like(v) if t.kind in LOCAL_KINDS else v
            for t, v in zip(state.terms, state.values, strict=True)
        ),
    )
    for j in range(cfg.n_folds):
        test = folds == j
        if test.sum() == 0 or (~test).sum() < 10:
            continue
        res = fit(start, data.subset(~test), max_iter=6, rtol=1e-6)
        pred = evaluate(res.state, data.subset(test), jacobian=False).y_nT
        e = data.y_nT[test] - pred
        sq += float(np.sum(e * e))
        cnt += e.size
    return float(np.sqrt(sq / max(cnt, 1)))


# ----------------------------------------------------------------------------- main loop


def _bic(rss: float, n_eff: float, k: int) -> float:
    return n_eff * np.log(rss / n_eff) + k * np.log(n_eff)


def _n_eff(res: FitResult, data: FitData) -> float:
    return res.residual_nT.size / inflation(res.residual_nT, data.t_s)


def _bic_between(a: FitResult, b: FitResult, data: FitData) -> float:
    """BIC of fit ``a`` minus BIC of fit ``b``, both with one effective sample count.

    Each candidate's delta BIC is discounted by the correlation of its own residual; two
    candidates are compared with the smaller of their two counts (the conservative one), so
    the difference measures their fits and parameter counts, not their residuals' texture.
    """
    n = min(_n_eff(a, data), _n_eff(b, data))
    return _bic(a.rss, n, a.state.n_params()) - _bic(b.rss, n, b.state.n_params())


def _axes(x: np.ndarray) -> list[str]:
    rms = np.sqrt(np.mean(np.asarray(x) ** 2, axis=0))
    if not np.any(rms > 0):
        return []
    return [a for a, v in zip("xyz", rms, strict=True) if v >= 0.3 * rms.max()]


def _contribution(before: ModelState, after: ModelState, data: FitData) -> np.ndarray:
    """Prediction difference (mag frame) made by the last term at the fitted values."""
    without = dataclasses.replace(
        after, terms=after.terms[:-1], values=after.values[:-1],
        T_enu=np.eye(3) if after.terms[-1].kind is EffectKind.AXIS_TILT else after.T_enu,
    )
    return (
        evaluate(after, data, jacobian=False).y_nT - evaluate(without, data, jacobian=False).y_nT
    )


def _to_enu(v_mag: np.ndarray, state: ModelState, data: FitData) -> np.ndarray:
    """Map mag-frame vectors to ENU with the fitted rotation and attitude (inverse model)."""
    C = quat_to_matrix(data.track.at(data.t_s - state.tau_s()))
    v = np.linalg.solve(state.D(), v_mag.T).T @ state.R_body_mag.T
    return np.einsum("nij,nj->ni", C, v)


#: search rounds the progress line expects (most recordings need two or three)
_ROUNDS_SHOWN = 3


def diagnose_data(
    data: FitData,
    init: ModelState | None = None,
    cfg: DiagnoseConfig | None = None,
    *,
    turntable: bool = False,
) -> tuple[Diagnosis, FitResult]:
    """Run detection, selection and location on prepared data.

    Parameters
    ----------
    data : FitData
        Stamps, readings and attitude track.
    init : ModelState, optional
        Baseline starting values (``R_body_mag``, ``B_enu``); Wahba initialisation otherwise.
    cfg : DiagnoseConfig, optional
        Thresholds (defaults when omitted).
    turntable : bool
        The attitude comes from a single-axis turntable (``axis_tilt`` is then a candidate).

    Returns
    -------
    (Diagnosis, FitResult)
        The diagnosis and the final fit.

    """
    cfg = cfg or DiagnoseConfig()
    if len(data) < 30:
        raise EstimationError("too few magnetometer samples with an attitude to diagnose")
    from_wahba = init is None
    if init is None:
        init = wahba_init(data)
    cur = fit(ModelState(init.R_body_mag, init.B_enu_nT), data)
    if not from_wahba:
        # a poor starting point (e.g. an estimator that assumed a clean sensor) must not
        # decide the baseline: keep the better of it and Wahba's start
        alt = fit(wahba_init(data), data)
        if alt.rss < cur.rss:
            cur = alt
    stats = motion_stats(data)
    # the baseline residual as calibrate reports it (equal weights); then the likelihood's
    # weights for what the attitude noise does between attitude samples
    # (effects.sample_weights)
    base_rms = cur.rms_nT
    nm = estimate_noise_model(cur.residual_nT, data)
    if nm is not None:
        data = dataclasses.replace(data, noise_model=nm)
        cur = fit(cur.state, data)
    e_int_nT = interpolation_error_nT(data)
    if e_int_nT > 0.05 * robust_sigma(cur.residual_nT):
        # the attitude's own interpolation error stands out of the noise: what it could
        # produce is not named (ScoreTest.interp_statistic)
        data = dataclasses.replace(data,
                                   interp_error_nT=interpolation_error_proxy(cur.state, data))
    cv_cur = heldout_rms(cur.state, data, cfg)
    baseline = {"effects": [], "residual_rms_nT": base_rms, "heldout_rms_nT": cv_cur}
    base_fit, cv_base = cur, cv_cur
    findings: list[Finding] = []
    not_ident: dict[str, str] = {}
    kinds = list(GLOBAL_KINDS)
    if not (turntable or data.B_known_enu_nT is not None):
        kinds.remove(EffectKind.AXIS_TILT)
    if turntable and data.B_known_enu_nT is None:
        why = identifiability_reason(EffectKind.AXIS_TILT, stats, data, 0.0)
        not_ident["axis_tilt"] = why or ""
    rejected: set[tuple] = set()  # failed in this round; retried once the model changes
    dropped: set[tuple] = set()  # removed by the backward step; never re-added
    cov_final = None
    while len(findings) < cfg.max_findings:
        sig = robust_sigma(cur.residual_nT)
        present = {t.kind for t in cur.state.terms}
        cands: list[Term] = [Term(k) for k in kinds if k not in present]
        taken = [w for t in cur.state.terms if t.kind in LOCAL_KINDS for w in t.windows_s]
        for w in scan_windows(cur.residual_nT, data.t_s, cfg):
            if any(w[0] >= a and w[1] <= b for a, b in taken):
                continue  # inside a window already modelled, not a new event
            # the scan sees where the excess is large; a bell-shaped transient starts and
            # ends earlier and later than that
            pad = max(0.5, 0.25 * (w[1] - w[0]))
            wd = (max(float(data.t_s[0]), w[0] - pad), min(float(data.t_s[-1]), w[1] + pad))
            ks = min(2.0, max(0.75, (wd[1] - wd[0]) / 6))
            cands.append(Term(EffectKind.DISTURBANCE, (wd,), knot_step_s=ks))
            ws = refine_step(w, cur.residual_nT, data.t_s)
            cands.append(Term(EffectKind.HARD_IRON_STEP, (ws,)))
        tests = []
        replace_trial = None
        for j, term in enumerate(cands):
            progress.detail(f"search {len(findings) + 1}, candidate {j + 1}/{len(cands)}",
                            len(findings) + 0.5 * j / len(cands), _ROUNDS_SHOWN)
            if (term.kind, term.windows_s) in rejected | dropped:
                continue
            if term.kind is EffectKind.FIELD_DRIFT and EffectKind.HEADING_DRIFT in present:
                # the heading drift spans part of the field drift: the field drift can only
                # replace it (tried below), not be added to it
                replace_trial = term
                continue
            if term.kind is EffectKind.FIELD_GRADIENT and data.p_m is not None:
                st = gradient_candidate(cur, data, sig)
                term = st.term
            elif term.kind is EffectKind.EDDY_CURRENT and EffectKind.TIME_OFFSET in present:
                # only what a time offset cannot explain: the anisotropic part of E_s
                st = anisotropic_eddy_test(cur, data, sig)
            else:
                st = score_test(cur, term, data, sig)
            Bc = cur.state.B_enu_nT
            reason = identifiability_reason(
                term.kind, stats, data, st.efficiency,
                horizontal_fraction=float(np.linalg.norm(Bc[:2]) / max(np.linalg.norm(Bc),
                                                                        1e-9)))
            if reason is None and st.rot_efficiency < CONFOUND_RATIO \
                    and term.kind not in LOCAL_KINDS:
                reason = (
                    f"with it the motion leaves the rotation R_body_mag confounded (only "
                    f"{st.rot_efficiency:.1e} of its weakest combination stays determined): it "
                    "would trade against the misalignment; rotate through more attitudes"
                )
            if (reason is None and st.statistic < INTERP_MARGIN**2 * st.interp_statistic
                    and st.statistic > st.k * np.log(cur.residual_nT.size)):
                # it would have been tried, but the interpolation error could produce it
                reason = _interp_reason(data)
            if reason is not None:
                if term.kind in LOCAL_KINDS:
                    continue
                if not findings:
                    not_ident.setdefault(term.kind.value, reason)
                elif term.kind is EffectKind.TIME_OFFSET and EffectKind.EDDY_CURRENT in present:
                    not_ident.setdefault(term.kind.value, (
                        "a time offset is the isotropic part of the eddy-current term already "
                        "in the model (E_s = -tau I to first order): the two cannot be told "
                        "apart"))
                continue
            tests.append(st)
        n = cur.residual_nT.size
        tests.sort(key=lambda s: -s.statistic + s.k * np.log(n))
        # the score test ranks the candidates; the few strongest are refitted and the one
        # with the lowest BIC is the strongest (a score statistic far from the null is only
        # a local approximation when much is still unmodelled)
        fits = []
        for r, st in enumerate(tests[: cfg.n_refit]):
            if -st.statistic + st.k * np.log(n) > 0:
                break
            progress.detail(f"search {len(findings) + 1}, refit {r + 1}/{cfg.n_refit}",
                            len(findings) + 0.5 + 0.5 * r / cfg.n_refit, _ROUNDS_SHOWN)
            fr = _refit(cur, st.term, data, cfg)
            if fr is None:
                rejected.add((st.term.kind, st.term.windows_s))
                continue
            fits.append((fr[1], st, fr[0]))
        if replace_trial is not None:
            rt = _replacement_fit(cur, EffectKind.HEADING_DRIFT, replace_trial, data, cfg)
            if rt is not None:
                fits.append(rt)
        fits.sort(key=lambda x: x[0])
        # nested terms resolve to the simplest that explains the data as well (time offset
        # inside eddy currents, a mag-frame step inside a free ENU disturbance)
        by_kind = {f[1].term.kind: f for f in fits}
        if fits:
            best = fits[0]
            simpler = {**NESTED_SIMPLER,
                       EffectKind.DISTURBANCE: EffectKind.HARD_IRON_STEP}.get(best[1].term.kind)
            if simpler is not None:
                alt = by_kind.get(simpler)
                if alt is None and simpler in NESTED_SIMPLER.values() and simpler not in present:
                    fr = _refit(cur, Term(simpler), data, cfg)
                    alt = None if fr is None else (fr[1], best[1], fr[0])
                elif alt is None and simpler is EffectKind.HARD_IRON_STEP:
                    fr = _refit(cur, Term(simpler, best[1].term.windows_s), data, cfg)
                    alt = None if fr is None else (fr[1], best[1], fr[0])
                # the pairs of NESTED_SIMPLER are compared with one effective sample count:
                # with each its own, a time offset lost to eddy currents by the texture of
                # the residuals alone (issue 15); the window pair keeps its calibrated rule
                if alt is not None and simpler in NESTED_SIMPLER.values():
                    prefer = _bic_between(alt[2], best[2], data) <= cfg.bic_margin
                else:
                    prefer = alt is not None and alt[0] <= best[0] + cfg.bic_margin
                if alt is not None and prefer:
                    fits.remove(best) if best in fits else None
                    fits.insert(0, alt)
        accepted = False
        for dbic, st, res in fits:
            cv_new = _heldout_ok(cur, res, data, cfg, cv_cur)
            if cv_new is None:
                rejected.add((st.term.kind, st.term.windows_s))
                continue
            term = res.state.terms[-1]
            gone = {t.kind for t in cur.state.terms} - {t.kind for t in res.state.terms}
            if gone:  # a replacement: the nested term it contains leaves the model
                findings = [f for f in findings if EffectKind(f.effect) not in gone]
                cur = fit(dataclasses.replace(res.state, terms=res.state.terms[:-1],
                                              values=res.state.values[:-1]), data)
            findings.append(_finding(cur, res, term, st, dbic, cv_cur, cv_new, data))
            cur, cv_cur = res, cv_new
            accepted = True
            rejected.clear()
            break
        if not accepted:
            break
        if data.noise_model is None:
            # the attitude noise may only now stand out of what the model leaves
            nm = estimate_noise_model(
                cur.residual_nT if cur.raw_residual_nT is None else cur.raw_residual_nT, data)
            if nm is not None:
                data = dataclasses.replace(data, noise_model=nm)
                cur = fit(cur.state, data)
                cv_cur = heldout_rms(cur.state, data, cfg)
        # backward step: a term chosen earlier, while more was unmodelled, may have stood in
        # for what a later term explains properly; drop it if it no longer earns its margin
        i = 0
        while i < len(cur.state.terms) - 1:
            st_wo = _without(cur.state, i)
            res_wo = fit(st_wo, data)
            n_eff = _n_eff(cur, data)
            bic_cur = _bic(cur.rss, n_eff, cur.state.n_params())
            keep = bic_cur - _bic(res_wo.rss, n_eff, res_wo.state.n_params())
            t_i = cur.state.terms[i]
            if keep > -cfg.bic_margin:
                dropped.add((t_i.kind, t_i.windows_s))
                findings.pop(i)
                cur = res_wo
                cv_cur = heldout_rms(cur.state, data, cfg)
                continue
            simpler = _simpler(t_i)
            if simpler is not None and simpler.kind not in {t.kind for t in st_wo.terms}:
                res_s = fit(res_wo.state.with_term(simpler), data)
                if _bic(res_s.rss, n_eff, res_s.state.n_params()) - bic_cur < cfg.bic_margin:
                    # the simpler nested term explains the data as well: it replaces the other
                    cv_s = heldout_rms(res_s.state, data, cfg)
                    st_s = score_test(res_wo, simpler, data, robust_sigma(res_wo.residual_nT))
                    dbic_s = _bic(res_s.rss, n_eff, res_s.state.n_params()) - _bic(
                        res_wo.rss, n_eff, res_wo.state.n_params())
                    cv_wo = heldout_rms(res_wo.state, data, cfg)
                    findings.pop(i)
                    findings.append(_finding(res_wo, res_s, simpler, st_s, dbic_s, cv_wo, cv_s,
                                             data))
                    dropped.add((t_i.kind, t_i.windows_s))
                    cur, cv_cur = res_s, cv_s
                    continue
            i += 1
    # the evidence of each finding was measured against the model of the moment it was added;
    # later rounds may have dropped or replaced terms before it. Re-measure it as a build-up in
    # the final order so that the numbers chain from the baseline to the final model.
    canon = canonical_rate_terms(cur, data)
    if canon is not cur:
        cur, cv_cur = canon, heldout_rms(canon.state, data, cfg)
    findings, cur, cv_cur = split_isotropic_eddy(findings, cur, cv_cur, data, cfg)
    findings = _chain_evidence(findings, cur, base_fit, cv_base, cv_cur, data, cfg)
    cov_final = _covariance(cur, data)
    note = _gradient_note(cur, data, not_ident)
    findings = [
        dataclasses.replace(
            f,
            params=(p := term_params(cur.state.terms[i], cur.state.values[i], cur.state, data)),
            sigma=_sigma_for(cur, i, cov_final, data),
            explanation=explanation(cur.state.terms[i].kind, p, data.duration_s, note=note),
        )
        for i, f in enumerate(findings)
    ]
    final = {
        "effects": [f.effect for f in findings],
        "residual_rms_nT": cur.rms_nT,
        "heldout_rms_nT": cv_cur,
    }
    diag = Diagnosis(
        baseline=baseline,
        final=final,
        findings=tuple(findings),
        not_identifiable=tuple(
            (k, v) for k, v in not_ident.items() if k not in final["effects"]
        ),
        duration_s=data.duration_s,
    )
    return diag, cur


def _gradient_note(cur: FitResult, data: FitData, not_ident: dict[str, str]) -> str | None:
    """Return what the test of a spatial gradient found, for the drift explanation.

    None without positions (the drift explanation then says that drift and gradient cannot
    be separated).
    """
    if data.p_m is None:
        return None
    for t, v in zip(cur.state.terms, cur.state.values, strict=True):
        if t.kind is EffectKind.FIELD_GRADIENT:
            g = float(np.linalg.norm(gradient_matrix(v, t.yaw_rad))) / 1e3
            return (
                "The recording carries positions: a spatial field gradient was tested and is "
                f"in the model (field_gradient, {g:.2f} uT/m); this drift is the change left "
                "in time once the field's variation along the path is modelled"
            )
    why = not_ident.get(EffectKind.FIELD_GRADIENT.value)
    if why:
        return (
            "The recording carries positions, but a spatial field gradient could not be "
            f"tested: {why}; the term may still stand for both"
        )
    return (
        "The recording carries positions: a spatial field gradient was tested and did not "
        "lower both the BIC and the held-out error, so this is a change in time rather than "
        "the field varying along the sensor's path"
    )


def _prefix(state: ModelState, k: int) -> ModelState:
    """``state`` with only its first ``k`` terms (values as fitted in ``state``)."""
    has_tilt = any(t.kind is EffectKind.AXIS_TILT for t in state.terms[:k])
    return dataclasses.replace(
        state, terms=state.terms[:k], values=state.values[:k],
        T_enu=state.T_enu if has_tilt else np.eye(3),
    )


def _chain_evidence(
    findings: list[Finding],
    final: FitResult,
    base: FitResult,
    cv_base: float,
    cv_final: float,
    data: FitData,
    cfg: DiagnoseConfig,
) -> list[Finding]:
    """Recompute each finding's evidence as a sequential build-up in the final order.

    Finding ``k`` is measured between the model with the findings before it and the model
    that adds it, so ``rms_after`` of finding ``k`` is ``rms_before`` of finding ``k + 1``,
    the first ``rms_before`` is the baseline's and the last ``rms_after`` the final model's
    (the same for the held-out RMS). Intermediate models are refitted from the final values.

    Parameters
    ----------
    findings : list of Finding
        In the order of ``final.state.terms``.
    final, base : FitResult
        The final and the baseline fit.
    cv_base, cv_final : float
        Their held-out RMS, nT.
    data : FitData
        The fitted samples.
    cfg : DiagnoseConfig
        Cross-validation settings.

    Returns
    -------
    list of Finding
        Same effects and order; evidence, ``where`` and signature re-measured.

    """
    K = len(findings)
    if K == 0:
        return findings
    fits = [base] + [fit(_prefix(final.state, k), data) for k in range(1, K)] + [final]
    cvs = [cv_base] + [heldout_rms(f.state, data, cfg) for f in fits[1:K]] + [cv_final]
    out = []
    for k, fd in enumerate(findings):
        before, after = fits[k], fits[k + 1]
        term = after.state.terms[-1]
        st = score_test(before, term, data, robust_sigma(before.residual_nT))
        n_eff = _n_eff(after, data)
        dbic = _bic(after.rss, n_eff, after.state.n_params()) - _bic(
            before.rss, n_eff, before.state.n_params())
        new = _finding(before, after, term, st, float(dbic), cvs[k], cvs[k + 1], data)
        out.append(dataclasses.replace(new, params=fd.params, sigma=fd.sigma))
    return out


def _simpler(term: Term) -> Term | None:
    """Return the simplest nested special case of ``term``, or None.

    A time offset inside eddy currents, a mag-frame step inside a free ENU disturbance.
    """
    if term.kind in NESTED_SIMPLER:
        return Term(NESTED_SIMPLER[term.kind])
    if term.kind is EffectKind.DISTURBANCE:
        return Term(EffectKind.HARD_IRON_STEP, term.windows_s)
    return None


def _replacement_fit(
    cur: FitResult, simple: EffectKind, term: Term, data: FitData, cfg: DiagnoseConfig
) -> tuple[float, ScoreTest, FitResult] | None:
    """Replace the nested ``simple`` term of the model by ``term``, which contains it.

    Returns ``(delta BIC against the current model, score test, fit)`` when the replacement
    lowers the BIC by ``bic_margin`` (the extra parameters counted), else None. The score test
    is made against the model without ``simple``.
    """
    i = next(k for k, t in enumerate(cur.state.terms) if t.kind is simple)
    wo = fit(_without(cur.state, i), data)
    res = fit(wo.state.with_term(term), data)
    if not res.rss < cur.rss:
        return None
    n_eff = _n_eff(res, data)
    dbic = _bic(res.rss, n_eff, res.state.n_params()) - _bic(cur.rss, n_eff, cur.state.n_params())
    if dbic > -cfg.bic_margin:
        return None
    st = score_test(wo, term, data, robust_sigma(wo.residual_nT))
    return float(dbic), st, res


#: Orthonormal basis (8, 9) of the traceless 3x3 matrices, row-major: the part of ``E_s``
#: that a time offset (``E_s = -tau I``, CONVENTIONS eddy_current) cannot produce.
_TRACELESS = np.array(
    [np.eye(3)[i][:, None] @ np.eye(3)[j][None, :] for i in range(3) for j in range(3)
     if i != j]
    + [np.diag([1.0, -1.0, 0.0]) / np.sqrt(2.0), np.diag([1.0, 1.0, -2.0]) / np.sqrt(6.0)]
).reshape(8, 9)
#: The isotropic direction of ``E_s`` (row-major), unit length.
_ISO = np.eye(3).ravel() / np.sqrt(3.0)


def anisotropic_eddy_test(cur: FitResult, data: FitData, sigma: float) -> ScoreTest:
    """Score test of the anisotropic part of ``eddy_current`` with a time offset in the model.

    The isotropic part of ``E_s`` is the time offset's (``E_s = -tau I`` to first order): with
    ``time_offset`` in the model the eddy term is tested on the 8 traceless directions only,
    so the nested simpler term keeps what it explains and the eddy term is admitted only for
    what it cannot (issue 15). ``k`` stays 9 (conservative).
    """
    term = Term(EffectKind.EDDY_CURRENT)
    ev = evaluate(cur.state.with_term(term), data)
    J = ev.J.reshape(-1, ev.J.shape[-1])
    p0 = cur.state.n_params()
    Jt = np.concatenate([J[:, :p0], J[:, p0:] @ _TRACELESS.T], axis=1)
    return _score_from_J(cur, term, Jt, data, sigma)


def canonical_rate_terms(res: FitResult, data: FitData) -> FitResult:
    """With ``time_offset`` and ``eddy_current`` both in the model, move ``tr(E_s)/3`` to tau.

    The two share one direction (``E_s = -tau I`` to first order): the fit leaves it where the
    iterations stopped. The canonical split gives the time offset the isotropic part, ``tau <-
    tau - tr(E_s)/3`` and ``E_s <- E_s - tr(E_s)/3 I`` (no refit: a refit drifts back along the
    shared direction). It is taken unless it worsens the fit by more than one parameter's BIC
    (``ln N`` noise variances), which the second-order difference of the two terms stays far
    below.
    """
    from pipeline.effects import normal_equations

    kinds = [t.kind for t in res.state.terms]
    if EffectKind.TIME_OFFSET not in kinds or EffectKind.EDDY_CURRENT not in kinds:
        return res
    it, ie = kinds.index(EffectKind.TIME_OFFSET), kinds.index(EffectKind.EDDY_CURRENT)
    vals = list(res.state.values)
    E = vals[ie].reshape(3, 3)
    iso = float(np.trace(E)) / 3.0
    vals[it] = vals[it] - iso
    vals[ie] = (E - iso * np.eye(3)).ravel()
    st = dataclasses.replace(res.state, values=tuple(vals))
    ev = evaluate(st, data)
    r = data.y_nT - ev.y_nT
    rss = float(np.sum(r * r))
    n = max(res.residual_nT.size, 2)
    if not np.isfinite(rss) or rss - res.rss > np.log(n) * res.rss / n:
        return res
    H, _ = normal_equations(ev.J, r)
    return FitResult(st, r, rss, H, res.n_iter)


def split_isotropic_eddy(
    findings: list[Finding], cur: FitResult, cv_cur: float, data: FitData,
    cfg: DiagnoseConfig,
) -> tuple[list[Finding], FitResult, float]:
    """Turn an eddy term with a significant isotropic part into a time offset and the rest.

    The simpler nested term is reported for what it explains: when the final model has
    ``eddy_current`` but no ``time_offset`` and ``tr(E_s)/3`` differs from zero by more than
    the BIC gate of one parameter (``z^2 > ln n_eff + bic_margin``), the model is refitted with
    ``time_offset`` (tau = -tr(E_s)/3) and the traceless remainder of ``E_s``; the remainder is
    kept only if it still lowers the BIC by ``bic_margin`` and the held-out error.
    """
    kinds = [t.kind for t in cur.state.terms]
    if EffectKind.EDDY_CURRENT not in kinds or EffectKind.TIME_OFFSET in kinds:
        return findings, cur, cv_cur
    ie = kinds.index(EffectKind.EDDY_CURRENT)
    o = cur.state.offsets()[ie]
    cov = _covariance(cur, data)[o : o + 9, o : o + 9]
    E = cur.state.values[ie]
    iso = float(_ISO @ E)
    var = float(_ISO @ cov @ _ISO)
    n_eff = _n_eff(cur, data)
    if var <= 0 or iso * iso / var <= np.log(n_eff) + cfg.bic_margin:
        return findings, cur, cv_cur
    tau = -iso / np.sqrt(3.0)  # E_iso = (iso / sqrt 3) I = -tau I
    st = dataclasses.replace(
        cur.state,
        terms=cur.state.terms[:ie] + (Term(EffectKind.TIME_OFFSET),) + cur.state.terms[ie:],
        values=cur.state.values[:ie] + (np.array([tau]),) + (
            (E.reshape(3, 3) + tau * np.eye(3)).ravel(),) + cur.state.values[ie + 1:],
    )
    split = canonical_rate_terms(fit(st, data), data)
    Es = split.state.values[ie + 1]
    if abs(float(_ISO @ Es)) > 1e-3 * max(float(np.linalg.norm(Es)), 1e-12):
        # the canonical split was refused: the data tell the isotropic eddy term from a
        # time offset (second order, fast motion); the eddy term stays as it is
        return findings, cur, cv_cur
    placeholder = dataclasses.replace(findings[ie], effect=EffectKind.TIME_OFFSET.value)
    new_findings = findings[:ie] + [placeholder] + findings[ie:]
    # does the anisotropic remainder earn its place?
    ie2 = ie + 1
    wo = canonical_rate_terms(fit(_without(split.state, ie2), data), data)
    n_eff = _n_eff(split, data)
    keep = _bic(split.rss, n_eff, split.state.n_params()) - _bic(wo.rss, n_eff,
                                                                   wo.state.n_params())
    cv_split = heldout_rms(split.state, data, cfg)
    cv_wo = heldout_rms(wo.state, data, cfg)
    if keep > -cfg.bic_margin or _heldout_ok(wo, split, data, cfg, cv_wo) is None:
        return new_findings[:ie2] + new_findings[ie2 + 1:], wo, cv_wo
    return new_findings, split, cv_split


def _without(state: ModelState, i: int) -> ModelState:
    """``state`` without its ``i``-th term."""
    t = state.terms[i]
    return dataclasses.replace(
        state,
        terms=state.terms[:i] + state.terms[i + 1:],
        values=state.values[:i] + state.values[i + 1:],
        T_enu=np.eye(3) if t.kind is EffectKind.AXIS_TILT else state.T_enu,
    )


def _refit(
    cur: FitResult, term: Term, data: FitData, cfg: DiagnoseConfig
) -> tuple[FitResult, float] | None:
    """Refit with ``term``; return (fit, delta BIC) if the BIC drops by ``bic_margin``."""
    res = canonical_rate_terms(fit(cur.state.with_term(term), data), data)
    if not res.rss < cur.rss:
        return None
    n_eff = _n_eff(res, data)
    dbic = _bic(res.rss, n_eff, res.state.n_params()) - _bic(cur.rss, n_eff, cur.state.n_params())
    if dbic > -cfg.bic_margin:
        return None
    return res, float(dbic)


def _heldout_ok(
    cur: FitResult, res: FitResult, data: FitData, cfg: DiagnoseConfig, cv_old: float
) -> float | None:
    """Held-out RMS of the model with the new term, or None if it does not improve enough.

    The improvement in chi-square units of the (correlation-discounted) noise must clear the
    same bar as the BIC: a term that only fits noise does not predict new blocks.
    """
    cv_new = heldout_rms(res.state, data, cfg)
    n_eff = _n_eff(res, data)
    s2 = res.rss / res.residual_nT.size
    k = res.state.n_params() - cur.state.n_params()
    gain = (cv_old**2 - cv_new**2) * n_eff / s2
    if cv_new < cv_old * (1.0 - cfg.heldout_margin) and gain >= k * np.log(n_eff) + cfg.bic_margin:
        return cv_new
    return None


def _covariance(res: FitResult, data: FitData) -> np.ndarray:
    """Parameter covariance: ``s^2 (J'J)^-1`` times the residual-correlation inflation."""
    P = res.info.shape[0]
    dof = max(res.residual_nT.size - P, 1)
    s2 = res.rss / dof * inflation(res.residual_nT, data.t_s)
    H = res.info.copy()
    if data.B_known_enu_nT is not None:
        H[3:6, :] = 0.0
        H[:, 3:6] = 0.0
        H[3:6, 3:6] = np.eye(3)
    kinds = [t.kind for t in res.state.terms]
    if EffectKind.TIME_OFFSET in kinds and EffectKind.EDDY_CURRENT in kinds:
        # tr(E_s) = 0 (canonical_rate_terms): the shared direction belongs to tau
        o = res.state.offsets()[kinds.index(EffectKind.EDDY_CURRENT)]
        a = np.zeros(P)
        a[o : o + 9] = _ISO
        H = H + float(np.max(np.diag(H))) * np.outer(a, a)
    return s2 * np.linalg.pinv(H, rcond=1e-13)


def _sigma_for(res: FitResult, i: int, cov: np.ndarray, data: FitData) -> dict[str, Any]:
    term = res.state.terms[i]
    o = res.state.offsets()[i]
    blk = cov[o : o + term.n_params(), o : o + term.n_params()]
    return term_sigma(term, blk, res.state, data)


def _finding(
    cur: FitResult,
    res: FitResult,
    term: Term,
    st: ScoreTest,
    dbic: float,
    cv_before: float,
    cv_after: float,
    data: FitData,
) -> Finding:
    info = EFFECTS[term.kind]
    i = len(res.state.terms) - 1
    params = term_params(term, res.state.values[i], res.state, data)
    contrib = _contribution(cur.state, res.state, data)
    resid = cur.residual_nT
    frame = info.frame
    if frame == "enu":
        contrib_f = _to_enu(contrib, res.state, data)
        resid_f = _to_enu(resid, res.state, data)
    else:
        contrib_f, resid_f = contrib, resid
    if term.windows_s:
        windows = [[float(a), float(b)] for a, b in term.windows_s]
        m = term.indicator(data.t_s) > 0
        axes = _axes(contrib_f[m]) if m.any() else []
    else:
        windows = [[0.0, float(data.t_s[-1])]]
        axes = _axes(contrib_f)
    stride = max(1, len(data) // 4000)
    regressor = None
    if term.kind in (EffectKind.TIME_OFFSET, EffectKind.EDDY_CURRENT):
        regressor = evaluate(cur.state, data, jacobian=False).ydot0_nT_s[::stride]
    sigtr = Signature(data.t_s[::stride], resid_f[::stride], contrib_f[::stride], regressor)
    expl = explanation(term.kind, params, data.duration_s)
    return Finding(
        effect=term.kind.value,
        params=params,
        sigma={},
        evidence={
            "statistic": float(st.statistic),
            "delta_bic": float(dbic),
            "rms_before_nT": cur.rms_nT,
            "rms_after_nT": res.rms_nT,
            "heldout_rms_before_nT": float(cv_before),
            "heldout_rms_after_nT": float(cv_after),
        },
        where={"windows_s": windows, "axes": axes, "frame": frame},
        explanation=expl,
        signature=sigtr,
    )


# ----------------------------------------------------------------------------- stage


def fit_data_from(
    recording: Recording,
    aligned: AlignedSeries,
    *,
    reference_field_enu_nT: np.ndarray | None = None,
    max_samples: int | None = None,
) -> FitData:
    """Build the fitting data: stamps in s from the first magnetometer sample.

    The attitude track is the recording's attitude channel (so a time offset re-interpolates
    it); without one (turntable), the aligned attitude shifted back by the ``tau`` it was
    interpolated with.
    """
    t0 = int(recording.mag.t_ns[0]) if len(recording.mag) else int(aligned.t_ns[0])
    t_s = (np.asarray(aligned.t_ns, dtype=np.int64) - t0) * 1e-9
    if recording.attitude is not None and len(recording.attitude) >= 2:
        ta = (np.asarray(recording.attitude.t_ns, dtype=np.int64) - t0) * 1e-9
        # THE interpolator, as calibrate and restore: the same recording and model
        # give the same prediction
        track = AttitudeTrack(ta, np.asarray(recording.attitude.q_enu_body, dtype=float))
    else:
        track = AttitudeTrack(t_s - aligned.time_offset_s, np.asarray(aligned.q_enu_body))
    y = np.asarray(aligned.mag_nT, dtype=float)
    # a sample whose sensing time t - tau falls outside the attitude track cannot be
    # predicted (the track is held at its ends): for lags up to MAX_LAG_S the samples that
    # close to the track's ends are left out (a lag of 100 ms otherwise shows as a step in
    # the first 0.1 s)
    edge = (t_s >= track.t_s[0] + MAX_LAG_S) & (t_s <= track.t_s[-1] - MAX_LAG_S)
    if np.count_nonzero(edge) >= 0.9 * len(t_s):
        t_s, y = t_s[edge], y[edge]
        aligned_t_ns = np.asarray(aligned.t_ns)[edge]
    else:
        aligned_t_ns = np.asarray(aligned.t_ns)
    pos: dict[str, Any] = {}
    p = _positions_at(recording, aligned_t_ns)
    if p is not None:
        ok = np.isfinite(p).all(axis=1)
        t_s, y, p = t_s[ok], y[ok], p[ok]
        pos = {"p_m": p, "p_ref_m": p.mean(axis=0),
               "position_frame": recording.position.frame.value}  # type: ignore[union-attr]
    n_avail, stride = len(t_s), 1
    if max_samples is not None and len(t_s) > max_samples:
        stride = int(np.ceil(len(t_s) / max_samples))
        t_s, y = t_s[::stride], y[::stride]
        if pos:
            pos["p_m"] = pos["p_m"][::stride]
    B = None if reference_field_enu_nT is None else np.asarray(reference_field_enu_nT, float)
    return FitData(t_s, y, track, B_known_enu_nT=B, stride=stride, n_available=n_avail, **pos)


#: Positions are used only when at least this fraction of the samples has one.
MIN_POSITION_COVERAGE = 0.5


def _positions_at(recording: Recording, t_ns: np.ndarray) -> np.ndarray | None:
    """Positions at the magnetometer stamps (N, 3), m, NaN where unknown; None when unused.

    Samples without a position (lost markers: NaN rows, or gaps longer than 0.1 s) are
    left out of the diagnosis, for every model alike so that the BIC and held-out errors
    compare the same samples. When fewer than :data:`MIN_POSITION_COVERAGE` of the samples
    have a position, the positions are not used at all (``field_gradient`` is then not
    identifiable: no positions).
    """
    if recording.position is None or len(t_ns) == 0:
        return None
    p = recording.position.at(np.asarray(t_ns, dtype=np.int64))
    if np.mean(np.isfinite(p).all(axis=1)) < MIN_POSITION_COVERAGE:
        return None
    return p


def _heldout_split(state: ModelState, train: FitData, test: FitData, cfg: DiagnoseConfig,
                   t0_s: float) -> float:
    """Held-out RMS (nT) when the model is fitted on ``train`` and predicts ``test``.

    Like :func:`heldout_rms` (the same time blocks, counted from ``t0_s``: with the first
    sample of the diagnosis data the folds are exactly those of :func:`heldout_rms`), but the
    samples fitted and the samples predicted may differ: the repeats of a sample-and-hold
    sensor are predicted although only the first copies are fitted.
    """
    f_tr = np.floor((train.t_s - t0_s) / cfg.block_s).astype(np.int64) % cfg.n_folds
    f_te = np.floor((test.t_s - t0_s) / cfg.block_s).astype(np.int64) % cfg.n_folds
    start = dataclasses.replace(state, values=tuple(
        np.zeros_like(v) if t.kind in LOCAL_KINDS else v
        for t, v in zip(state.terms, state.values, strict=True)))
    sq, cnt = 0.0, 0
    for j in range(cfg.n_folds):
        te, tr = f_te == j, f_tr != j
        if te.sum() == 0 or tr.sum() < 10:
            continue
        res = fit(start, train.subset(tr), max_iter=6, rtol=1e-6)
        sub = test.subset(te)
        e = sub.y_nT - evaluate(res.state, sub, jacobian=False).y_nT
        sq += float(np.sum(e * e))
        cnt += e.size
    return float(np.sqrt(sq / max(cnt, 1)))


def sample_hold_finding(
    diag: Diagnosis,
    res: FitResult,
    data: FitData,
    recording: Recording,
    aligned: AlignedSeries,
    sh: SampleHold,
    cfg: DiagnoseConfig,
    *,
    reference_field_enu_nT: Any = None,
) -> tuple[Diagnosis, FitResult, FitData] | None:
    """Add the ``sample_hold`` finding: the final model refitted on the handled data.

    Two handlings are compared on the same messages (the diagnosis samples, repeats
    included) by their held-out RMS: (a) the repeats are left out of the fit and every
    message is predicted at the stamp of the first copy of its conversion; (b) as (a), with
    the conversions re-stamped on the sensor's native grid (``SampleHold.t_sensed_ns``). The
    better one is kept; without it (the messages fitted and predicted at their own stamps)
    is the final model of ``diag``. The finding is added when the handling lowers
    the held-out error; its evidence is the change of the in-sample and held-out RMS over the
    same messages.

    Returns
    -------
    (Diagnosis, FitResult, FitData) or None
        The diagnosis with the finding appended, the fit on the handled data, and that data;
        None when the handling does not help.

    """
    mag_t = np.asarray(recording.mag.t_ns, dtype=np.int64)
    t0 = int(mag_t[0])
    idx = np.clip(np.searchsorted(mag_t, t0 + np.round(data.t_s * 1e9).astype(np.int64)), 0,
                  len(mag_t) - 1)
    first_idx = np.maximum.accumulate(np.where(sh.first, np.arange(len(mag_t)), 0))
    al_idx = (np.arange(len(aligned)) if aligned.index is None
              else np.asarray(aligned.index, dtype=np.int64))
    keep = sh.first[al_idx]
    variants = {
        "first_stamp": mag_t[first_idx],
        "native_grid": np.asarray(sh.t_sensed_ns, dtype=np.int64),
    }
    best = None
    for name, t_new in variants.items():
        al_new = AlignedSeries(t_new[al_idx][keep], aligned.mag_nT[keep],
                               aligned.q_enu_body[keep], aligned.time_offset_s, al_idx[keep])
        train = fit_data_from(recording, al_new, reference_field_enu_nT=reference_field_enu_nT,
                              max_samples=cfg.max_samples)
        test = dataclasses.replace(data, t_s=(t_new[idx] - t0) * 1e-9)
        if len(train) < 30:
            continue
        cv = _heldout_split(res.state, train, test, cfg, float(data.t_s[0]))
        if best is None or cv < best[0]:
            best = (cv, name, train, test)
    # the same blocks as the handled variants and as diag.final's held-out error
    cv_old = _heldout_split(res.state, data, data, cfg, float(data.t_s[0]))
    if best is None or not best[0] < cv_old:
        return None
    cv_new, name, train, test = best
    res_h = fit(res.state, train)
    r_new = test.y_nT - evaluate(res_h.state, test, jacobian=False).y_nT
    rss_new = float(np.sum(r_new * r_new))
    n_eff = _n_eff(res, data)
    s2 = res.rss / res.residual_nT.size
    span = float(mag_t[-1] - mag_t[0]) * 1e-9
    p = sh.params()
    restamped = name == "native_grid"
    expl = EFFECTS[EffectKind.SAMPLE_HOLD].physics + "; signature: " + EFFECTS[
        EffectKind.SAMPLE_HOLD].signature + ". " + sh.explanation(restamped=restamped) + (
        f" Compared on the same messages, the held-out error goes from {cv_old:.1f} to "
        f"{cv_new:.1f} nT. Read the sensor at its native rate (or publish only new "
        "conversions, stamped when they were sensed)")
    fd = Finding(
        effect=EffectKind.SAMPLE_HOLD.value,
        params=p,
        sigma={"native_rate_hz": 1.0 / max(span, 1e-9),
               "repeated_fraction": float(np.sqrt(p["repeated_fraction"] * (
                   1 - p["repeated_fraction"]) / len(mag_t)))},
        evidence={
            # no parameter is added: the in-sample RSS over the messages cannot rise or fall
            # by fitting, so the statistic and the BIC change are those of the held-out error
            "statistic": float((cv_old**2 - cv_new**2) * n_eff / s2),
            "delta_bic": float(n_eff * np.log(max(cv_new, 1e-30) ** 2 / max(cv_old, 1e-30) ** 2)),
            "rms_before_nT": res.rms_nT,
            "rms_after_nT": float(np.sqrt(rss_new / max(r_new.size, 1))),
            "heldout_rms_before_nT": cv_old,
            "heldout_rms_after_nT": float(cv_new),
        },
        where={"windows_s": [[0.0, float(data.t_s[-1])]], "axes": ["x", "y", "z"],
               "frame": "mag"},
        explanation=expl,
    )
    final = {
        "effects": list(diag.final["effects"]) + [fd.effect],
        "residual_rms_nT": fd.evidence["rms_after_nT"],
        "heldout_rms_nT": float(cv_new),
    }
    return (dataclasses.replace(diag, findings=diag.findings + (fd,), final=final), res_h,
            train)


def _model_values(term: Term, value: np.ndarray, data: FitData) -> dict[str, Any]:
    """Return the fitted values of a ``disturbance`` / ``field_drift`` / ``heading_drift`` term.

    The CONVENTIONS params of these terms (``peak_nT``, ``peak_to_peak_nT``) describe them
    but cannot reproduce them; the calibration also carries the fitted values so that
    :meth:`pipeline.calibration.Calibration.predict` includes them (the residual of the
    final model is then the same number everywhere).
    """
    if term.kind is EffectKind.DISTURBANCE:
        knots = term.knots()
        v = np.asarray(value, dtype=float).reshape(-1, 3)
        out, i = [], 0
        for kn in knots:
            out.append(v[i:i + len(kn)].tolist())
            i += len(kn)
        return {"knots_s": [k.tolist() for k in knots], "knot_field_nT": out}
    if term.kind is EffectKind.FIELD_DRIFT:
        span = float(data.track.t_s[-1]) if data.track.t_s[-1] > 0 else 1.0
        return {"legendre_nT": np.asarray(value, dtype=float).reshape(-1, 3).tolist(),
                "span_s": span}
    if term.kind is EffectKind.HEADING_DRIFT:
        span = float(data.track.t_s[-1]) if data.track.t_s[-1] > 0 else 1.0
        return {"legendre_rad": np.asarray(value, dtype=float).reshape(-1).tolist(),
                "span_s": span}
    return {}


def calibration_from(res: FitResult, data: FitData, findings: tuple[Finding, ...]) -> Calibration:
    """Return the final model as a Calibration; terms beyond D, o, tau go to ``effects``."""
    st = res.state
    cov = _covariance(res, data)
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    sig_rot = np.degrees(sd[0:3])
    D = st.D() if st.value(EffectKind.SOFT_IRON) is not None else None
    o = st.value(EffectKind.HARD_IRON)
    tau = st.value(EffectKind.TIME_OFFSET)
    extra: dict[str, Any] = {}
    sig: dict[str, Any] = {}
    for i, t in enumerate(st.terms):
        blk = slice(st.offsets()[i], st.offsets()[i] + t.n_params())
        if t.kind is EffectKind.HARD_IRON:
            sig["offset"] = sd[blk]
        elif t.kind is EffectKind.SOFT_IRON:
            sig["D"] = np.asarray(term_sigma(t, cov[blk, blk], st, data)["D"])
        elif t.kind is EffectKind.TIME_OFFSET:
            sig["tau"] = float(sd[blk][0])
        else:
            params = term_params(t, st.values[i], st, data)
            params.update(_model_values(t, st.values[i], data))
            extra.setdefault(t.kind.value, []).append(params)
    effects = {k: (v[0] if len(v) == 1 else v) for k, v in extra.items()}
    return Calibration(
        R_body_mag=st.R_body_mag,
        sigma_rotvec_deg=sig_rot,
        B_enu_nT=st.B_enu_nT,
        estimator="diagnose",
        residual_rms_nT=res.rms_nT,
        n_samples=len(data),
        D=D,
        offset_nT=o,
        time_offset_s=None if tau is None else float(tau[0]),
        sigma_D=sig.get("D"),
        sigma_offset_nT=sig.get("offset"),
        sigma_time_offset_s=sig.get("tau"),
        sigma_B_enu_nT=None if data.B_known_enu_nT is not None else sd[3:6],
        effects=effects,
    )


def final_split(res: FitResult, data: FitData):
    """Refit the final model on two contiguous halves of equal rotation information.

    Returns a :class:`stages.estimators.checks.SplitCheck` (the halves' rotations, their
    difference and its chi-square under the halves' covariances), or None when a half is too
    small. A term that the motion barely determines, or physics the final model still leaves
    out, shows up as halves that disagree.
    """
    from pipeline.geometry import matrix_to_quat, quat_to_rotvec
    from stages.estimators.checks import SplitCheck, info_halves

    if len(data) < 200:
        return None
    ev = evaluate(res.state, data)
    Jr = ev.J[:, :, 0:3]
    first = info_halves(np.einsum("nip,nip->n", Jr, Jr))
    out = []
    for m in (first, ~first):
        sub = data.subset(m)
        if len(sub) < 50:
            return None
        r = fit(res.state, sub)
        cov = _covariance(r, sub)
        out.append((r.state.R_body_mag, np.clip(np.diag(cov)[0:3], 0.0, None)))
    (Ra, va), (Rb, vb) = out

    def rv(R: np.ndarray) -> np.ndarray:
        return quat_to_rotvec(matrix_to_quat(R))

    d = rv(Ra @ Rb.T)
    var = va + vb
    ok = np.isfinite(var) & (var > 0)
    chi2 = float(np.sum(d[ok] ** 2 / var[ok]))
    t_split = float(data.t_s[np.flatnonzero(~first)[0]] - data.t_s[0])
    return SplitCheck(np.degrees(rv(Ra)), np.degrees(rv(Rb)), np.degrees(d), chi2, t_split)


@dataclass(frozen=True)
class Diagnose:
    """Stage: find, name, model and verify what the calibration model leaves out.

    Parameters
    ----------
    config : DiagnoseConfig
    reference_field_enu_nT : tuple of 3 floats, optional
        Known background field (ENU, nT); the field is then not estimated (and ``axis_tilt``
        becomes identifiable on a turntable).
    max_gap_s : float or None
        Attitude gap rule of the final model's residual over the whole recording (as the
        Restore stage); None: the automatic rule.

    The final residual (``diagnosis.final.residual_rms_nT`` and the final calibration's
    ``residual_rms_nT``) is that of the final model over every sample of the recording with
    a usable attitude (:func:`stages.restore.restore_samples`): the number the restored
    ``<mag>/residual`` channel, the residual figure and the report show.

    """

    config: DiagnoseConfig = field(default_factory=DiagnoseConfig)
    reference_field_enu_nT: tuple[float, float, float] | None = None
    max_gap_s: float | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "aligned", "calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"diagnosis", "calibration", "restored"})

    def run(self, ctx: Context) -> Context:
        """Diagnose ``ctx.recording``; the final model replaces ``ctx.calibration``."""
        rec, al = ctx.recording, ctx.aligned
        data = fit_data_from(
            rec, al, reference_field_enu_nT=self.reference_field_enu_nT,
            max_samples=self.config.max_samples,
        )
        init = None
        cal = ctx.calibration
        if cal is not None:
            init = ModelState(np.asarray(cal.R_body_mag), np.asarray(cal.B_enu_nT))
        diag, res = diagnose_data(data, init, self.config, turntable=rec.turntable is not None)
        data = dataclasses.replace(data, noise_model=res.noise_model)
        sh = detect_sample_hold(rec.mag.t_ns, rec.mag.values)
        extra: dict[str, Any] = {}
        if sh is not None:
            out = sample_hold_finding(diag, res, data, rec, al, sh, self.config,
                                      reference_field_enu_nT=self.reference_field_enu_nT)
            if out is not None:
                diag, res, data = out
                extra["sample_hold"] = diag.findings[-1].params
        final = calibration_from(res, data, diag.findings)
        if extra:
            final = dataclasses.replace(final, effects={**(final.effects or {}), **extra})
        from stages.estimators.checks import apply_split

        split = final_split(res, data)
        if cal is not None:
            from stages.estimate import carry_checks

            explained = bool(diag.findings) and (split is None or split.consistent)
            final = carry_checks(cal, final, explained=explained)
        if split is not None:
            final = final.replace(checks={**final.checks, "split_final": split.to_dict()})
            final = apply_split(final, split, " under the final model")
        iron = [e for e, _ in diag.not_identifiable if e in ("hard_iron", "soft_iron")]
        if iron and len(final.unobservable_axes_body) == 0:
            doubt = (
                f"the motion cannot determine {' or '.join(x.replace('_', ' ') for x in iron)}"
                ": the misalignment assumes there is none; a magnetised or soft-magnetic part "
                "near the sensor would bias it (see the diagnosis)"
            )
            final = final.replace(checks={**final.checks, "doubts": list(
                final.checks.get("doubts", ())) + [doubt]})
        fit_samples: dict[str, Any] = {"n": len(data), "stride": int(data.stride),
                                       "of": int(data.n_available or len(data))}
        if "sample_hold" in extra:
            fit_samples["note"] = ", sample-and-hold repeats left out"
        final = final.replace(checks={**final.checks, "fit_samples": fit_samples})
        restored = None
        if rec.attitude is not None and len(rec.attitude) >= 2:
            from stages.restore import restore_samples

            restored = restore_samples(rec, final, max_gap_s=self.max_gap_s)
            rms = restored.residual_rms_nT
            if np.isfinite(rms):
                final = final.replace(residual_rms_nT=rms)
                diag = dataclasses.replace(diag, final={**diag.final, "residual_rms_nT": rms})
        # the restore result of the final model goes along: Restore keeps it (same model)
        return ctx.replace(diagnosis=diag, calibration=final, restored=restored)


# ----------------------------------------------------------------------------- figures


def finding_figures(diagnosis: Diagnosis, dpi: int = 100) -> list[tuple[str, bytes]]:
    """One PNG per finding showing its signature in the residual.

    Time offset / eddy currents: residual before against the reading's rate of change.
    Local effects: residual norm against time with the located windows shaded.
    Others: residual before and the fitted contribution against time, per axis. Colours
    and fonts are the report's (:mod:`pipeline.style`).

    Returns
    -------
    list of (title, png bytes)

    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from pipeline import style

    out = []
    for f in diagnosis.findings:
        s = f.signature
        if s is None:
            continue
        with plt.rc_context(style.rc() | {"savefig.dpi": dpi, "figure.dpi": dpi}):
            fig, ax = plt.subplots(figsize=(12, 3.8))
            frame = f.where["frame"]
            if s.regressor is not None:
                for i, c in enumerate("xyz"):
                    ax.plot(s.regressor[:, i], s.residual_before_nT[:, i], ".", ms=2,
                            alpha=0.4, color=style.AXIS[i], label=f"{frame} {c}")
                ax.set_xlabel(f"rate of change of the reading ({frame} frame, nT/s)")
                ax.set_ylabel("residual before (nT)")
                ax.legend(markerscale=5, ncol=3, loc="upper right")
            elif f.effect in ("disturbance", "hard_iron_step"):
                ax.plot(s.t_s, np.linalg.norm(s.residual_before_nT, axis=1), lw=0.7,
                        color=style.BEFORE, label="|residual| before this term")
                ax.plot(s.t_s, np.linalg.norm(s.contribution_nT, axis=1), lw=1.6,
                        color=style.AFTER, label="|fitted term|")
                for a, b in f.where["windows_s"]:
                    ax.axvspan(a, b, color=style.EVENT, alpha=0.5, lw=0, zorder=0)
                h, lab = ax.get_legend_handles_labels()
                ax.legend(h + [Patch(color=style.EVENT, alpha=0.5)],
                          lab + ["window found"], loc="upper left", ncol=3)
                ax.margins(y=0.25)  # room for the key above the curves
                ax.set_xlabel("time from the first sample (s)")
                ax.set_ylabel("nT")
            else:
                for i, c in enumerate("xyz"):
                    ax.plot(s.t_s, s.residual_before_nT[:, i], lw=0.5, alpha=0.35,
                            color=style.AXIS[i], label=f"residual {c}")
                    ax.plot(s.t_s, s.contribution_nT[:, i], lw=1.6, color=style.AXIS[i],
                            label=f"fitted term {c}")
                ax.set_xlabel("time from the first sample (s)")
                ax.set_ylabel(f"nT ({frame} frame)")
                ax.legend(ncol=3, loc="upper right")
            title = style.minus(f"{f.effect}: {_estimate_text(f)}").replace(" uT/m", " \u00b5T/m")
            ax.set_title(title)
            fig.tight_layout()
            buf = io.BytesIO()
            fig.savefig(buf, format="png")
            plt.close(fig)
        out.append((title, buf.getvalue()))
    return out

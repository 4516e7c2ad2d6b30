"""Global checks of a fit: honest covariance, determinability, multi-start, split halves.

More in docs/modules.md, ``stages.estimators.checks``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.core.geometry import so3_log
from stages.diagnose.model import CONFOUND_RATIO
from stages.estimators.base import RELATIVE_INFO_THRESHOLD

F64 = NDArray[np.float64]

#: Blocks of the sandwich covariance, s. Residual correlation longer than this (slow physics
#: the model leaves out) is caught by the split-half check instead.
BLOCK_S = 1.0
#: At least this many blocks: shorter recordings get shorter blocks (the block covariance has
#: about ``n_blocks`` degrees of freedom, so its sigmas err by ``1 / sqrt(2 n_blocks)``).
MIN_BLOCKS = 40
#: 95 % quantile of chi-square with 3 degrees of freedom: halves that disagree by more are
#: inconsistent with the covariance (the model leaves out physics that changes in time).
SPLIT_CHI2_95 = 7.815


def block_index(t_ns: NDArray[np.int64], block_s: float = BLOCK_S,
                min_blocks: int = MIN_BLOCKS) -> NDArray[np.int64]:
    """Block number of every sample, (N,).

    ``K`` blocks of equal duration divide the span exactly (``K`` the larger of
    ``span / block_s`` and ``min_blocks``), so that the partition is the same read forwards
    or backwards in time.
    """
    t = np.asarray(t_ns, np.int64)
    span = max(float(t[-1] - t[0]) * 1e-9, 1e-9)
    k = max(int(round(span / block_s)), min_blocks)
    x = (t - t[0]).astype(float) * 1e-9 / span
    return np.minimum((x * k).astype(np.int64), k - 1)


def scores(J: F64, W: F64 | None, w: F64, r: F64) -> F64:
    """Per-sample scores ``g_i = w_i J_i^T W_i r_i``, (N, P)."""
    Wr = r if W is None else (W @ r[:, :, None])[:, :, 0]
    return np.einsum("nip,ni->np", J, Wr * w[:, None])


def sandwich_cov(J: F64, W: F64 | None, w: F64, r: F64, t_ns: NDArray[np.int64],
                 H_pinv: F64, cov_white: F64) -> tuple[F64, float]:
    """Block (batch-means) sandwich covariance and the effective-sample factor.

    Parameters
    ----------
    J : ndarray (N, 3, P)
        Jacobian of the prediction at the solution.
    W : ndarray (N, 3, 3) or None
        Per-sample inverse covariances (None: identity).
    w : ndarray (N,)
        Robust weights.
    r : ndarray (N, 3)
        Residuals, nT.
    t_ns : ndarray int64 (N,)
        Stamps (blocks are contiguous in time).
    H_pinv : ndarray (P, P)
        The (truncated) inverse of ``J^T W J`` used for the white covariance.
    cov_white : ndarray (P, P)
        The white-noise covariance; the result is never smaller on its diagonal.

    Returns
    -------
    cov : ndarray (P, P)
    n_eff_fraction : float
        Effective fraction of independent samples for the rotation-like leading parameters:
        mean over the first three parameters of ``var_white / var_sandwich`` (at most 1).

    """
    g = scores(J, W, w, r)
    blk = block_index(t_ns)
    G = np.zeros((int(blk[-1]) + 1, g.shape[1]))
    np.add.at(G, blk, g)
    S = G.T @ G
    cov = H_pinv @ S @ H_pinv
    cov = 0.5 * (cov + cov.T)
    dw = np.sqrt(np.maximum(np.diag(cov_white), 0.0))
    ds = np.sqrt(np.maximum(np.diag(cov), 0.0))
    # Never below the white covariance: a block estimate that comes out smaller only tells
    # the noise of the estimate, not a negative correlation worth trusting.
    k = np.where(ds > 0, np.maximum(dw / np.where(ds > 0, ds, 1.0), 1.0), 1.0)
    cov = cov * k[:, None] * k[None, :]
    ds = ds * k
    lead = slice(0, min(3, len(dw)))
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(ds[lead] > 0, (dw[lead] / ds[lead]) ** 2, 1.0)
    return cov, float(np.clip(np.mean(frac), 0.0, 1.0))


def per_sample_rot_info(J: F64, W: F64 | None, rot: slice) -> F64:
    """Trace of each sample's rotation information ``J_i^T W_i J_i`` (rot block), (N,)."""
    Jr = J[:, :, rot]
    WJ = Jr if W is None else W @ Jr
    return np.einsum("nip,nip->n", Jr, WJ)


def info_halves(info: F64) -> NDArray[np.bool_]:
    """Mask of the first of two contiguous halves that carry equal rotation information."""
    c = np.cumsum(np.maximum(info, 0.0))
    if c[-1] <= 0:
        half = len(info) // 2
    else:
        half = int(np.searchsorted(c, 0.5 * c[-1])) + 1
    m = np.zeros(len(info), bool)
    m[:max(1, min(half, len(info) - 1))] = True
    return m


@dataclass(frozen=True)
class SplitCheck:
    """Split-half consistency of the rotation.

    Attributes
    ----------
    rotvec_a_deg, rotvec_b_deg : ndarray (3,)
        Rotation vectors of the two halves (body frame).
    diff_deg : ndarray (3,)
        ``log(R_a R_b^T)``, deg, body frame.
    chi2 : float
        ``d^T (Cov_a + Cov_b)^-1 d`` (3 degrees of freedom under the model).
    split_s : float
        Where the halves meet, s from the first sample.

    """

    rotvec_a_deg: F64
    rotvec_b_deg: F64
    diff_deg: F64
    chi2: float
    split_s: float

    @classmethod
    def compare(cls, a, b, split_s: float) -> SplitCheck:
        """Compare the rotations of two calibrations fitted to the halves of a recording.

        ``chi2`` weighs the difference by the halves' own rotation variances (the axes with
        a finite, positive variance); ``split_s``: where the halves meet, s.
        """
        d = so3_log(a.R_body_mag @ b.R_body_mag.T)
        var = np.radians(a.sigma_rotvec_deg) ** 2 + np.radians(b.sigma_rotvec_deg) ** 2
        ok = np.isfinite(var) & (var > 0)
        chi2 = float(np.sum(d[ok] ** 2 / var[ok]))
        return cls(a.rotvec_body_mag_deg, b.rotvec_body_mag_deg, np.degrees(d), chi2,
                   float(split_s))

    @property
    def consistent(self) -> bool:
        """Whether the halves agree within the 95 % chi-square bound."""
        return bool(self.chi2 <= SPLIT_CHI2_95)

    def to_dict(self) -> dict:
        """JSON-able summary."""
        return {
            "rotvec_first_half_deg": [float(x) for x in self.rotvec_a_deg],
            "rotvec_second_half_deg": [float(x) for x in self.rotvec_b_deg],
            "difference_deg": [float(x) for x in self.diff_deg],
            "chi2": float(self.chi2),
            "split_s": float(self.split_s),
        }


def split_inflation(diff_rad: F64) -> F64:
    """Covariance (rad^2, 3x3) added to the rotation when the halves disagree significantly.

    The halves' difference ``d`` estimates the spread of a bias that changes over the
    recording (physics the model leaves out); each half's bias then has a spread of about
    ``|d| / sqrt(2)`` along ``d``, and the whole recording's estimate is given that spread:
    ``d d^T / 2``. Conservative on purpose: a bias common to both halves is not seen at all.
    """
    d = np.asarray(diff_rad, float).reshape(3)
    return np.outer(d, d) / 2.0


def confounded(ratios: dict[str, F64], names: list[str]) -> dict[str, float]:
    """Blocks among ``names`` with a direction below :data:`CONFOUND_RATIO` (and above null).

    Parameters
    ----------
    ratios : dict of str -> ndarray
        ``Analysis.block_ratio`` (fraction of information kept per eigen-direction).
    names : list of str
        Blocks to look at.

    Returns
    -------
    dict of str -> float
        Block name -> its smallest non-null ratio, for the confounded blocks.

    """
    out = {}
    for n in names:
        lam = np.asarray(ratios.get(n, np.ones(1)), float)
        live = lam[lam >= RELATIVE_INFO_THRESHOLD]
        if live.size and float(np.min(live)) < CONFOUND_RATIO:
            out[n] = float(np.min(live))
    return out


#: The halves' disagreement makes the result questionable when it more than doubles a sigma
#: (below that it is a warning: the sigmas already carry it).
SPLIT_DOUBT_GROWTH = 2.0


def apply_split(cal, split: SplitCheck, what: str = ""):
    """Return ``cal`` with an inconsistent split's disagreement in its rotation sigmas.

    Parameters
    ----------
    cal : Calibration
        The fit whose rotation was split.
    split : SplitCheck
        Its split-half check.
    what : str
        Words for the model that was split (e.g. ``" under the final model"``).

    Returns
    -------
    cal : Calibration
        Sigmas inflated by :func:`split_inflation`; the words are appended to ``warnings``
        when no sigma more than doubles, else to ``checks["doubts"]`` (the verdict).

    """
    if split.consistent:
        return cal
    before = np.asarray(cal.sigma_rotvec_deg, float)
    var = np.radians(before) ** 2 + np.diag(split_inflation(np.radians(split.diff_deg)))
    after = np.degrees(np.sqrt(var))
    words = (
        f"the two halves of the recording disagree by {np.linalg.norm(split.diff_deg):.2f} "
        f"deg{what} (chi-square {split.chi2:.0f} for 3 degrees of freedom): the model leaves "
        "out physics that changes over the recording, or a term the motion barely determines; "
        "sigmas include the disagreement"
    )
    fin = np.isfinite(before) & (before > 0)
    grow = float(np.max(after[fin] / before[fin])) if np.any(fin) else 1.0
    cal = cal.replace(sigma_rotvec_deg=after)
    if grow > SPLIT_DOUBT_GROWTH:
        doubts = [d for d in cal.checks.get("doubts", ()) if not d.startswith("the two halves")]
        return cal.replace(checks={**cal.checks, "doubts": doubts + [words]})
    return cal.replace(warnings=cal.warnings + (words,))

"""Global checks of a fit: honest covariance, determinability, multi-start, split halves.

More in docs/modules.md, ``stages.estimators.checks``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtri

from pipeline.core.geometry import so3_log
from pipeline.core.words import sig2
from pipeline.model.calibration import SIGMA_FLOOR_DEG
from pipeline.model.effects.base import CONFOUND_RATIO
from stages.estimators.base import RELATIVE_INFO_THRESHOLD

F64 = NDArray[np.float64]

#: Blocks of the sandwich covariance, s. Residual correlation longer than this (slow physics
#: the model leaves out) is caught by the split-half check instead.
BLOCK_S = 1.0
#: At least this many blocks: shorter recordings get shorter blocks (the block covariance has
#: about ``n_blocks`` degrees of freedom, so its sigmas err by ``1 / sqrt(2 n_blocks)``).
MIN_BLOCKS = 40
#: Stated false-alarm rate of the split-halves check: the probability that the halves of a
#: recording the model describes (noise only) fail it. The limit is the chi-square quantile
#: at ``1 - SPLIT_FALSE_ALARM`` for the directions the halves determine (:func:`split_limit`);
#: measured on independent nulls by bench/halves_null.py (docs/testing.md).
SPLIT_FALSE_ALARM = 0.05
#: A direction of the halves' difference covariance below this fraction of its largest
#: eigenvalue is one the motion does not determine (its variance is rounding): left out of
#: the statistic and of its degrees of freedom.
SPLIT_RANK_RCOND = 1e-9


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


def split_limit(dof: int) -> float:
    """Chi-square limit of the halves' statistic with ``dof`` degrees of freedom."""
    return float(chdtri(max(int(dof), 1), SPLIT_FALSE_ALARM))


def undetermined_directions(*cals) -> F64:
    """Return the directions (body frame, (k, 3)) about which calibrations leave R open.

    Its ``unobservable_axes_body`` and the body axes whose sigma is infinite, of every
    calibration given (None skipped): the halves are compared about the other directions.
    """
    dirs: list[F64] = []
    for c in cals:
        if c is None:
            continue
        dirs += [np.asarray(a, float) for a in c.unobservable_axes_body]
        sig = np.asarray(c.sigma_rotvec_deg, float)
        dirs += [np.eye(3)[i] for i in range(3) if not np.isfinite(sig[i])]
    return np.array(dirs, float).reshape(-1, 3)


def split_statistic(d_rad: F64, cov_rad2: F64, excluded: F64 | None = None
                    ) -> tuple[float, int]:
    """Chi-square of the halves' difference ``d`` under the covariance of the difference.

    Parameters
    ----------
    d_rad : ndarray (3,)
        Rotation vector of ``R_a R_b^T``, rad.
    cov_rad2 : ndarray (3, 3)
        Covariance of that difference: the sum of the halves' own rotation covariances (the
        halves hold disjoint samples), each with its correlated-noise inflation. A
        non-finite diagonal entry marks an axis the motion does not determine.
    excluded : ndarray (k, 3), optional
        Directions the whole recording does not determine (:func:`undetermined_directions`):
        a half's fit may wander about them without meaning anything, so they are projected
        out of the difference and its covariance.

    Returns
    -------
    chi2 : float
        ``d^T (C + 2 f^2 I)^-1 d`` over the directions the halves determine, ``f`` the
        numerical floor :data:`pipeline.model.calibration.SIGMA_FLOOR_DEG` of each half's
        sigma: a difference below the floor is agreement, however small the sigmas.
    dof : int
        The number of those directions (0: nothing to compare).

    """
    d = np.asarray(d_rad, float).reshape(3)
    C = np.asarray(cov_rad2, float).reshape(3, 3)
    fin = np.isfinite(np.diag(C))
    E = [np.eye(3)[i] for i in range(3) if not fin[i]]
    if excluded is not None and np.size(excluded):
        E += list(np.asarray(excluded, float).reshape(-1, 3))
    # an orthonormal basis Q of the directions compared: the complement of the excluded
    if E:
        u, sv, _ = np.linalg.svd(np.array(E).T, full_matrices=True)
        Q = u[:, int(np.sum(sv > 1e-6)):]
    else:
        Q = np.eye(3)
    if Q.shape[1] == 0:
        return 0.0, 0
    Cf = np.where(np.isfinite(C), C, 0.0)
    Cq = Q.T @ (0.5 * (Cf + Cf.T)) @ Q
    w, V = np.linalg.eigh(Cq)
    top = float(np.max(w))
    # directions of rounding-level variance are not determined by the motion; with no
    # variance at all (a noise-free fit) every direction is compared under the floor alone
    keep = w > SPLIT_RANK_RCOND * top if top > 0 else np.ones(len(w), bool)
    floor2 = 2.0 * np.radians(SIGMA_FLOOR_DEG) ** 2
    z = V[:, keep].T @ (Q.T @ d)
    chi2 = float(np.sum(z**2 / (np.maximum(w[keep], 0.0) + floor2)))
    return chi2, int(np.sum(keep))


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
        :func:`split_statistic`: the difference under the covariance of the difference
        (``Cov_a + Cov_b``, numerical floor included), over the ``dof`` directions the
        halves determine.
    split_s : float
        Where the halves meet, s from the first sample.
    dof : int
        Degrees of freedom of ``chi2``.

    """

    rotvec_a_deg: F64
    rotvec_b_deg: F64
    diff_deg: F64
    chi2: float
    split_s: float
    dof: int = 3

    @classmethod
    def compare(cls, a, b, split_s: float, cov_a: F64 | None = None,
                cov_b: F64 | None = None, excluded: F64 | None = None) -> SplitCheck:
        """Compare the rotations of two calibrations fitted to the halves of a recording.

        ``cov_a``, ``cov_b``: the halves' rotation covariances, rad^2 (3x3, with their
        correlated-noise inflation); without them the halves' sigmas (no correlation between
        axes). ``split_s``: where the halves meet, s. ``excluded``: directions not compared
        (:func:`split_statistic`).
        """
        d = so3_log(a.R_body_mag @ b.R_body_mag.T)

        def cov(c, given: F64 | None) -> F64:
            if given is not None:
                return np.asarray(given, float)
            return np.diag(np.radians(np.asarray(c.sigma_rotvec_deg, float)) ** 2)

        chi2, dof = split_statistic(d, cov(a, cov_a) + cov(b, cov_b), excluded)
        return cls(a.rotvec_body_mag_deg, b.rotvec_body_mag_deg, np.degrees(d), chi2,
                   float(split_s), dof)

    @property
    def limit(self) -> float:
        """The statistic's limit at the stated false-alarm rate (:func:`split_limit`)."""
        return split_limit(self.dof)

    @property
    def consistent(self) -> bool:
        """Whether the halves agree: within the limit, or nothing to compare."""
        return bool(self.dof == 0 or self.chi2 <= self.limit)

    def to_dict(self) -> dict:
        """JSON-able summary."""
        return {
            "rotvec_first_half_deg": [float(x) for x in self.rotvec_a_deg],
            "rotvec_second_half_deg": [float(x) for x in self.rotvec_b_deg],
            "difference_deg": [float(x) for x in self.diff_deg],
            "chi2": float(self.chi2),
            "dof": int(self.dof),
            "limit": float(self.limit),
            "consistent": self.consistent,
            "split_s": float(self.split_s),
        }


def split_inflation(diff: F64) -> F64:
    """Covariance added to an estimate when its halves disagree significantly.

    The halves' difference ``d`` (any parameter vector: the rotation's, rad, or a term's)
    estimates the spread of a bias that changes over the recording (physics the model leaves
    out); each half's bias then has a spread of about ``|d| / sqrt(2)`` along ``d``, and the
    whole recording's estimate is given that spread: ``d d^T / 2``. Conservative on purpose:
    a bias common to both halves is not seen at all.
    """
    d = np.asarray(diff, float).ravel()
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


HALVES_DOUBT = "the two halves of the recording disagree"


def apply_split(cal, split: SplitCheck, what: str = ""):
    """Return ``cal`` with an inconsistent split's disagreement in its sigmas and doubts.

    One rule, the same for every model and every command: halves that fail the check at its
    stated false-alarm rate (:data:`SPLIT_FALSE_ALARM`) put their disagreement into the
    rotation's sigmas (:func:`split_inflation`) and are a doubt (the verdict is at most
    QUESTIONABLE); halves that pass change nothing.

    Parameters
    ----------
    cal : Calibration
        The fit whose rotation was split.
    split : SplitCheck
        Its split-half check.
    what : str
        Words for the model that was split (e.g. ``" under the final model"``).

    """
    if split.consistent:
        return cal
    before = np.asarray(cal.sigma_rotvec_deg, float)
    var = np.radians(before) ** 2 + np.diag(split_inflation(np.radians(split.diff_deg)))
    after = np.degrees(np.sqrt(var))
    words = (
        f"{HALVES_DOUBT} by {sig2(float(np.linalg.norm(split.diff_deg)))} "
        f"deg{what} (chi-square {split.chi2:.0f} for {split.dof} degrees of freedom, above "
        f"{split.limit:.1f}, which halves agreeing within their sigmas exceed "
        f"{100 * SPLIT_FALSE_ALARM:.0f} % of the time): the model leaves out physics that "
        "changes over the recording, or a term the motion barely determines; sigmas include "
        "the disagreement"
    )
    doubts = [d for d in cal.checks.get("doubts", ()) if not d.startswith("the two halves")]
    return cal.replace(sigma_rotvec_deg=after,
                       checks={**cal.checks, "doubts": doubts + [words]})

"""Magnetometer-only hard/soft-iron fit (algebraic ellipsoid), and a two-step baseline.

More in docs/modules.md, ``stages.estimators.ellipsoid``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np

from pipeline.core.errors import NotObservableError
from pipeline.core.geometry import skew
from pipeline.model.calibration import Calibration
from stages.estimators.base import (
    F64,
    EstimationProblem,
    analyse,
    canonical_axis,
    init_rotation,
    rotation_words,
    sigma_with_null,
)

#: The readings must spread over three dimensions: the smallest principal spread of the
#: centred readings must be at least this fraction of the largest for an ellipsoid fit.
MIN_SPREAD_RATIO = 0.05


def fit_ellipsoid(mag_nT: F64) -> tuple[F64, F64]:
    """Algebraic ellipsoid fit.

    Parameters
    ----------
    mag_nT : ndarray (N, 3)
        Raw readings, mag frame.

    Returns
    -------
    offset_nT : ndarray (3,)
    D : ndarray (3, 3)
        Symmetric positive definite, scaled so that the corrected field has the mean norm of
        the raw readings (the field magnitude is not known to the magnetometer alone).

    Raises
    ------
    NotObservableError
        If the readings do not cover three dimensions (a single-axis rotation draws a circle).

    """
    y = np.asarray(mag_nT, float)
    mu = y.mean(0)
    sc = float(np.sqrt(np.mean(np.sum((y - mu) ** 2, 1)))) or 1.0
    spread = np.linalg.svd((y - mu) / sc, compute_uv=False)
    if len(y) < 10 or spread[-1] < MIN_SPREAD_RATIO * spread[0]:
        raise NotObservableError(
            "the magnetometer readings do not cover three dimensions, an ellipsoid (hard/soft "
            "iron) fit is not possible",
            hint="turn the sensor about at least two axes",
        )
    x = (y - mu) / sc  # conditioning
    X, Y, Z = x.T
    M = np.stack(
        [X * X, Y * Y, Z * Z, 2 * X * Y, 2 * X * Z, 2 * Y * Z, X, Y, Z, np.ones_like(X)], 1
    )
    _, _, Vt = np.linalg.svd(M, full_matrices=False)
    a = Vt[-1]
    Q = np.array([[a[0], a[3], a[4]], [a[3], a[1], a[5]], [a[4], a[5], a[2]]])
    q = a[6:9]
    c = a[9]
    if np.linalg.det(Q) < 0:
        Q, q, c = -Q, -q, -c
    w = np.linalg.eigvalsh(Q)
    if w[0] <= 0:
        raise NotObservableError("the magnetometer readings do not fit an ellipsoid")
    oc = -0.5 * np.linalg.solve(Q, q)
    k = float(oc @ Q @ oc - c)
    if k <= 0:
        raise NotObservableError("the magnetometer readings do not fit an ellipsoid")
    A = Q / k
    w, V = np.linalg.eigh(A)
    D = (V / np.sqrt(w)) @ V.T  # symmetric square root of A^-1
    o = mu + sc * oc
    D = D * sc
    # Scale: the corrected readings D^-1 (y - o) lie on the unit sphere; rescale D so that they
    # keep the mean norm of the raw readings about the centre.
    D = D / float(np.mean(np.linalg.norm(y - o, axis=1)))
    return o, D


@dataclass(frozen=True)
class EllipsoidEstimator:
    """Two-step baseline: ellipsoid (o, D) from the magnetometer alone, then Wahba for R."""

    name: str = "ellipsoid"

    def fit(self, p: EstimationProblem) -> Calibration:
        """Estimate; raises :class:`NotObservableError` on single-axis data."""
        o, D = fit_ellipsoid(p.mag_nT)
        B_ref = p.reference_field_enu_nT
        if B_ref is not None:
            # With a known |B| the scale of D is observable: corrected norm = |B_ref|.
            m0 = np.linalg.solve(D, (p.mag_nT - o).T).T
            D = D * float(np.mean(np.linalg.norm(m0, axis=1))) / float(np.linalg.norm(B_ref))
        m = cast(F64, np.linalg.solve(D, (p.mag_nT - o).T).T)
        C = p.C_enu_body
        R, B = init_rotation(m, C, B_ref, iterations=30)
        # Rotation-only information of the Wahba step (isotropic noise, scaled by residuals).
        b = np.einsum("nji,j->ni", C, B)

        J = R.T @ skew(b)  # d(R.T b)/dphi for m = R.T b
        blocks = {"rot": slice(0, 3)}
        Jf = J
        if B_ref is None:
            Jf = np.concatenate([J, R.T @ np.swapaxes(C, 1, 2)], axis=2)
            blocks["B"] = slice(3, 6)
        H = np.einsum("nip,niq->pq", Jf, Jf)
        r = m - b @ R
        s2 = float(np.sum(r**2)) / max(3 * p.n - Jf.shape[2], 1)
        an = analyse(H, blocks)
        nul = an.block_null.get("rot", np.zeros((3, 0)))
        sig = sigma_with_null(an.cov[:3, :3] * s2, nul)
        axes = [canonical_axis(v) for v in nul.T]
        warnings = [
            "two-step baseline: D normalised to the mean field norm; sigmas ignore the "
            "uncertainty of the ellipsoid step"
        ]
        if axes:
            warnings.append(rotation_words(axes, B_ref is not None))
        yhat = (b @ R) @ D.T + o
        return Calibration(
            R_body_mag=R,
            sigma_rotvec_deg=np.degrees(sig),
            B_enu_nT=B,
            estimator=self.name,
            residual_rms_nT=float(np.sqrt(np.mean((p.mag_nT - yhat) ** 2))),
            n_samples=p.n,
            unobservable_axes_body=tuple(axes),
            D=D,
            offset_nT=o,
            R_nominal_body_mag=p.R_nominal_body_mag,
            warnings=tuple(warnings),
        )

"""Dot-product invariance (DPI) baseline.

More in docs/modules.md, ``stages.estimators.dpi``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.geometry import so3_exp
from pipeline.model.calibration import Calibration
from stages.estimators.base import (
    EstimationProblem,
    analyse,
    canonical_axis,
    init_rotation,
    sigma_with_null,
    solve_truncated,
)


@dataclass(frozen=True)
class DpiEstimator:
    """Dot-product invariance with the vertical (docs/modules.md)."""

    name: str = "dpi"
    max_iter: int = 50

    def fit(self, p: EstimationProblem) -> Calibration:
        """Estimate ``R_body_mag`` from the invariance of the field's vertical component."""
        m = p.mag_nT
        C = p.C_enu_body
        u = C[:, 2, :]  # row 2 of C_enu_body = C.T e_up: up in the body frame
        ref = p.reference_field_enu_nT
        # Start: the Wahba multi-start shared with the other estimators (DPI alone has mirror
        # solutions far from the truth); the result is then DPI's own optimum.
        R, B = init_rotation(m, C, ref)
        fix_c = ref is not None
        c = float(ref[2]) if ref is not None else float(B[2])  # fix_c

        def residual(R: np.ndarray, c: float) -> np.ndarray:
            return np.sum((m @ R.T) * u, 1) - c

        r = residual(R, c)
        cost = float(r @ r)
        for _ in range(self.max_iter):
            Jr = np.cross(m @ R.T, u)  # d r / d phi
            J = Jr if fix_c else np.concatenate([Jr, -np.ones((len(r), 1))], 1)
            H = J.T @ J
            delta = solve_truncated(H, -J.T @ r)
            lam = 1.0
            for _ in range(20):
                R_new = so3_exp(lam * delta[:3]) @ R
                c_new = c if fix_c else c + lam * float(delta[3])
                r_new = residual(R_new, c_new)
                cost_new = float(r_new @ r_new)
                if cost_new <= cost * (1 + 1e-12):
                    break
                lam *= 0.5
            else:
                break
            done = np.max(np.abs(lam * delta[:3])) < 1e-13 or (cost - cost_new) <= 1e-15 * cost
            R, c, r, cost = R_new, c_new, r_new, cost_new
            if done:
                break
        Jr = np.cross(m @ R.T, u)
        J = Jr if fix_c else np.concatenate([Jr, -np.ones((len(r), 1))], 1)
        blocks = {"rot": slice(0, 3)} if fix_c else {"rot": slice(0, 3), "c": slice(3, 4)}
        an = analyse(J.T @ J, blocks)
        s2 = cost / max(len(r) - J.shape[1], 1)
        nul = an.block_null.get("rot", np.zeros((3, 0)))
        sig = sigma_with_null(an.cov[:3, :3] * s2, nul)
        axes = [canonical_axis(v) for v in nul.T]
        warnings = []
        if axes:
            ax = "; ".join("[" + ", ".join(f"{x:+.3f}" for x in a) + "]" for a in axes)
            warnings.append(
                f"dot-product invariance cannot see the rotation about body axis {ax} (kept at "
                "its initial value, sigma infinite): it only sees the field's vertical "
                "component; tilt the platform (pitch and roll) or use the ml estimator"
            )
        if p.terms:
            warnings.append(
                "dpi estimates the rotation only; requested terms "
                + ", ".join(sorted(t.value for t in p.terms))
                + " were not estimated"
            )
        # The field: the mean restored vector (its vertical part is the DPI constant).
        B_out = np.einsum("nij,nj->ni", C, m @ R.T).mean(0) if ref is None else ref
        b_body = np.einsum("nji,j->ni", C, B_out)
        return Calibration(
            R_body_mag=R,
            sigma_rotvec_deg=np.degrees(sig),
            B_enu_nT=B_out,
            estimator=self.name,
            residual_rms_nT=float(np.sqrt(np.mean((m - b_body @ R) ** 2))),
            n_samples=p.n,
            unobservable_axes_body=tuple(axes),
            R_nominal_body_mag=p.R_nominal_body_mag,
            warnings=tuple(warnings),
        )

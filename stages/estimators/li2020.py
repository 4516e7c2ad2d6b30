"""Li et al. 2020, Section 3: misalignment from the measured and a virtual trajectory.

S. Li, D. Cheng, Q. Gao et al., "An Improved Calibration Method for the Misalignment Error of
a Triaxial Magnetometer and Inertial Navigation System in a Three-Component Magnetic Survey
System", Applied Sciences 10(19) 6707, 2020.

The steps, with the paper's equations:

1. Virtual auxiliary vector (Eqs. 4-9). An ENU vector ``V`` is carried into the body frame by
   the INS attitude ``E = Ey(roll) Ex(pitch) Ez(heading)`` (Eq. 7, ``E = C_body_enu``):
   ``v_i = E_i V``. The points ``v_i`` form the virtual trajectory; the magnetometer readings
   ``m_i`` form the measured trajectory. With the right ``R`` (Eq. 1: ``v_body = R v_mag``)
   and ``V = B``, ``R m_i = v_i``.
2. Normal and tangent vectors of both trajectories (Eqs. 10-13): tangent
   ``t_i = unit(x_{i+k} - x_{i-k})`` and normal of the local trajectory plane
   ``n_i = unit((x_i - x_{i-k}) x (x_{i+k} - x_i))``.
3. Angle and rotation between the measured and the virtual normals and tangents
   (Eqs. 14-16): here as one least-squares rotation (Wahba / SVD) over all normal and tangent
   pairs, the rotation that brings the measured trajectory's frame onto the virtual one. It is
   the starting value ``R0``.
4. Objective (Eq. 24): the sum over samples of ``|R n^m_i - n^v_i|^2 + |R t^m_i - t^v_i|^2 +
   |R m_i - E_i V|^2 / |V|^2``, minimised over ``R`` and (without a known field) ``V`` by
   nonlinear least squares (``scipy.optimize.least_squares``), with ``R`` written through the
   Cayley transform ``R = (I - S)^-1 (I + S)`` of an antisymmetric ``S`` (Eq. 3).

Choices where the paper text was not available or is ambiguous (ours, not the paper's):

- The virtual vector ``V`` is the reference field when one is given, otherwise it is
  estimated together with ``R`` (started from the mean restored field). Under a single-axis
  rotation without a reference, the rotation about that axis is then not determined; it is
  reported as unobservable rather than fixed by an arbitrary ``V``.
- The Cayley transform cannot represent rotations of 180 deg (axis permutations such as
  ``[[-1,0,0],[0,0,1],[0,1,0]]``), so the unknown is the correction ``R = cay(S) @ R0`` on
  top of the closed-form start of step 3, itself started from a Wahba multi-start.
- Finite differences use a stride ``k`` chosen so that the median angle between ``x_i`` and
  ``x_{i+k}`` is at least 2 deg: adjacent samples of a 0.1 nT-noise sensor at 50 Hz differ
  by too little for a usable tangent.
- The three groups of residuals are unweighted (dimensionless); the reported sigmas are the
  Gauss-Newton covariance scaled by the residual variance (the paper gives none).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from pipeline.calibration import Calibration
from pipeline.geometry import so3_exp

from .base import (
    F64,
    Problem,
    analyse,
    canonical_axis,
    init_rotation,
    rotation_words,
    sigma_with_null,
    wahba,
)

MIN_STEP_DEG = 2.0


def cayley(s: F64) -> F64:
    """``R = (I - S)^-1 (I + S)`` with ``S = [s]x`` (Li 2020, Eq. 3)."""
    S = np.array([[0.0, -s[2], s[1]], [s[2], 0.0, -s[0]], [-s[1], s[0], 0.0]])
    eye = np.eye(3)
    return np.linalg.solve(eye - S, eye + S)


def _unit(x: F64) -> F64:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.where(n > 0, n, 1.0)


def stride_for(x: F64, min_step_deg: float = MIN_STEP_DEG) -> int:
    """Smallest stride ``k`` whose median angular step of the trajectory is >= min_step_deg."""
    u = _unit(x)
    n = len(u)
    k = 1
    while k < n // 4:
        c = np.clip(np.sum(u[k:] * u[:-k], 1), -1.0, 1.0)
        if np.degrees(np.median(np.arccos(c))) >= min_step_deg:
            break
        k *= 2
    return k


def normals_tangents(x: F64, k: int) -> tuple[F64, F64, F64]:
    """Tangents and normals of a trajectory (Li 2020, Eqs. 10-13) at its inner points.

    Returns
    -------
    t, n : ndarray (M, 3)
        Unit tangents and unit normals at points ``k .. N-k-1``.
    ok : ndarray (M,) bool
        Where the three points are not collinear (the normal is defined).

    """
    a = x[k:-k] - x[: -2 * k]
    b = x[2 * k :] - x[k:-k]
    t = _unit(x[2 * k :] - x[: -2 * k])
    cr = np.cross(a, b)
    ok = np.linalg.norm(cr, axis=1) > 1e-9 * np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    return t, _unit(cr), ok


@dataclass(frozen=True)
class Li2020Estimator:
    """The method of Li et al. 2020, Section 3 (see the module docstring for our choices)."""

    name: str = "li2020"

    def fit(self, p: Problem) -> Calibration:
        """Estimate ``R_body_mag`` (and the virtual vector ``V`` when no field is given)."""
        m = p.mag_nT
        C = p.C_enu_body
        E = np.swapaxes(C, 1, 2)  # Li 2020, Eq. 7: E = C_body_enu
        ref = p.reference_field_enu_nT
        R_w, V0 = init_rotation(m, C, ref)
        k = stride_for(m)
        tm, nm, ok_m = normals_tangents(m, k)
        scaleV = float(np.linalg.norm(V0))

        def virtual(V: F64) -> tuple[F64, F64, F64, F64]:
            v = np.einsum("nij,j->ni", E, V)  # Li 2020, Eqs. 8-9
            tv, nv, ok_v = normals_tangents(v, k)
            return v, tv, nv, ok_v

        # Li 2020, Eqs. 14-16: the rotation bringing the measured normals and tangents onto the
        # virtual ones (least squares over all pairs).
        _, tv0, nv0, okv0 = virtual(V0)
        ok0 = ok_m & okv0
        R0 = wahba(np.concatenate([tm, nm[ok0]]), np.concatenate([tv0, nv0[ok0]]))
        if _cost_simple(R0, m, E, V0) > _cost_simple(R_w, m, E, V0):
            R0 = R_w  # the closed form is only a start; keep the better of the two
        fixV = ref is not None

        def resid(x: F64) -> F64:
            R = cayley(x[:3]) @ R0
            V = V0 if fixV else x[3:6] * scaleV
            v, tv, nv, ok_v = virtual(V)
            ok = (ok_m & ok_v).astype(float)[:, None]
            r_n = (nm @ R.T - nv) * ok  # Li 2020, Eq. 24, normal term
            r_t = tm @ R.T - tv  # Li 2020, Eq. 24, tangent term
            r_v = (m @ R.T - v) / scaleV  # Li 2020, Eq. 24, vector term
            return np.concatenate([r_n.ravel(), r_t.ravel(), r_v.ravel()])

        x0 = np.zeros(3) if fixV else np.concatenate([np.zeros(3), V0 / scaleV])
        sol = least_squares(
            resid, x0, method="trf", x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=200
        )
        R = cayley(sol.x[:3]) @ R0
        V = V0 if fixV else sol.x[3:6] * scaleV
        # Covariance about the solution: Jacobian w.r.t. a body-frame rotation phi (left
        # perturbation) and V, by central differences.
        x_hat = sol.x.copy()

        def resid_phi(z: F64) -> F64:
            Rz = so3_exp(z[:3]) @ R
            xs = x_hat.copy()
            Sm = Rz @ R0.T
            # back to Cayley parameters: S = (R - I)(R + I)^-1 (valid away from 180 deg)
            Sk = (Sm - np.eye(3)) @ np.linalg.inv(Sm + np.eye(3))
            xs[:3] = [Sk[2, 1], Sk[0, 2], Sk[1, 0]]
            if not fixV:
                xs[3:6] = z[3:6]
            return resid(xs)

        z0 = np.concatenate([np.zeros(3), x_hat[3:6]]) if not fixV else np.zeros(3)
        J = _numjac(resid_phi, z0)
        r = sol.fun
        H = J.T @ J
        blocks = {"rot": slice(0, 3)}
        if not fixV:
            blocks["V"] = slice(3, 6)
        an = analyse(H, blocks)
        s2 = float(r @ r) / max(len(r) - len(z0), 1)
        nul = an.block_null.get("rot", np.zeros((3, 0)))
        sig = sigma_with_null(an.cov[:3, :3] * s2, nul)
        axes = [canonical_axis(v) for v in nul.T]
        warnings = []
        if axes:
            warnings.append(rotation_words(axes, fixV))
        if p.terms:
            warnings.append(
                "li2020 estimates the rotation only; requested terms "
                + ", ".join(sorted(t.value for t in p.terms))
                + " were not estimated"
            )
        yhat = np.einsum("nij,j->ni", E, V) @ R
        return Calibration(
            R_body_mag=R,
            sigma_rotvec_deg=np.degrees(sig),
            B_enu_nT=V,
            estimator=self.name,
            residual_rms_nT=float(np.sqrt(np.mean((m - yhat) ** 2))),
            n_samples=p.n,
            unobservable_axes_body=tuple(axes),
            R_nominal_body_mag=p.R_nominal_body_mag,
            warnings=tuple(warnings),
        )


def _cost_simple(R: F64, m: F64, E: F64, V: F64) -> float:
    return float(np.sum((m @ R.T - np.einsum("nij,j->ni", E, V)) ** 2))


def _numjac(f, x0: F64, h: float = 1e-7) -> F64:
    cols = []
    for i in range(len(x0)):
        e = np.zeros_like(x0)
        e[i] = h
        cols.append((f(x0 + e) - f(x0 - e)) / (2 * h))
    return np.stack(cols, 1)

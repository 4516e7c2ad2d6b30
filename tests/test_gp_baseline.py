"""The reduced-rank GP baseline of bench/gp_baseline.py: its basis, prior and fit.

A wrong basis (a sign, a factor in the eigenvalues, the spectral density or the
eigenfunctions' normalisation) fails one of these: the field must be minus the gradient of
the potential and curl-free; the basis with its prior must reproduce the squared-exponential
kernel away from the box's faces; and fitted to noise-free samples of one dipole it must
predict held-out points within 0.5 nT.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import gp_baseline as gp  # noqa: E402


def _box(n_basis: int = 300) -> gp.LaplaceBox:
    corners = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    return gp.LaplaceBox.around(corners, 0.0, n_basis)


def test_field_is_minus_the_gradient_of_the_potential_and_curl_free():
    box = _box()
    rng = np.random.default_rng(1)
    x = rng.uniform(-0.7, 0.7, (20, 3))
    w = rng.normal(size=box.n_basis)
    h = 1e-5
    grad = np.stack([(box.potential(x + h * e) - box.potential(x - h * e)) / (2 * h) @ w
                     for e in np.eye(3)], axis=1)
    B = box.field(x) @ w
    np.testing.assert_allclose(B, -grad, rtol=0, atol=1e-6 * np.abs(B).max())
    # curl of B by central differences of the analytic field: zero to the step's accuracy
    J = np.stack([(box.field(x + h * e) @ w - box.field(x - h * e) @ w) / (2 * h)
                  for e in np.eye(3)], axis=2)  # J[n, i, j] = dB_i / dx_j
    curl = np.stack([J[:, 2, 1] - J[:, 1, 2], J[:, 0, 2] - J[:, 2, 0],
                     J[:, 1, 0] - J[:, 0, 1]], axis=1)
    assert np.abs(curl).max() < 1e-6 * np.abs(J).max()
    # the eigenfunctions vanish on the faces (Dirichlet)
    face = x.copy()
    face[:, 0] = box.centre_m[0] + box.half_m[0]
    assert np.abs(box.potential(face)).max() < 1e-12


def test_basis_and_prior_reproduce_the_se_kernel_inside_the_box():
    """sum_j S(sqrt(lambda_j)) phi_j(x) phi_j(x') -> sigma_f^2 exp(-r^2 / (2 l^2))."""
    box = _box(1500)
    # l = 0.2 m: the modes up to k l = 4.5 are in the basis, and the faces (mirror images of
    # the kernel) are 3.75 l or more from the points
    sf, ell = 2.0, 0.2
    rng = np.random.default_rng(2)
    x = rng.uniform(-0.25, 0.25, (15, 3))
    P = box.potential(x)
    K_approx = (P * box.spectral_density(sf, ell)) @ P.T
    r2 = np.sum((x[:, None, :] - x[None, :, :]) ** 2, axis=-1)
    K_true = sf**2 * np.exp(-0.5 * r2 / ell**2)
    np.testing.assert_allclose(K_approx, K_true, rtol=0, atol=1e-4 * sf**2)


def test_fit_to_one_dipole_predicts_held_out_points_within_half_a_nT():
    rng = np.random.default_rng(3)
    m = np.array([0.3, -0.5, 0.8])  # A m^2, 0.6-1 m below the sampled volume

    def dipole(x: np.ndarray) -> np.ndarray:
        r = x - np.array([0.1, -0.2, -0.9])
        n = np.linalg.norm(r, axis=1, keepdims=True)
        return 100.0 * (3.0 * (r @ m)[:, None] * r / n**5 - m / n**3)

    B0 = np.array([1000.0, 20000.0, -45000.0])
    x = rng.uniform([-0.5, -0.5, -0.15], [0.5, 0.5, 0.15], (3000, 3))
    fitted = gp.fit(x, B0 + dipole(x), n_basis=500, margin_m=0.4)
    xt = rng.uniform([-0.4, -0.4, -0.1], [0.4, 0.4, 0.1], (300, 3))
    err = fitted.predict(xt) - (B0 + dipole(xt))
    spread = np.sqrt(np.mean((dipole(xt) - dipole(xt).mean(axis=0)) ** 2))
    assert spread > 20.0  # a field worth mapping: tens of nT across the volume
    assert np.sqrt(np.mean(err**2)) < 0.5, np.sqrt(np.mean(err**2))
    # B0 and the basis' lowest modes, nearly uniform over the sampled volume, trade: about
    # 100 nT however the likelihood is maximised (82-118 nT from five starting points)
    assert np.abs(fitted.B0_nT - B0).max() < 150.0

"""A reduced-rank Gaussian-process map of the magnetic field: the baseline of issue 38.

The model of Solin, Kok, Wahlstroem, Schoen and Saerkkae, "Modeling and interpolation of the
ambient magnetic field by Gaussian processes", IEEE Transactions on Robotics 34(4), 2018
(below "Solin 2018"), written here from the paper with numpy and scipy only; nothing of
magalign's own field map (``pipeline.model.field_map``) is used, so that the baseline cannot
share a mistake with what it is compared against.

The field is curl-free where no current flows, so it is minus the gradient of a scalar
potential: ``B(x) = B0 - grad phi(x)`` (Solin 2018, Sect. III). The potential gets a
Gaussian-process prior with the squared-exponential kernel ``k(x, x') = sigma_f^2
exp(-|x - x'|^2 / (2 l^2))``; the constant ``B0`` (Solin 2018's linear kernel on the
potential, ``phi_lin = -B0 . x``) gets a broad Gaussian prior. The GP is approximated in
the Hilbert-space basis of Solin and Saerkkae (Statistics and Computing 30, 2020) that Solin
2018 uses (Sect. IV): the eigenfunctions of the Laplacian in a box ``[-L_1, L_1] x [-L_2,
L_2] x [-L_3, L_3]`` (about its centre) with Dirichlet boundary,

    phi_j(x) = prod_d L_d^(-1/2) sin(pi n_jd (x_d + L_d) / (2 L_d)),
    lambda_j = sum_d (pi n_jd / (2 L_d))^2,

and the weights' prior variances are the kernel's spectral density at ``sqrt(lambda_j)``,

    S(w) = sigma_f^2 (2 pi l^2)^(3/2) exp(-w^2 l^2 / 2)        (three dimensions).

The measurement model is linear in the weights: ``y = Phi w + e``, ``Phi`` holding ``-grad
phi_j`` at the samples (and the identity for ``B0``), ``e`` white with variance
``sigma_n^2``. Everything is written with ``K x K`` matrices (``K`` basis functions), never
``N x N``: the normal matrix ``Phi^T Phi`` and ``Phi^T y`` are summed once over the samples
(they do not depend on the hyperparameters), after which each evaluation of the marginal
likelihood costs one ``K x K`` Cholesky factorisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve
from scipy.optimize import minimize

F64 = NDArray[np.float64]

#: Prior standard deviation of each component of the constant field ``B0``, nT: broad against
#: any field on Earth, so that the data alone fix it (Solin 2018's linear kernel with a large
#: magnitude).
B0_PRIOR_NT = 1e5

#: Samples per block when the normal matrix is summed: bounds the memory to a block's
#: ``3 n x K`` design.
_BLOCK = 2000


@dataclass(frozen=True)
class LaplaceBox:
    """The Dirichlet-Laplacian eigenbasis of a box: the reduced-rank GP's basis.

    Attributes
    ----------
    centre_m : ndarray (3,)
        Centre of the box, m.
    half_m : ndarray (3,)
        Half widths ``L_d`` of the box, m.
    modes : ndarray (K, 3) of int
        ``n_jd >= 1`` of every basis function, in ascending eigenvalue.

    """

    centre_m: F64
    half_m: F64
    modes: NDArray[np.int64]

    @classmethod
    def around(cls, points_m: F64, margin_m: float, n_basis: int) -> LaplaceBox:
        """Return the box ``margin_m`` beyond the points' bounding box, ``n_basis`` functions.

        The functions are those of the ``n_basis`` lowest eigenvalues: the reduced-rank
        approximation keeps the frequencies where the SE spectral density is largest, and
        the same cut-off wavenumber holds in every direction.
        """
        p = np.asarray(points_m, dtype=float)
        lo, hi = p.min(axis=0) - margin_m, p.max(axis=0) + margin_m
        centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        # enough candidates per axis that the n_basis lowest are among them: a sphere of
        # radius r in mode space holds about pi r^3 / 6 prod(L_d / L_max) of the grid
        scale = half / half.max()
        r = (6.0 * n_basis / (np.pi * np.prod(scale))) ** (1.0 / 3.0)
        n_ax = np.maximum(np.ceil(1.3 * r * scale).astype(int) + 1, 2)
        g = np.stack(np.meshgrid(*(np.arange(1, n + 1) for n in n_ax), indexing="ij"), -1)
        g = g.reshape(-1, 3)
        lam = np.sum((np.pi * g / (2.0 * half)) ** 2, axis=1)
        keep = np.argsort(lam, kind="stable")[:n_basis]
        return cls(centre, half, g[keep].astype(np.int64))

    @property
    def n_basis(self) -> int:
        """``K``."""
        return int(self.modes.shape[0])

    @property
    def wavenumbers(self) -> F64:
        """``pi n_jd / (2 L_d)``, rad/m, (K, 3)."""
        return np.pi * self.modes / (2.0 * self.half_m[None, :])

    @property
    def eigenvalues(self) -> F64:
        """``lambda_j = sum_d (pi n_jd / (2 L_d))^2``, rad^2/m^2, (K,) (Solin 2018, Sect. IV:
        the Dirichlet eigenvalues of the box)."""
        return np.sum(self.wavenumbers**2, axis=1)

    def _args(self, x_m: F64) -> F64:
        # pi n (x + L) / (2 L) with x about the box's centre: (N, 3, K)
        u = np.asarray(x_m, dtype=float).reshape(-1, 3) - self.centre_m + self.half_m
        return u[:, :, None] * self.wavenumbers.T[None, :, :]

    def potential(self, x_m: F64) -> F64:
        """``phi_j(x) = prod_d L_d^(-1/2) sin(pi n_jd (x_d + L_d) / (2 L_d))``, (N, K).

        The orthonormal eigenfunctions of Solin 2018, Sect. IV (unit L2 norm over the box).
        """
        return np.prod(np.sin(self._args(x_m)), axis=1) / np.sqrt(np.prod(self.half_m))

    def field(self, x_m: F64) -> F64:
        """``-grad phi_j(x)``, (N, 3, K), 1/m^(5/2): the field of a unit weight."""
        a = self._args(x_m)
        s, c = np.sin(a), np.cos(a)
        k = self.wavenumbers.T  # (3, K)
        out = np.empty_like(a)
        for d in range(3):
            e, f = [i for i in range(3) if i != d]
            # d/dx_d of the product: only the d-th factor is differentiated
            out[:, d, :] = -k[d][None, :] * c[:, d, :] * s[:, e, :] * s[:, f, :]
        return out / np.sqrt(np.prod(self.half_m))

    def spectral_density(self, sigma_f: float, ell_m: float) -> F64:
        """``S(sqrt(lambda_j))`` of the 3-D SE kernel, (nT m)^2 m^3, (K,): the weights' prior
        variances (Solin 2018, Sect. IV: the SE spectral density ``sigma_f^2 (2 pi l^2)^(3/2)
        exp(-w^2 l^2 / 2)`` in three dimensions)."""
        return sigma_f**2 * (2.0 * np.pi * ell_m**2) ** 1.5 * np.exp(
            -0.5 * self.eigenvalues * ell_m**2)


@dataclass(frozen=True)
class Normal:
    """The sufficient statistics of a training set: ``Phi^T Phi``, ``Phi^T y``, ``y^T y``, n.

    The first three columns of ``Phi`` belong to ``B0`` (the identity), the rest to the
    basis functions. ``n`` counts scalar observations (three per sample).
    """

    PtP: F64
    Pty: F64
    yty: float
    n: int


def design(box: LaplaceBox, x_m: F64) -> F64:
    """``Phi`` of the samples at ``x_m`` (N, 3): (3 N, 3 + K), rows x, y, z per sample."""
    g = box.field(x_m)  # (N, 3, K)
    n = g.shape[0]
    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    return np.concatenate([eye, g], axis=2).reshape(3 * n, 3 + box.n_basis)


def normal_equations(box: LaplaceBox, x_m: F64, y_nT: F64) -> Normal:
    """Sum ``Phi^T Phi``, ``Phi^T y``, ``y^T y`` over the samples in blocks (``K x K`` memory).

    Parameters
    ----------
    x_m : ndarray (N, 3)
        Sensor positions, m, in the frame of ``y_nT``'s components.
    y_nT : ndarray (N, 3)
        Field at the sensor, nT.

    """
    x = np.asarray(x_m, dtype=float)
    y = np.asarray(y_nT, dtype=float)
    m = 3 + box.n_basis
    PtP, Pty = np.zeros((m, m)), np.zeros(m)
    for a in range(0, len(x), _BLOCK):
        P = design(box, x[a:a + _BLOCK])
        yy = y[a:a + _BLOCK].reshape(-1)
        PtP += P.T @ P
        Pty += P.T @ yy
    return Normal(PtP, Pty, float(np.sum(y * y)), 3 * len(x))


def _prior_variance(box: LaplaceBox, sigma_f: float, ell_m: float) -> F64:
    return np.r_[np.full(3, B0_PRIOR_NT**2), box.spectral_density(sigma_f, ell_m)]


def log_marginal_likelihood(box: LaplaceBox, ne: Normal, sigma_f: float, ell_m: float,
                            sigma_n: float) -> float:
    """``log p(y | sigma_f, l, sigma_n)`` of the reduced-rank model with K x K matrices.

    With ``Lambda`` the weights' prior variances and ``Z = sigma_n^2 Lambda^-1 + Phi^T Phi``
    (the Hilbert-space GP's marginal likelihood, Solin and Saerkkae 2020, used by Solin 2018
    to learn the hyperparameters)::

        log p = -(n - m)/2 log sigma_n^2 - 1/2 sum log Lambda_j - 1/2 log det Z
                - 1/(2 sigma_n^2) (y^T y - y^T Phi Z^-1 Phi^T y) - n/2 log 2 pi

    (matrix determinant lemma and Woodbury identity on ``Phi Lambda Phi^T + sigma_n^2 I``).
    """
    lam = _prior_variance(box, sigma_f, ell_m)
    s2 = sigma_n**2
    Z = ne.PtP + np.diag(s2 / lam)
    try:
        cf = cho_factor(Z, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return -np.inf
    quad = ne.yty - ne.Pty @ cho_solve(cf, ne.Pty, check_finite=False)
    m = len(lam)
    logdetZ = 2.0 * float(np.sum(np.log(np.diag(cf[0]))))
    return float(-0.5 * (ne.n - m) * np.log(s2) - 0.5 * np.sum(np.log(lam)) - 0.5 * logdetZ
                 - 0.5 * quad / s2 - 0.5 * ne.n * np.log(2.0 * np.pi))


@dataclass(frozen=True)
class GPMap:
    """A fitted map: its basis, hyperparameters and the weights' posterior mean.

    Attributes
    ----------
    box : LaplaceBox
    sigma_f : float
        Magnitude of the potential's SE kernel, nT m.
    ell_m : float
        Length scale, m.
    sigma_n : float
        Noise standard deviation per component, nT.
    weights : ndarray (3 + K,)
        ``B0`` (nT) then the basis weights (posterior mean).
    log_ml : float
        Log marginal likelihood at the hyperparameters.

    """

    box: LaplaceBox
    sigma_f: float
    ell_m: float
    sigma_n: float
    weights: F64
    log_ml: float

    @property
    def B0_nT(self) -> F64:
        """The constant field ``B0``, nT (3,)."""
        return self.weights[:3]

    def predict(self, x_m: F64) -> F64:
        """Posterior mean of the field at ``x_m`` (N, 3), nT, (N, 3): ``Phi_* w``."""
        x = np.asarray(x_m, dtype=float).reshape(-1, 3)
        out = np.empty_like(x)
        for a in range(0, len(x), _BLOCK):
            out[a:a + _BLOCK] = (design(self.box, x[a:a + _BLOCK]) @ self.weights).reshape(-1, 3)
        return out

    def potential(self, x_m: F64) -> F64:
        """The potential ``phi(x)`` of the map's GP part, nT m, (N,) (``B = B0 - grad phi``)."""
        return self.box.potential(x_m) @ self.weights[3:]


def posterior_weights(box: LaplaceBox, ne: Normal, sigma_f: float, ell_m: float,
                      sigma_n: float) -> F64:
    """Posterior mean ``w = Z^-1 Phi^T y`` with ``Z = sigma_n^2 Lambda^-1 + Phi^T Phi``.

    The reduced-rank predictive mean of Solin 2018, Sect. IV (``E[f_*] = Phi_* Z^-1 Phi^T
    y``).
    """
    lam = _prior_variance(box, sigma_f, ell_m)
    Z = ne.PtP + np.diag(sigma_n**2 / lam)
    return cho_solve(cho_factor(Z, lower=True, check_finite=False), ne.Pty, check_finite=False)


def fit(x_m: F64, y_nT: F64, *, n_basis: int = 1200, margin_m: float = 0.4,
        init: tuple[float, float, float] | None = None,
        ell_bounds_m: tuple[float, float] = (0.05, 5.0),
        sigma_n_bounds: tuple[float, float] = (1e-3, 1e4),
        box: LaplaceBox | None = None) -> GPMap:
    """Fit the map to field samples, the hyperparameters by the marginal likelihood.

    Parameters
    ----------
    x_m : ndarray (N, 3)
        Sensor positions, m.
    y_nT : ndarray (N, 3)
        Field at the sensor in the same axes, nT.
    n_basis : int
        ``K``, basis functions (the lowest eigenvalues of the box).
    margin_m : float
        The box reaches this far beyond the positions: the Dirichlet faces (``phi = 0``)
        must stay a length scale or more from where the map is used.
    init : (sigma_f, ell_m, sigma_n), optional
        Starting hyperparameters; by default a field of the data's spread (``sigma_f = std
        l``), ``l`` a tenth of the box's largest width, ``sigma_n`` a tenth of the spread.
    ell_bounds_m, sigma_n_bounds : (float, float)
        Search bounds of the length scale and the noise.
    box : LaplaceBox, optional
        The basis; by default :meth:`LaplaceBox.around` the positions.

    Returns
    -------
    GPMap
        At the hyperparameters that maximise the log marginal likelihood (L-BFGS-B on their
        logarithms from ``init``).

    """
    x = np.asarray(x_m, dtype=float)
    y = np.asarray(y_nT, dtype=float)
    if box is None:
        box = LaplaceBox.around(x, margin_m, n_basis)
    ne = normal_equations(box, x, y)
    if init is None:
        spread = float(np.sqrt(np.mean((y - y.mean(axis=0)) ** 2)))
        ell0 = 0.2 * float(box.half_m.max())
        init = (max(spread, 1e-3) * ell0, ell0, max(0.1 * spread, 2 * sigma_n_bounds[0]))

    def nll(theta: F64) -> float:
        # a line search may try hyperparameters far out (sigma_f of 1e162, a length scale
        # whose spectral density underflows to zero): the likelihood there is not finite,
        # which the search is told with 1e300, and numpy need not warn on the way
        with np.errstate(over="ignore", under="ignore", divide="ignore", invalid="ignore"):
            sf, ell, sn = np.exp(theta)
            v = log_marginal_likelihood(box, ne, sf, ell, sn)
        return -v if np.isfinite(v) else 1e300

    bounds = [(None, None), tuple(np.log(ell_bounds_m)), tuple(np.log(sigma_n_bounds))]
    th0 = np.log(np.asarray(init, dtype=float))
    th0[1] = np.clip(th0[1], *bounds[1])
    th0[2] = np.clip(th0[2], *bounds[2])
    # three parameters: finite-difference gradients cost three K x K factorisations each
    res = minimize(nll, th0, method="L-BFGS-B", bounds=bounds,
                   options={"maxiter": 200, "eps": 1e-5})
    sf, ell, sn = (float(v) for v in np.exp(res.x))
    w = posterior_weights(box, ne, sf, ell, sn)
    return GPMap(box, sf, ell, sn, w, -float(res.fun))

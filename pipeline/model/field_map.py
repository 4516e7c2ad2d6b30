"""``field_map``: a smooth curl-free field from a scalar potential, in a reduced-rank basis.

More in docs/modules.md, ``pipeline.model.field_map``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.core.geometry import rot_z

F64 = NDArray[np.float64]

#: Name of the basis (the ``basis`` param of CONVENTIONS ``field_map``).
BASIS_NAME = "laplace_dirichlet_box"

#: The box is the positions' bounding box padded on every side by this fraction of the
#: bounding box's largest extent: the Dirichlet faces (``phi = 0``, so no field along them)
#: stay away from where the sensor was, and a flat path (a survey at one height) still gets a
#: box thick enough for the potential to change across it (the vertical field).
MARGIN_FRACTION = 0.25

#: ... and at least this, m (a path of a few centimetres).
MIN_MARGIN_M = 0.05

#: Fewest modes along any axis: with one, a path in the box's middle plane sees no field
#: along that axis (``cos`` of the first mode is zero there); two give both parts.
MIN_MODES_PER_AXIS = 2


def mode_indices(n_axis: tuple[int, ...] | NDArray[np.int64]) -> NDArray[np.int64]:
    """Mode numbers ``(n_1, n_2, n_3)`` of every basis function, (K, 3), ``n_3`` fastest."""
    n1, n2, n3 = (int(x) for x in n_axis)
    g = np.stack(np.meshgrid(np.arange(1, n1 + 1), np.arange(1, n2 + 1), np.arange(1, n3 + 1),
                             indexing="ij"), axis=-1)
    return g.reshape(-1, 3).astype(np.int64)


def domain_for(p_m: F64, margin_fraction: float = MARGIN_FRACTION,
               min_margin_m: float = MIN_MARGIN_M) -> F64:
    """Box around the positions ``p_m`` (N, 3), m: their bounding box padded, (3, 2) ``[a, b]``.

    Every side is padded by ``max(margin_fraction * E, min_margin_m)`` with ``E`` the largest
    extent of the bounding box (NaN rows ignored).
    """
    p = np.asarray(p_m, dtype=float)
    p = p[np.isfinite(p).all(axis=1)]
    lo, hi = p.min(axis=0), p.max(axis=0)
    m = max(margin_fraction * float(np.max(hi - lo)), min_margin_m)
    return np.stack([lo - m, hi + m], axis=1)


#: An axis along which the positions spread less than this fraction of their largest extent
#: is flat: the path samples the field on a plane (or a line) there, and the two modes of
#: :data:`MIN_MODES_PER_AXIS` carry all it can see of that axis (the potential and its
#: derivative across the plane).
FLAT_FRACTION = 0.1


def axis_counts(domain_m: F64, n: int, extent_m: F64 | None = None) -> tuple[int, int, int]:
    """Modes per axis for complexity ``n``: ``n`` along the box's longest axis, fewer across.

    ``N_d = clip(ceil(n W_d / W_max), MIN_MODES_PER_AXIS, n)`` with ``W_d`` the box's widths:
    the same wavelength along every axis, so the basis resolves the field alike in every
    direction. With the positions' extent per axis ``extent_m`` (3,), m, a flat axis (extent
    below :data:`FLAT_FRACTION` of the largest, e.g. a survey at one height) gets
    :data:`MIN_MODES_PER_AXIS`.
    """
    d = np.asarray(domain_m, dtype=float)
    w = d[:, 1] - d[:, 0]
    c = np.clip(np.ceil(n * w / float(np.max(w)) - 1e-9), MIN_MODES_PER_AXIS, max(n, 2))
    if extent_m is not None:
        e = np.asarray(extent_m, dtype=float)
        c[e < FLAT_FRACTION * max(float(np.max(e)), 1e-12)] = MIN_MODES_PER_AXIS
    return (int(c[0]), int(c[1]), int(c[2]))


def length_scale_for(domain_m: F64, n: int) -> float:
    """GP length scale ``l`` (m) that goes with complexity ``n``: ``W_max / (2 n)``.

    The highest mode along the longest axis then has ``k l = pi / 2``: the prior damps it
    by ``exp(-(k l)^2 / 2) = 0.29`` in variance and the next, left out, by more than half as
    much again; the basis and the prior describe the same smoothness.
    """
    w = np.diff(np.asarray(domain_m, dtype=float), axis=1)[:, 0]
    return float(np.max(w)) / (2.0 * n)


@dataclass(frozen=True)
class FieldMapBasis:
    """The basis of one ``field_map`` (docs/modules.md): a box and the modes per axis.

    Attributes
    ----------
    domain_m : ndarray (3, 2)
        ``[a_d, b_d]`` per position-frame axis, m.
    n_axis : tuple of 3 int
        ``N_d``: modes ``n_d = 1 .. N_d`` along each axis; ``K = N_1 N_2 N_3`` functions.

    """

    domain_m: F64
    n_axis: tuple[int, int, int]

    @classmethod
    def of(cls, domain_m: Any, n_axis: Any) -> FieldMapBasis:
        """Return the basis from lists (JSON) or arrays."""
        d = np.asarray(domain_m, dtype=float).reshape(3, 2)
        n = tuple(int(x) for x in np.asarray(n_axis).reshape(3))
        return cls(d, (n[0], n[1], n[2]))

    @property
    def n_basis(self) -> int:
        """``K``, the number of basis functions (weights)."""
        return int(np.prod(self.n_axis))

    @property
    def half_widths_m(self) -> F64:
        """``L_d``, m, (3,)."""
        return 0.5 * (self.domain_m[:, 1] - self.domain_m[:, 0])

    @cached_property
    def modes(self) -> NDArray[np.int64]:
        """``(n_1, n_2, n_3)`` per basis function, (K, 3)."""
        return mode_indices(self.n_axis)

    @cached_property
    def wavenumbers(self) -> F64:
        """``k_jd = pi n_d / (2 L_d)``, rad/m, (K, 3)."""
        return np.pi * self.modes / (2.0 * self.half_widths_m[None, :])

    @cached_property
    def eigenvalues(self) -> F64:
        """``lambda_j = |k_j|^2``, rad^2/m^2, (K,)."""
        return np.sum(self.wavenumbers**2, axis=1)

    def _factors(self, x_m: F64) -> tuple[F64, F64, F64]:
        """``sin``, ``cos`` of ``k_jd (x_d - a_d)`` per sample, axis and mode, (N, 3, K); ``k``.

        Along axis ``d`` the K functions take only ``N_d`` wavenumbers: each sine and cosine
        is computed once per sample and mode number and gathered to the functions (the
        same numbers as from ``wavenumbers``: 3 K transcendental calls per sample become
        ``N_1 + N_2 + N_3``).
        """
        x = np.asarray(x_m, dtype=float)
        u = x - self.domain_m[:, 0][None, :]  # (N, 3)
        n, K = len(u), self.n_basis
        s, c = np.empty((n, 3, K)), np.empty((n, 3, K))
        for d in range(3):
            kd = np.pi * np.arange(1, self.n_axis[d] + 1) / (2.0 * self.half_widths_m[d])
            arg = u[:, d, None] * kd[None, :]  # (N, N_d)
            pick = self.modes[:, d] - 1
            s[:, d, :] = np.sin(arg)[:, pick]
            c[:, d, :] = np.cos(arg)[:, pick]
        return s, c, self.wavenumbers.T

    def potential(self, x_m: F64) -> F64:
        """``psi_j(x)`` (N, K), m, at positions ``x_m`` (N, 3) in the position frame."""
        s, _, _ = self._factors(x_m)
        return np.prod(s, axis=1) / np.sqrt(self.eigenvalues)[None, :]

    def field(self, x_m: F64) -> F64:
        """``g_j(x) = -grad psi_j(x)`` (N, 3, K), unitless (nT per nT of weight), position axes."""
        s, c, k = self._factors(x_m)
        g = np.empty_like(s)
        for d in range(3):
            e, f = [a for a in range(3) if a != d]
            g[:, d, :] = -k[d][None, :] * c[:, d, :] * s[:, e, :] * s[:, f, :]
        return g / np.sqrt(self.eigenvalues)[None, None, :]

    def field_gradient(self, x_m: F64, weights: F64) -> F64:
        """``dB_x/dx = -sum_j w_j hess psi_j(x)`` (N, 3, 3), nT/m: symmetric (curl-free)."""
        s, c, k = self._factors(x_m)
        w = np.asarray(weights, dtype=float) / np.sqrt(self.eigenvalues)
        out = np.empty((s.shape[0], 3, 3))
        for d in range(3):
            for e in range(d, 3):
                if d == e:
                    # d^2/dx_d^2 prod sin = -k_d^2 prod sin
                    h = -(k[d] ** 2)[None, :] * np.prod(s, axis=1)
                else:
                    (f,) = [a for a in range(3) if a not in (d, e)]
                    h = (k[d] * k[e])[None, :] * c[:, d, :] * c[:, e, :] * s[:, f, :]
                out[:, d, e] = out[:, e, d] = -(h @ w)
        return out

    def prior_variance(self, length_scale_m: float, sigma_B_nT: float) -> F64:
        """Prior variance of each weight, nT^2, (K,): ``S(sqrt(lambda_j)) lambda_j / prod L_d``.

        ``S`` is the squared-exponential's spectral density in three dimensions with
        ``sigma_phi = sigma_B l`` (docs/modules.md): each field component then has the prior
        standard deviation ``sigma_B_nT`` where the box is large against ``l``.
        """
        ell = float(length_scale_m)
        lam = self.eigenvalues
        s_phi2 = (sigma_B_nT * ell) ** 2
        S = s_phi2 * (2.0 * np.pi * ell * ell) ** 1.5 * np.exp(-0.5 * lam * ell * ell)
        return S * lam / float(np.prod(self.half_widths_m))


def weighted_field(g: F64, weights: F64) -> F64:
    """Return ``sum_j w_j g_j`` (N, 3) of the basis' fields ``g`` (N, 3, K).

    One matrix-vector product over the functions (einsum loops over the samples).
    """
    g = np.asarray(g, dtype=float)
    return (g.reshape(-1, g.shape[2]) @ np.asarray(weights, dtype=float)).reshape(-1, 3)


def map_field_enu(basis: FieldMapBasis, weights: F64, yaw_rad: float, x_m: F64) -> F64:
    """Return the map's field ``Q B_x(x)`` in ENU, nT, (N, 3), at position-frame points ``x_m``."""
    return weighted_field(basis.field(x_m), weights) @ rot_z(yaw_rad).T


def map_points(p_m: F64, yaw_rad: float, lever_enu_m: F64 | None = None) -> F64:
    """Where the sensor is in the position frame, (N, 3), m: ``x = p + Q.T C l``.

    The lever arm ``C l`` is in ENU (CONVENTIONS ``lever_arm``); the map's box is in the
    position frame, turned to ENU by ``Q = Rz(yaw)``.
    """
    x = np.asarray(p_m, dtype=float)
    if lever_enu_m is None:
        return x
    return x + np.asarray(lever_enu_m, dtype=float) @ rot_z(yaw_rad)

"""The point dipole's field and Jacobian columns, one pass over the samples (compiled).

A survey's diagnosis evaluates each located source on every sample it sees, at every
iteration of every fit: on the 2-hour survey of ``bench/spatial.py`` that was a third of the
diagnosis (docs/performance.md). Written with numpy, each sample's 3 x 3 gradient, field
matrix and their product with ``G`` are arrays of (N, 3, 3) passed through memory several
times; here they stay in registers, and the loop is compiled by numba (which harmonica's
equivalent sources already need). The field is :func:`pipeline.model.forward.dipole_field`'s;
the columns repeat the formulas of :func:`~pipeline.model.forward.dipole_gradient` and
:func:`~pipeline.model.forward.dipole_matrix`, to which ``tests/test_local_source.py`` holds
them.

numba is imported, and the loops compiled (or read from numba's on-disk cache), on first
use, or by :func:`warm` on a helper thread from the start of a diagnosis with positions: a
recording without positions never pays for it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.model import parallel
from pipeline.model.compiled import compiled

F64 = NDArray[np.float64]

#: mu0 / 4 pi in nT m^3 / (A m^2): B = 100 nT (3 (m.u) u - m) / r^3 (CONVENTIONS local_source)
DIPOLE_NT = 100.0

#: Closest distance (m) at which a point dipole is evaluated: a guard against a fit step that
#: puts the source on the path (the field there is not a point dipole's anyway)
MIN_SOURCE_DISTANCE_M = 0.01


def _field_loop(r: F64, m: F64, w: F64, out: F64) -> None:  # pragma: no cover - compiled
    """``out += w B(r)``: ``B = k (3 (m.u) u - m) / d^3`` per sample."""
    for k in range(r.shape[0]):
        x, y, z = r[k, 0], r[k, 1], r[k, 2]
        d = max(np.sqrt(x * x + y * y + z * z), MIN_SOURCE_DISTANCE_M)
        s = w[k] * DIPOLE_NT / (d * d * d)
        mu3 = 3.0 * (x * m[0] + y * m[1] + z * m[2]) / (d * d)
        out[k, 0] += s * (mu3 * x - m[0])
        out[k, 1] += s * (mu3 * y - m[1])
        out[k, 2] += s * (mu3 * z - m[2])


def _columns_loop(r: F64, m: F64, cos_psi: float, sin_psi: float, G: F64, r_p: F64,
                  w: F64, fit_yaw: bool, out: F64) -> None:  # pragma: no cover - compiled
    """``out = w G [-K Rz(psi), P(r), K (e_z x r_p)]`` per sample (LocalSource.columns).

    ``K = dB/dr`` (forward.dipole_gradient: ``a (r m' + m r' + (m.r) I) - c r r'`` with
    ``a = 3 k / d^5``, ``c = 5 a (m.r) / d^2``); ``P = k (3 u u' - I) / d^3``
    (forward.dipole_matrix); ``Rz(psi) = [[c, -s, 0], [s, c, 0], [0, 0, 1]]``.
    """
    n_col = 7 if fit_yaw else 6
    K = np.empty((3, 3))
    dB = np.empty((3, 7))
    rr = np.empty(3)
    for k in range(r.shape[0]):
        rr[0], rr[1], rr[2] = r[k, 0], r[k, 1], r[k, 2]
        d = max(np.sqrt(rr[0] * rr[0] + rr[1] * rr[1] + rr[2] * rr[2]), MIN_SOURCE_DISTANCE_M)
        d2 = d * d
        mr = rr[0] * m[0] + rr[1] * m[1] + rr[2] * m[2]
        a = 3.0 * DIPOLE_NT / (d2 * d2 * d)
        c = 5.0 * a * mr / d2
        s = DIPOLE_NT / (d2 * d)
        for i in range(3):
            for j in range(3):
                K[i, j] = a * (rr[i] * m[j] + m[i] * rr[j]) - c * rr[i] * rr[j]
                dB[i, 3 + j] = 3.0 * s * rr[i] * rr[j] / d2
            K[i, i] += a * mr
            dB[i, 3 + i] -= s
            dB[i, 0] = -(K[i, 0] * cos_psi + K[i, 1] * sin_psi)
            dB[i, 1] = K[i, 0] * sin_psi - K[i, 1] * cos_psi
            dB[i, 2] = -K[i, 2]
            if fit_yaw:
                dB[i, 6] = K[i, 1] * r_p[k, 0] - K[i, 0] * r_p[k, 1]
        for i in range(3):
            for j in range(n_col):
                out[k, i, j] = w[k] * (G[k, i, 0] * dB[0, j] + G[k, i, 1] * dB[1, j]
                                       + G[k, i, 2] * dB[2, j])


def _grid_loop(p: F64, cands: F64, Q: F64, M: F64, H: F64, w: F64, A: F64, W: F64,
               g: F64) -> None:  # pragma: no cover - compiled
    """Per candidate place: ``A = X'X``, ``W = Qn' X``, ``g = X' r_perp`` of its columns.

    ``X = G P(r)`` (3n, 3) with ``r = Q (p - c)``: summed per sample in closed form as
    ``stages/diagnose/sources.py`` derives them, ``M = G'G``, ``H_j = G' Q_j``, ``w = G' r``.
    """
    u = np.empty(3)
    v = np.empty(3)
    for k in range(cands.shape[0]):
        A[k] = 0.0
        W[k] = 0.0
        g[k] = 0.0
        for t in range(p.shape[0]):
            x0, x1, x2 = p[t, 0] - cands[k, 0], p[t, 1] - cands[k, 1], p[t, 2] - cands[k, 2]
            for i in range(3):
                u[i] = Q[i, 0] * x0 + Q[i, 1] * x1 + Q[i, 2] * x2
            d = max(np.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]), MIN_SOURCE_DISTANCE_M)
            s = DIPOLE_NT / (d * d * d)
            for i in range(3):
                u[i] /= d
            for i in range(3):
                v[i] = M[t, i, 0] * u[0] + M[t, i, 1] * u[1] + M[t, i, 2] * u[2]
            s2, uv = s * s, u[0] * v[0] + u[1] * v[1] + u[2] * v[2]
            for i in range(3):
                for j in range(3):
                    A[k, i, j] += s2 * (9.0 * uv * u[i] * u[j] - 3.0 * (u[i] * v[j] + v[i] * u[j])
                                        + M[t, i, j])
            for jq in range(H.shape[1]):
                hu = H[t, jq, 0] * u[0] + H[t, jq, 1] * u[1] + H[t, jq, 2] * u[2]
                for i in range(3):
                    W[k, jq, i] += s * (3.0 * hu * u[i] - H[t, jq, i])
            wu = w[t, 0] * u[0] + w[t, 1] * u[1] + w[t, 2] * u[2]
            for i in range(3):
                g[k, i] += s * (3.0 * wu * u[i] - w[t, i])


def warm() -> None:
    """Load numba and every loop for the argument types the model passes them.

    Loading numba and its cached machine code takes about a second in a new process; a
    diagnosis of a recording with positions starts this on a helper thread
    (:func:`pipeline.core.warm.warm_in_background`) while its first fits run, which have no
    source yet. The Jacobian's columns are a view of a larger array: that layout too.
    """
    r = np.array([[1.0, 0.5, -0.5], [0.2, -1.0, 0.3]])
    m, G = np.ones(3), np.tile(np.eye(3), (2, 1, 1))
    add_dipole_field(r, m, np.zeros((2, 3)))
    J = np.zeros((2, 3, 9))
    dipole_columns(r, m, 0.1, G, None, None, J[:, :, 1:7])
    dipole_columns(r, m, 0.1, G, r, np.ones(2), J[:, :, 1:8])
    dipole_grid_sums(r, r[:1], np.eye(3), G, np.zeros((2, 1, 3)), r)


def _c(a: Any) -> F64:
    return np.ascontiguousarray(a, dtype=float)


def add_dipole_field(r_enu_m: F64, m_Am2: F64, out_nT: F64, weight: F64 | None = None) -> None:
    """Add the field of the dipole ``m_Am2`` (3,) at offsets ``r_enu_m`` (N, 3) to ``out_nT``.

    ``out_nT`` (N, 3), nT, is added to in place; ``weight`` (N,) scales each sample (a
    source's presence), default 1.
    """
    r = _c(r_enu_m)
    w = np.ones(len(r)) if weight is None else _c(weight)
    compiled(_field_loop)(r, _c(m_Am2), w, out_nT)


def dipole_columns(r_enu_m: F64, m_Am2: F64, psi_rad: float, G: F64, r_p_m: F64 | None,
                   weight: F64 | None, out: F64) -> None:
    """Write ``G dB/d(c, m[, psi])`` of a dipole into ``out`` (N, 3, 6 or 7).

    ``r_enu_m`` (N, 3) the offsets from the source to the sensor; ``G`` (N, 3, 3) the
    reading's derivative by the ENU field; ``r_p_m`` (N, 3) the turned offset of the
    positions alone (the bearing's column; None: no bearing column); ``weight`` (N,) the
    source's presence (None: 1). ``out`` may be a view of a larger Jacobian.
    """
    r = _c(r_enu_m)
    w = np.ones(len(r)) if weight is None else _c(weight)
    rp = r if r_p_m is None else _c(r_p_m)
    compiled(_columns_loop)(r, _c(m_Am2), float(np.cos(psi_rad)), float(np.sin(psi_rad)),
                         _c(G), rp, w, r_p_m is not None, out)


def dipole_grid_sums(p_m: F64, cands_m: F64, Q: F64, M: F64, H: F64, w: F64
                     ) -> tuple[F64, F64, F64]:
    """Sum a dipole's columns' products at each candidate place (a source's grid search).

    ``p_m`` (n, 3) positions, ``cands_m`` (K, 3) places, ``Q`` (3, 3) the frame's turn;
    per sample ``M`` (n, 3, 3) ``G'G``, ``H`` (n, q, 3) ``G'`` times the nuisance columns and
    ``w`` (n, 3) ``G'`` times the residual. Returns ``A`` (K, 3, 3), ``W`` (K, q, 3) and
    ``g`` (K, 3), as ``stages/diagnose/sources.py`` uses them.
    """
    K, q = len(cands_m), H.shape[1]
    A, W, g = np.empty((K, 3, 3)), np.empty((K, q, 3)), np.empty((K, 3))
    loop, c = compiled(_grid_loop), _c(cands_m)
    p, Qc, Mc, Hc, wc = _c(p_m), _c(Q), _c(M), _c(H), _c(w)
    # each place's sums are its own: the places in runs side by side (pipeline.model.parallel)
    cuts = np.linspace(0, K, parallel.cores() + 1).astype(int)
    runs = [slice(a, b) for a, b in zip(cuts[:-1], cuts[1:], strict=True) if b > a]
    parallel.ordered(lambda r: loop(p, c[r], Qc, Mc, Hc, wc, A[r], W[r], g[r]), runs)
    return A, W, g

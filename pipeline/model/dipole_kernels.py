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
use: a recording without positions never pays for it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

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


_COMPILED: dict[str, Any] = {}


def _compiled(name: str) -> Any:
    """Return the loop ``name`` compiled (numba, cached on disk) on first use in a process."""
    if not _COMPILED:
        import numba  # pipeline.core.warm.LATE_IMPORTS

        _COMPILED["field"] = numba.njit(cache=True, nogil=True)(_field_loop)
        _COMPILED["columns"] = numba.njit(cache=True, nogil=True)(_columns_loop)
    return _COMPILED[name]


def _c(a: Any) -> F64:
    return np.ascontiguousarray(a, dtype=float)


def add_dipole_field(r_enu_m: F64, m_Am2: F64, out_nT: F64, weight: F64 | None = None) -> None:
    """Add the field of the dipole ``m_Am2`` (3,) at offsets ``r_enu_m`` (N, 3) to ``out_nT``.

    ``out_nT`` (N, 3), nT, C-contiguous, is added to in place; ``weight`` (N,) scales each
    sample (a source's presence), default 1.
    """
    r = _c(r_enu_m)
    w = np.ones(len(r)) if weight is None else _c(weight)
    _compiled("field")(r, _c(m_Am2), w, out_nT)


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
    _compiled("columns")(r, _c(m_Am2), float(np.cos(psi_rad)), float(np.sin(psi_rad)),
                         _c(G), rp, w, r_p_m is not None, out)

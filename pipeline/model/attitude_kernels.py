"""The attitude's C1 cubic at query times, one pass over the queries (compiled).

The diagnosis fits a time offset: at every iteration of every fit the attitude is
interpolated anew at the shifted sensing times, and three times (the reading and the
rate's central difference). Written with numpy, :meth:`AttitudeInterpolator.at_rel_s
<pipeline.model.attitude.AttitudeInterpolator.at_rel_s>` passes its (N, 3) and (N, 4)
intermediates through memory once per operation; here each query stays in registers (the
measured share of the diagnosis: docs/performance.md). The loop repeats (A1)-(A5) and (A7)
of :mod:`pipeline.model.attitude` (``_locate``, ``_rotvec``, ``rotvec_to_quat``,
``quat_mul``) and ``quat_to_matrix``, to which ``tests/test_attitude_kernels.py`` holds it.

numba is loaded only where a recording's diagnosis loads it anyway, for its located sources
(a recording with positions: :mod:`pipeline.model.dipole_kernels`); without positions the
numpy path runs and no process pays for the compiler.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.model.compiled import compiled

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B8 = NDArray[np.bool_]


def _cubic_loop(tr: F64, dt: F64, a: F64, phi: F64, b: F64, qa: F64, tq: F64, max_gap: float,
                clamp: bool, q: F64, Ct: F64, pos: F64, valid: B8, held: B8, seg: I64,
                rv: F64) -> None:  # pragma: no cover - compiled
    """Fill the outputs of :func:`cubic_at` for every query ``tq``."""
    m = tr.shape[0]
    i = -1
    for k in range(tq.shape[0]):
        t = tq[k]
        held[k] = False
        if clamp and (t < tr[0] or t > tr[m - 1]):  # held end sample: no rotation
            held[k] = True
            t = min(max(t, tr[0]), tr[m - 1])
        # i: the largest with tr[i] <= t (-1 if none), searchsorted(side="right") - 1; the
        # queries come in time order, so the last query's segment or the next is tried first
        if not (0 <= i < m - 1 and tr[i] <= t < tr[i + 1]):
            i += 1
            if not (0 <= i < m - 1 and tr[i] <= t < tr[i + 1]):
                i = np.searchsorted(tr, t, side="right") - 1
        if t == tr[m - 1]:
            i = m - 2
        j = min(max(i, 0), m - 2)
        d = dt[j]
        t_lo, t_hi = tr[j], tr[j + 1]
        ok = (0 <= i < m - 1) and (d <= max_gap + 1e-12 or t == t_lo or t == t_hi)
        s = min(max((t - t_lo) / (d if d > 0 else 1.0), 0.0), 1.0)
        seg[k] = j
        valid[k] = ok
        if not ok:
            pos[k] = 0.0
            for c in range(4):
                q[k, c] = np.nan
            for r in range(3):
                rv[k, r] = np.nan
                for c in range(3):
                    Ct[k, r, c] = np.nan
            continue
        pos[k] = s
        s2 = s * s
        s3 = s2 * s
        ca, cp, cb = s3 - 2.0 * s2 + s, 3.0 * s2 - 2.0 * s3, s3 - s2  # (A2)
        x = ca * a[j, 0] + cp * phi[j, 0] + cb * b[j, 0]
        y = ca * a[j, 1] + cp * phi[j, 1] + cb * b[j, 1]
        z = ca * a[j, 2] + cp * phi[j, 2] + cb * b[j, 2]
        rv[k, 0], rv[k, 1], rv[k, 2] = x, y, z
        theta = np.sqrt(x * x + y * y + z * z)  # geometry.rotvec_to_quat
        f = 0.5 if theta < 1e-12 else np.sin(0.5 * theta) / theta
        rx, ry, rz, rw = x * f, y * f, z * f, np.cos(0.5 * theta)
        px, py, pz, pw = qa[j, 0], qa[j, 1], qa[j, 2], qa[j, 3]
        qx = pw * rx + px * rw + py * rz - pz * ry  # (A1): q_j * exp(r), geometry.quat_mul
        qy = pw * ry - px * rz + py * rw + pz * rx
        qz = pw * rz + px * ry - py * rx + pz * rw
        qw = pw * rw - px * rx - py * ry - pz * rz
        nq = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        qx, qy, qz, qw = qx / nq, qy / nq, qz / nq, qw / nq
        q[k, 0], q[k, 1], q[k, 2], q[k, 3] = qx, qy, qz, qw
        # C.T (geometry.quat_to_matrix, transposed): row r of C.T is column r of C
        Ct[k, 0, 0] = 1.0 - 2.0 * (qy * qy + qz * qz)
        Ct[k, 1, 0] = 2.0 * (qx * qy - qz * qw)
        Ct[k, 2, 0] = 2.0 * (qx * qz + qy * qw)
        Ct[k, 0, 1] = 2.0 * (qx * qy + qz * qw)
        Ct[k, 1, 1] = 1.0 - 2.0 * (qx * qx + qz * qz)
        Ct[k, 2, 1] = 2.0 * (qy * qz - qx * qw)
        Ct[k, 0, 2] = 2.0 * (qx * qz - qy * qw)
        Ct[k, 1, 2] = 2.0 * (qy * qz + qx * qw)
        Ct[k, 2, 2] = 1.0 - 2.0 * (qx * qx + qy * qy)


def cubic_at(tr: F64, dt: F64, a: F64, phi: F64, b: F64, qa: F64, tq: F64, max_gap_s: float,
             clamp: bool) -> tuple[F64, F64, F64, B8, B8, I64, F64]:
    """Evaluate the cubic (A1)-(A5) of :mod:`pipeline.model.attitude` at ``tq`` (N,), s.

    ``tr`` (M,) the samples' times, s from the first; ``dt`` (M-1,) their spacing; ``a``,
    ``phi``, ``b`` (M-1, 3) each segment's tangents and increment; ``qa`` (M, 4) the samples.
    Returns ``q`` (N, 4) and ``C.T`` (N, 3, 3) (NaN where not valid), the position in the
    segment (0 where not valid), ``valid``, ``held`` (clamped beyond the span), the segment
    and the rotation vector (A2) of each query.
    """
    n = len(tq)
    q, Ct, pos = np.empty((n, 4)), np.empty((n, 3, 3)), np.empty(n)
    valid, held = np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_)
    seg, rv = np.empty(n, dtype=np.int64), np.empty((n, 3))
    c = np.ascontiguousarray  # one layout, one compiled signature (a half track is a view)
    compiled(_cubic_loop)(c(tr, dtype=float), c(dt, dtype=float), c(a, dtype=float),
                          c(phi, dtype=float), c(b, dtype=float), c(qa, dtype=float),
                          c(tq, dtype=float), float(max_gap_s), bool(clamp), q, Ct, pos, valid,
                          held, seg, rv)
    return q, Ct, pos, valid, held, seg, rv


def warm() -> None:
    """Load numba and the loop for the argument types the interpolator passes it."""
    tr = np.array([0.0, 0.01, 0.02])
    qa = np.tile([0.0, 0.0, 0.0, 1.0], (3, 1))
    z = np.zeros((2, 3))
    cubic_at(tr, np.diff(tr), z, z, z, qa, np.array([0.005, 0.03]), np.inf, True)

"""Rotations: quaternions, SO(3) exponential and logarithm, Euler angles of Li et al. 2020.

Conventions (CONVENTIONS.md):

- Quaternions are Hamilton, stored **scalar-last** ``[x, y, z, w]`` (as ROS and scipy store
  them), arrays of shape ``(..., 4)``. ``q_enu_body`` rotates a body vector into ENU:
  ``v_enu = C_enu_body @ v_body``.
- Rotation matrices act on column vectors; names carry frames, ``C_a_b`` maps ``b`` to ``a``.
- Everything is vectorised over leading axes; nothing here loops over samples in Python.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


def skew(v: ArrayLike) -> F64:
    """Return the cross-product matrix ``[v]x`` so that ``skew(a) @ b == cross(a, b)``.

    Parameters
    ----------
    v : array_like, shape (..., 3)
        The vector(s) of the cross product's left side.

    Returns
    -------
    ndarray, shape (..., 3, 3)

    """
    v = np.asarray(v, dtype=float)
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    # written into place: the diagnosis builds one per sample at every iteration
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -w
    out[..., 0, 2] = y
    out[..., 1, 0] = w
    out[..., 1, 2] = -x
    out[..., 2, 0] = -y
    out[..., 2, 1] = x
    return out


def dot_last(a: F64, b: F64) -> F64:
    """``np.sum(a * b, axis=-1)`` of a short last axis (3 or 4), added in the same order.

    A reduction over so short an axis costs several times the products and sums; the
    diagnosis takes these over every sample and every candidate place of a source.
    """
    s = a[..., 0] * b[..., 0]
    for i in range(1, a.shape[-1]):
        s = s + a[..., i] * b[..., i]
    return cast(F64, s)


def rows_times(M: F64, v: F64) -> F64:
    """Per-sample matrix-vector products ``M_n @ v_n``: (N, 3, 3) x (N, 3) -> (N, 3).

    einsum's loop, a few times faster here than matmul's over a stack of 3 x 3 matrices.
    """
    return cast(F64, np.einsum("nij,nj->ni", M, v))


def each_times_rows(basis: F64, v: F64) -> F64:
    """``out[n, :, k] = basis[k] @ v[n]``: K matrices (K, 3, 3) on every row of ``v`` (N, 3).

    One matrix product (N, 3) x (3, 3K) on BLAS, not a loop over the samples, (N, 3, K).
    """
    K = basis.shape[0]
    return cast(F64, (v @ basis.transpose(2, 1, 0).reshape(3, 3 * K)).reshape(len(v), 3, K))


def left_times(A: F64, M: F64) -> F64:
    """Return ``A @ M_n`` for one (3, 3) matrix and a stack (N, 3, 3): one BLAS product.

    Row-major, ``vec(A M) = vec(M) kron(A.T, I)``: a (N, 9) x (9, 9) product instead of
    numpy's loop over the stack of small matrices.
    """
    n = len(M)
    return cast(F64, (M.reshape(n, 9) @ np.kron(A.T, np.eye(3))).reshape(n, 3, 3))


def right_times(M: F64, A: F64) -> F64:
    """Return ``M_n @ A`` for a stack (..., K) and one (K, L) matrix: one BLAS product.

    ``M @ A`` on a stack makes one small product per matrix of the stack; the rows of the
    whole stack against ``A`` are one product.
    """
    return cast(F64, (M.reshape(-1, M.shape[-1]) @ A).reshape(*M.shape[:-1], A.shape[-1]))


def norm_last(x: F64, keepdims: bool = False) -> F64:
    """``np.linalg.norm(x, axis=-1, keepdims=keepdims)`` of a short last axis (3 or 4)."""
    out = np.sqrt(dot_last(x, x))
    return cast(F64, out[..., None] if keepdims else out)


def so3_exp(phi: ArrayLike) -> F64:
    """Rodrigues' formula: rotation vector (rad) to rotation matrix, shape (..., 3, 3)."""
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + a * K + b * (K @ K)


def so3_log(C: ArrayLike) -> F64:
    """Rotation matrix to rotation vector (rad), shape (..., 3); robust near 0 and pi."""
    return quat_to_rotvec(matrix_to_quat(C))


def quat_normalize(q: ArrayLike) -> F64:
    """Normalise quaternion(s) to unit norm and ``w >= 0`` (the same rotation), (..., 4)."""
    qa: F64 = np.asarray(q, dtype=float)
    qn: F64 = qa / np.linalg.norm(qa, axis=-1, keepdims=True)
    return np.where(qn[..., 3:4] < 0, -qn, qn)


def quat_conj(q: ArrayLike) -> F64:
    """Conjugate (the inverse rotation for a unit quaternion)."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([-q[..., :3], q[..., 3:]], axis=-1)


def quat_mul(p: ArrayLike, q: ArrayLike) -> F64:
    """Hamilton product ``p * q`` (apply ``q`` first, then ``p``), scalar-last."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    px, py, pz, pw = np.moveaxis(p, -1, 0)
    qx, qy, qz, qw = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
            pw * qw - px * qx - py * qy - pz * qz,
        ],
        axis=-1,
    )


def quat_rotate(q: ArrayLike, v: ArrayLike) -> F64:
    """Rotate vectors ``v`` (..., 3) by unit quaternions ``q`` (..., 4): ``C(q) @ v``."""
    q = np.asarray(q, dtype=float)
    v = np.asarray(v, dtype=float)
    u = q[..., :3]
    w = q[..., 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_to_matrix(q: ArrayLike, transposed: bool = False) -> F64:
    """Convert unit quaternion(s) to rotation matrices, shape (..., 3, 3).

    ``transposed``: return ``C.T`` instead, each entry written to its transposed place
    (the diagnosis needs ``C.T`` of every sample at every iteration; no transposed copy).
    """
    q = np.asarray(q, dtype=float)
    x, y, z, w = np.moveaxis(q, -1, 0)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
        (2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
        (2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)),
    )
    C = np.empty(q.shape[:-1] + (3, 3))
    for i, row in enumerate(rows):
        for j, v in enumerate(row):
            C[(..., j, i) if transposed else (..., i, j)] = v
    return C


def matrix_to_quat(C: ArrayLike) -> F64:
    """Rotation matrices to unit quaternions (scalar-last, ``w >= 0``), shape (..., 4).

    Shepperd's method: of the four candidate formulas, each sample uses the one whose
    denominator (``4 w``, ``4 x``, ``4 y`` or ``4 z``) is largest, so no precision is lost near
    180 deg rotations. Plain numpy: importing scipy's rotation module costs more than a
    ``magalign calibrate`` run's whole fit.
    """
    C = np.asarray(C, dtype=float)
    m = C.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    # 4 * (squared component) for w, x, y, z
    cand = np.stack([1 + tr, 1 + 2 * m[:, 0, 0] - tr, 1 + 2 * m[:, 1, 1] - tr,
                     1 + 2 * m[:, 2, 2] - tr], -1)
    k = np.argmax(cand, axis=-1)
    s = 2.0 * np.sqrt(np.maximum(cand[np.arange(len(m)), k], 1e-300))  # 4 * largest component
    d21, d02, d10 = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
    s21, s02, s10 = m[:, 2, 1] + m[:, 1, 2], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 0] + m[:, 0, 1]
    q = np.empty((len(m), 4))
    rows = [  # (x, y, z, w) * s for k = w, x, y, z
        (d21, d02, d10, s * s / 4),
        (s * s / 4, s10, s02, d21),
        (s10, s * s / 4, s21, d02),
        (s02, s21, s * s / 4, d10),
    ]
    for j, comps in enumerate(rows):
        sel = k == j
        if sel.any():
            q[sel] = np.stack([c[sel] for c in comps], -1) / s[sel, None]
    q = np.where(q[:, 3:4] < 0, -q, q)
    return quat_normalize(q.reshape(C.shape[:-2] + (4,)))


def quat_to_rotvec(q: ArrayLike) -> F64:
    """Convert unit quaternion(s) to rotation vectors in rad, shape (..., 3)."""
    q = quat_normalize(q)
    v = q[..., :3]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, q[..., 3])
    scale = np.where(s < 1e-12, 2.0, angle / np.where(s < 1e-12, 1.0, s))
    return v * scale[..., None]


def rotvec_to_quat(phi: ArrayLike) -> F64:
    """Rotation vectors (rad) to unit quaternions, shape (..., 4)."""
    phi = np.asarray(phi, dtype=float)
    theta = norm_last(phi, keepdims=True)
    half = 0.5 * theta
    k = np.where(theta < 1e-12, 0.5, np.sin(half) / np.where(theta < 1e-12, 1.0, theta))
    return np.concatenate([phi * k, np.cos(half)], axis=-1)


def quat_slerp(q0: ArrayLike, q1: ArrayLike, s: ArrayLike) -> F64:
    """Spherical linear interpolation between pairs of unit quaternions.

    Parameters
    ----------
    q0 : array_like, shape (N, 4)
        Start quaternions (scalar-last).
    q1 : array_like, shape (N, 4)
        End quaternions (scalar-last).
    s : array_like, shape (N,)
        Fraction in [0, 1] from ``q0`` to ``q1``.

    Returns
    -------
    ndarray, shape (N, 4)
        Takes the short way round (``q1`` is flipped where ``q0 . q1 < 0``).

    """
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    s = np.asarray(s, dtype=float)[..., None]
    d = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(d < 0, -q1, q1)
    d = np.abs(d)
    # Exact SLERP down to tiny steps; plain lerp only where sin(omega) would underflow.
    near = d > 1.0 - 1e-13
    omega = np.arccos(np.clip(d, -1.0, 1.0))
    so = np.sin(omega)
    so = np.where(near, 1.0, so)
    a = np.where(near, 1.0 - s, np.sin((1.0 - s) * omega) / so)
    b = np.where(near, s, np.sin(s * omega) / so)
    out = a * q0 + b * q1
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def angle_between_deg(C_a: ArrayLike, C_b: ArrayLike) -> F64:
    """Angle in degrees of the rotation ``C_a @ C_b.T`` (geodesic distance on SO(3))."""
    d = np.asarray(C_a) @ np.swapaxes(np.asarray(C_b), -1, -2)
    c = (np.trace(d, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


# --- Euler angles of Li et al. 2020 -------------------------------------------------------
# The paper's E = Ey(beta) @ Ex(gamma) @ Ez(alpha) (Li 2020, Eqs. 4-6) is the coordinate
# transformation from the geographic frame to the carrier frame: v_body = E @ v_enu, i.e.
# E = C_body_enu. Each elementary matrix is a passive (frame) rotation. Heading alpha is about
# z (positive counter-clockwise seen from above, i.e. ENU yaw), pitch gamma about x and roll
# beta about y.


def Ez(alpha: ArrayLike) -> F64:
    """Elementary frame rotation about z by heading ``alpha`` (rad), Li 2020 Eq. 4."""
    a = np.asarray(alpha, dtype=float)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    rows = [np.stack([c, s, z], -1), np.stack([-s, c, z], -1), np.stack([z, z, o], -1)]
    return np.stack(rows, -2)


def Ex(gamma: ArrayLike) -> F64:
    """Elementary frame rotation about x by pitch ``gamma`` (rad), Li 2020 Eq. 5."""
    g = np.asarray(gamma, dtype=float)
    c, s, o, z = np.cos(g), np.sin(g), np.ones_like(g), np.zeros_like(g)
    rows = [np.stack([o, z, z], -1), np.stack([z, c, s], -1), np.stack([z, -s, c], -1)]
    return np.stack(rows, -2)


def Ey(beta: ArrayLike) -> F64:
    """Elementary frame rotation about y by roll ``beta`` (rad), Li 2020 Eq. 6."""
    b = np.asarray(beta, dtype=float)
    c, s, o, z = np.cos(b), np.sin(b), np.ones_like(b), np.zeros_like(b)
    rows = [np.stack([c, z, -s], -1), np.stack([z, o, z], -1), np.stack([s, z, c], -1)]
    return np.stack(rows, -2)


def li2020_C_body_enu(heading: ArrayLike, pitch: ArrayLike, roll: ArrayLike) -> F64:
    """``E = Ey(roll) @ Ex(pitch) @ Ez(heading)`` = ``C_body_enu`` (Li 2020, Eq. 7); rad."""
    return Ey(roll) @ Ex(pitch) @ Ez(heading)


def li2020_euler_to_quat(heading: ArrayLike, pitch: ArrayLike, roll: ArrayLike) -> F64:
    """Li 2020 heading/pitch/roll (rad) to ``q_enu_body`` (scalar-last), shape (..., 4)."""
    C_body_enu = li2020_C_body_enu(heading, pitch, roll)
    return matrix_to_quat(np.swapaxes(C_body_enu, -1, -2))


def quat_to_li2020_euler(q_enu_body: ArrayLike) -> tuple[F64, F64, F64]:
    """Inverse of :func:`li2020_euler_to_quat`: (heading, pitch, roll) in rad.

    From ``E = Ey(b) Ex(g) Ez(a)``: ``E[1,2] = sin g``, ``E[0,2] = -sin b cos g``,
    ``E[2,2] = cos b cos g``, ``E[1,0] = -sin a cos g``, ``E[1,1] = cos a cos g``.
    """
    # E = C_enu_body.T; only the five elements used, each with the expression of
    # quat_to_matrix (the same values, without building N 3x3 matrices)
    q = np.asarray(q_enu_body, dtype=float)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    e12 = 2 * (y * z + x * w)  # C[2, 1]
    e02 = 2 * (x * z - y * w)  # C[2, 0]
    e22 = 1 - 2 * (x * x + y * y)  # C[2, 2]
    e10 = 2 * (x * y - z * w)  # C[0, 1]
    e11 = 1 - 2 * (x * x + z * z)  # C[1, 1]
    pitch = np.arcsin(np.clip(e12, -1.0, 1.0))
    roll = np.arctan2(-e02, e22)
    heading = np.arctan2(-e10, e11)
    return heading, pitch, roll


def novatel_to_quat(roll_deg: ArrayLike, pitch_deg: ArrayLike, azimuth_deg: ArrayLike) -> F64:
    """NovAtel INSPVA roll, pitch, azimuth (deg) to ``q_enu_body``.

    NovAtel's body frame is x right, y forward, z up, and azimuth is clockwise from north, so
    the attitude is ``Rz(-azimuth) @ Rx(pitch) @ Ry(roll)`` (active rotations, NovAtel's order).
    The forward axis then points at ENU yaw ``90 deg - azimuth`` measured counter-clockwise
    from east, as CONVENTIONS state.
    """
    a = -np.radians(np.asarray(azimuth_deg, dtype=float))
    p = np.radians(np.asarray(pitch_deg, dtype=float))
    r = np.radians(np.asarray(roll_deg, dtype=float))
    qz = np.stack([np.zeros_like(a), np.zeros_like(a), np.sin(a / 2), np.cos(a / 2)], -1)
    qx = np.stack([np.sin(p / 2), np.zeros_like(p), np.zeros_like(p), np.cos(p / 2)], -1)
    qy = np.stack([np.zeros_like(r), np.sin(r / 2), np.zeros_like(r), np.cos(r / 2)], -1)
    return quat_normalize(quat_mul(quat_mul(qz, qx), qy))


def quat_to_novatel(q_enu_body: ArrayLike) -> tuple[F64, F64, F64]:
    """Inverse of :func:`novatel_to_quat`: (roll_deg, pitch_deg, azimuth_deg in [0, 360))."""
    C = quat_to_matrix(q_enu_body)
    # C = Rz(a) Rx(p) Ry(r): C[2,1] = sin p, C[2,0] = -cos p sin r, C[2,2] = cos p cos r,
    # C[0,1] = -sin a cos p, C[1,1] = cos a cos p.
    p = np.arcsin(np.clip(C[..., 2, 1], -1.0, 1.0))
    r = np.arctan2(-C[..., 2, 0], C[..., 2, 2])
    a = np.arctan2(-C[..., 0, 1], C[..., 1, 1])
    az = np.mod(-np.degrees(a), 360.0)
    return np.degrees(r), np.degrees(p), az


def rot_z(yaw_rad: float) -> np.ndarray:
    """Return the rotation about Up by ``yaw_rad``, (3, 3): ``p_enu = Q @ p_local``."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

"""Small in-memory synthetic problems for tests and the accuracy benchmark.

The full simulator (``pipeline.app.simulate``) writes recordings with every effect; this module
only draws the CONVENTIONS model quickly, vectorised, so that a Monte Carlo of hundreds of runs
stays fast.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.geometry import (
    li2020_euler_to_quat,
    quat_conj,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_to_matrix,
    rotvec_to_quat,
)
from pipeline.core.recording import AlignedSeries, AttitudeSeries
from stages.estimators.base import F64, NoiseModel


@dataclass(frozen=True)
class Synthetic:
    """A drawn data set and its truth."""

    aligned: AlignedSeries
    attitude: AttitudeSeries
    q_true: F64
    R_body_mag: F64
    B_enu_nT: F64
    D: F64
    offset_nT: F64
    time_offset_s: float


def euler_profile(kind: str, n: int, rate_hz: float, *, varying_rate: bool = False) -> tuple:
    """Heading, pitch, roll (rad) of a motion profile at ``n`` samples.

    ``"single"``: one full heading turn (Li 2020 Section 4.1: rotation about the vertical, pitch
    and roll fixed at 0). ``"multi"``: two heading turns while pitch and roll swing +-30 deg
    at incommensurate frequencies.
    """
    t = np.arange(n) / rate_hz
    T = n / rate_hz
    u = t / T
    if varying_rate:
        u = u + 0.08 * np.sin(2 * np.pi * 3 * u)
    if kind == "single":
        return 2 * np.pi * u, np.zeros(n), np.zeros(n)
    if kind == "multi":
        return (
            4 * np.pi * u,
            np.radians(30) * np.sin(2 * np.pi * 3.1 * u),
            np.radians(30) * np.sin(2 * np.pi * 4.7 * u + 0.4),
        )
    raise ValueError(kind)


def draw(
    *,
    kind: str = "multi",
    n: int = 2000,
    rate_hz: float = 50.0,
    R_body_mag: F64 | None = None,
    B_enu_nT: F64 | tuple[float, float, float] = (10000.0, 30000.0, 20000.0),
    D: F64 | None = None,
    offset_nT: F64 | None = None,
    time_offset_s: float = 0.0,
    noise: NoiseModel | None = None,
    varying_rate: bool = False,
    rng: np.random.Generator | None = None,
    t0_ns: int = 1_700_000_000_000_000_000,
) -> Synthetic:
    """Draw one synthetic data set of the CONVENTIONS model.

    The magnetometer sample stamped ``t`` senses the field at ``t - tau``; the attitude series
    is stamped at the true times, with attitude noise added as ``pipeline.app.simulate`` adds it
    (heading error about ENU up, pitch and roll errors about body x and body y).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    R = np.eye(3) if R_body_mag is None else np.asarray(R_body_mag, float)
    Dm = np.eye(3) if D is None else np.asarray(D, float)
    o = np.zeros(3) if offset_nT is None else np.asarray(offset_nT, float)
    B = np.asarray(B_enu_nT, float)
    # Attitude on a finer grid than the magnetometer so that tau can be interpolated.
    t_ns = t0_ns + (np.arange(n) * (1e9 / rate_hz)).astype(np.int64)
    h, p, r = euler_profile(kind, n, rate_hz, varying_rate=varying_rate)
    q_true = li2020_euler_to_quat(h, p, r)
    # The sensed field at t - tau: the attitude then (profile is a function of time).
    if time_offset_s:
        tt = np.arange(n) / rate_hz - time_offset_s
        hh, pp, rr = _profile_at(kind, n, rate_hz, tt, varying_rate)
        q_sensed = li2020_euler_to_quat(hh, pp, rr)
    else:
        q_sensed = q_true
    b_body = quat_rotate(quat_conj(q_sensed), np.broadcast_to(B, (n, 3)))
    y = (b_body @ R) @ Dm.T + o
    q_meas = q_true
    if noise is not None:
        y = y + noise.sigma_mag_nT * rng.standard_normal((n, 3))
        if noise.sigma_heading_rad or noise.sigma_pitch_rad or noise.sigma_roll_rad:
            # As pipeline.app.simulate applies it (and NoiseModel.attitude_cov_body models it):
            # heading error about ENU up, pitch and roll errors about body x and body y.
            dh = noise.sigma_heading_rad * rng.standard_normal(n)
            dp = noise.sigma_pitch_rad * rng.standard_normal(n)
            dr = noise.sigma_roll_rad * rng.standard_normal(n)
            zero = np.zeros(n)
            q_up = rotvec_to_quat(np.stack([zero, zero, dh], -1))
            q_pr = rotvec_to_quat(np.stack([dp, dr, zero], -1))
            q_meas = quat_normalize(quat_mul(quat_mul(q_up, q_true), q_pr))
    att = AttitudeSeries(t_ns, q_meas)
    al = AlignedSeries(t_ns, y, q_meas, 0.0, np.arange(n))
    return Synthetic(al, att, q_true, R, B, Dm, o, float(time_offset_s))


def _profile_at(kind: str, n: int, rate_hz: float, t_s: F64, varying_rate: bool) -> tuple:
    T = n / rate_hz
    u = t_s / T
    if varying_rate:
        u = u + 0.08 * np.sin(2 * np.pi * 3 * u)
    if kind == "single":
        return 2 * np.pi * u, np.zeros_like(u), np.zeros_like(u)
    return (
        4 * np.pi * u,
        np.radians(30) * np.sin(2 * np.pi * 3.1 * u),
        np.radians(30) * np.sin(2 * np.pi * 4.7 * u + 0.4),
    )


def small_rotation(deg_xyz: F64) -> F64:
    """Rotation matrix of a rotation vector given in degrees."""
    return quat_to_matrix(rotvec_to_quat(np.radians(np.asarray(deg_xyz, float))))


__all__ = ["Synthetic", "draw", "euler_profile", "small_rotation", "quat_mul"]

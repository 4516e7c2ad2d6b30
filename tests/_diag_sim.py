"""In-memory simulated data for the diagnose/effects tests (no dependency on the simulator)."""

from __future__ import annotations

import numpy as np

from pipeline.core.geometry import quat_mul, quat_normalize, rotvec_to_quat, so3_exp
from pipeline.core.vocabulary import EffectKind
from stages.diagnose.model import AttitudeTrack, FitData, ModelState, Term, evaluate

B_ENU = np.array([1500.0, 21000.0, -43000.0])


def tumble(
    duration_s: float, rate_hz: float, seed: int, single_axis: bool = False
) -> AttitudeTrack:
    """A smooth 3-D tumble (or a variable-rate turn about body z), q_enu_body at rate_hz."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    if single_axis:
        ang = 0.8 * t + 0.6 * np.sin(0.5 * t)
        q = rotvec_to_quat(np.stack([0 * t, 0 * t, ang], -1))
    else:
        w = np.zeros((len(t), 3))
        for k in range(3):
            f = rng.uniform(0.05, 0.2, 3)
            ph = rng.uniform(0, 2 * np.pi, 3)
            w[:, k] = sum(np.sin(2 * np.pi * f[j] * t + ph[j]) for j in range(3)) * 0.6
        dq = rotvec_to_quat(w / rate_hz)
        q = np.empty((len(t), 4))
        q[0] = [0, 0, 0, 1]
        # integrate in body frame (cumulative product, vectorised in chunks is overkill here)
        for i in range(1, len(t)):
            q[i] = quat_mul(q[i - 1], dq[i])
        q = quat_normalize(q)
    return AttitudeTrack(t, q)


def lissajous_m(t_s: np.ndarray, amplitude_m: float = 0.3) -> np.ndarray:
    """A path through space that revisits places at different times, (N, 3), m."""
    t = np.asarray(t_s, dtype=float)[:, None]
    return np.array([0.0, 0.0, 1.5]) + amplitude_m * np.array([1.0, 1.0, 0.6]) * np.sin(
        2 * np.pi * t / np.array([7.3, 5.1, 3.7]) + np.array([0.0, 1.0, 2.0]))


def make_data(
    terms: tuple[Term, ...] = (),
    values: tuple[np.ndarray, ...] = (),
    *,
    duration_s: float = 60.0,
    rate_hz: float = 50.0,
    noise_nT: float = 5.0,
    seed: int = 0,
    single_axis: bool = False,
    positions: np.ndarray | None = None,
    position_frame: str = "enu",
) -> tuple[FitData, ModelState]:
    """Readings predicted by the model with ``terms`` plus white noise; returns (data, truth).

    ``positions`` (N, 3), m, in ``position_frame``: the path of the sensor (``p_ref`` is its
    mean), needed by ``field_gradient``; a callable of the stamps (s) also works.
    """
    track = tumble(duration_s, rate_hz, seed, single_axis)
    R = so3_exp(np.radians([2.0, -1.5, 3.0]))
    truth = ModelState(R, B_ENU.copy(), tuple(terms), tuple(np.asarray(v, float) for v in values))
    t = track.t_s.copy()
    pos: dict = {}
    if positions is not None:
        p = positions(t) if callable(positions) else np.asarray(positions, float)
        pos = {"p_m": p, "p_ref_m": p.mean(axis=0), "position_frame": position_frame}
    data = FitData(t, np.zeros((len(t), 3)), track, **pos)
    y = evaluate(truth, data, jacobian=False).y_nT
    rng = np.random.default_rng(seed + 1000)
    y = y + rng.normal(0.0, noise_nT, y.shape)
    return FitData(t, y, track, **pos), truth


def all_terms() -> tuple[tuple[Term, ...], tuple[np.ndarray, ...]]:
    """Every effect at a moderate value (for Jacobian checks)."""
    terms = (
        Term(EffectKind.HARD_IRON),
        Term(EffectKind.SOFT_IRON),
        Term(EffectKind.TIME_OFFSET),
        Term(EffectKind.EDDY_CURRENT),
        Term(EffectKind.FIELD_DRIFT),
        Term(EffectKind.DISTURBANCE, ((10.0, 14.0),)),
        Term(EffectKind.HARD_IRON_STEP, ((20.0, 30.0),)),
        Term(EffectKind.AXIS_TILT),
    )
    vals = (
        np.array([300.0, -200.0, 100.0]),
        np.array([0.02, -0.01, 0.005, 0.01, -0.003]),
        np.array([0.02]),
        np.array([0.001, 0.002, 0.0, -0.001, 0.003, 0.0, 0.0, 0.001, 0.002]),
        np.array([10.0, -5.0, 3.0, 2.0, 1.0, -4.0, 3.0, 1.0, 0.0, -2.0, 1.0, 1.0]),
        np.arange(3 * 5, dtype=float) * 10.0,
        np.array([50.0, -30.0, 20.0]),
        np.array([0.0, 0.0]),
    )
    return terms, vals

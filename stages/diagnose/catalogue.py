"""The catalogue of effects: names, explanations, identifiability.

How a finding is explained (``explanation``: what each effect is, how it shows and what
its fitted values suggest are its module's, ``pipeline.model.effects``), and whether the
motion of a recording can determine it (``motion_stats``, ``identifiability_reason``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.core.geometry import quat_to_matrix
from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects import EFFECTS
from stages.diagnose.model import (
    CONFOUND_RATIO,
    F64,
    MIN_HORIZONTAL_FRACTION,
    FitData,
    drift_basis,
    drift_span,
)


def explanation(
    kind: EffectKind, params: dict[str, Any], duration_s: float, note: str | None = None
) -> str:
    """Words for one finding: the physics, the signature, and what the fitted values suggest.

    Parameters
    ----------
    kind : EffectKind
        The effect found.
    params : dict
        The finding's CONVENTIONS params.
    duration_s : float
        Span of the recording, s.
    note : str, optional
        ``field_drift`` with positions in the recording: what the test of a spatial
        gradient found (replaces the remark that drift and gradient cannot be separated).

    Returns
    -------
    str

    """
    # the effect's module writes its words and what its fitted values suggest
    return EFFECTS[kind].explanation(params, duration_s, note)


def position_confounding(data: FitData) -> tuple[float, float]:
    """Spread of the positions and the part of it that is not a function of time.

    Returns
    -------
    (spread_m, independent)
        RMS distance from the reference position, m; the fraction of the position variance
        left after a fit of the drift basis (a constant and Legendre P1..P4 in time): 0 when
        the path is a slow function of time that a field drift would mimic, 1 when the
        sensor comes back to the same places at different times.

    """
    if data.p_m is None or len(data) < 10:
        return 0.0, 0.0
    dp = data.dp_m
    spread = float(np.sqrt(np.mean(np.sum(dp**2, axis=1))))
    P = np.column_stack([np.ones(len(data)), drift_basis(data.t_s, 0.0, drift_span(data))])
    coef, *_ = np.linalg.lstsq(P, dp, rcond=None)
    left = dp - P @ coef
    tot = float(np.sum((dp - dp.mean(axis=0)) ** 2))
    return spread, float(np.sum(left**2) / tot) if tot > 0 else 0.0


#: A gradient needs the sensor to move at least this far (RMS about its mean position), m.
MIN_POSITION_SPREAD_M = 0.02


#: ... and at least this fraction of that movement not to be a smooth function of time.
MIN_POSITION_INDEPENDENT = 0.05


@dataclass(frozen=True)
class MotionStats:
    """Descriptors of the motion that decide what is identifiable.

    Attributes
    ----------
    axis_spread : float
        Second largest / largest eigenvalue of the angular-velocity second moment (0 for a
        rotation about a single axis, ~1 for rich 3-D motion).
    rate_cv : float
        Coefficient of variation of the rotation rate (0 for a constant rate).
    rate_rms_deg_s : float
        RMS rotation rate, deg/s.
    main_axis_body : ndarray (3,)
        Dominant rotation axis, body frame.
    total_turn_deg : float
        Integrated rotation angle over the recording.

    """

    axis_spread: float
    rate_cv: float
    rate_rms_deg_s: float
    main_axis_body: F64
    total_turn_deg: float


def motion_stats(data: FitData) -> MotionStats:
    """Angular velocity statistics from the attitude track at the sample stamps."""
    t = data.t_s
    h = max(data.track.step_s, 1e-3)
    q0 = data.track.at(t - h)
    q1 = data.track.at(t + h)
    C0 = quat_to_matrix(q0)
    C1 = quat_to_matrix(q1)
    # body-frame angular velocity: C0.T C1 = exp([w]x 2h)
    dC = np.swapaxes(C0, -1, -2) @ C1
    w = np.stack(
        [dC[:, 2, 1] - dC[:, 1, 2], dC[:, 0, 2] - dC[:, 2, 0], dC[:, 1, 0] - dC[:, 0, 1]], -1
    )
    w = w / (2.0 * 2.0 * h)
    M = w.T @ w / max(len(w), 1)
    ev, evec = np.linalg.eigh(M)
    spread = float(ev[1] / ev[2]) if ev[2] > 0 else 0.0
    rate = np.linalg.norm(w, axis=1)
    mean = float(np.mean(rate))
    cv = float(np.std(rate) / mean) if mean > 1e-9 else 0.0
    dt = np.diff(t, prepend=t[0])
    return MotionStats(
        axis_spread=spread,
        rate_cv=cv,
        rate_rms_deg_s=float(np.degrees(np.sqrt(np.mean(rate**2)))),
        main_axis_body=evec[:, 2],
        total_turn_deg=float(np.degrees(np.sum(rate * dt))),
    )


def identifiability_reason(
    kind: EffectKind, stats: MotionStats, data: FitData, efficiency: float,
    horizontal_fraction: float | None = None,
) -> str | None:
    """Why ``kind`` cannot be determined from this recording, or None if it can.

    Parameters
    ----------
    kind : EffectKind
        The candidate effect.
    stats : MotionStats
        The recording's motion.
    data : FitData
        The data (a known reference field changes what is identifiable).
    efficiency : float
        Smallest eigenvalue ratio of the term's efficient information (Schur complement
        against the parameters already in the model) to its own information: the fraction of
        the weakest parameter combination that the other parameters cannot mimic.
    horizontal_fraction : float, optional
        ``|B_horizontal| / |B|`` of the current field (``heading_drift`` needs one).

    Returns
    -------
    str or None

    """
    single_axis = stats.axis_spread < 0.02
    if kind is EffectKind.LEVER_ARM:
        if data.p_m is None:
            return "no positions in the recording: the sensor's offset from the tracked " \
                   "point acts only through a field that varies in space"
        if efficiency < CONFOUND_RATIO:
            return (
                f"the field varies too little in space along this motion (only {efficiency:.1e} "
                "of the weakest lever-arm direction is independent of the other terms); turn "
                "the platform near a source or in a strong gradient to determine it"
            )
        return None
    if kind is EffectKind.LOCAL_SOURCE:
        if data.p_m is None:
            return "no positions in the recording: a source fixed in the surroundings is seen " \
                   "only through where the sensor is"
        return None
    if kind is EffectKind.FIELD_GRADIENT:
        if data.p_m is None:
            return "no positions in the recording (the attitude messages carry none)"
        spread, indep = position_confounding(data)
        if spread < MIN_POSITION_SPREAD_M:
            return (
                f"the sensor hardly moved through space ({spread * 100:.1f} cm RMS about its "
                "mean position): a field gradient has nothing to act on"
            )
        if indep < MIN_POSITION_INDEPENDENT:
            return (
                f"the sensor's path is a slow function of time (only {100 * indep:.1f} % of "
                "the position variance is left after a quartic in time): a gradient along it "
                "cannot be told from a field drift; revisit places at different times"
            )
        if efficiency < 1e-3:
            return (
                "the path through space leaves the gradient confounded with terms already in "
                f"the model (only {efficiency:.1e} of its weakest combination is independent)"
            )
        return None
    if stats.total_turn_deg < 20.0 and kind is not EffectKind.FIELD_DRIFT:
        return (
            f"the platform turned only {stats.total_turn_deg:.0f} deg in total: without "
            "turning, every term that acts like a field looks like the background field itself"
        )
    if kind is EffectKind.AXIS_TILT:
        if data.B_known_enu_nT is None:
            return (
                "a tilt of the rotation axis is absorbed exactly by the misalignment and the field "
                "while the field is estimated; give a reference field to determine it"
            )
    if kind is EffectKind.HARD_IRON and single_axis and data.B_known_enu_nT is None:
        return (
            "the sensor turned about a single axis only: the part of the offset along that "
            "axis looks the same as the unknown field; turn it about a second axis or give a "
            "reference field"
        )
    rate_kinds = (EffectKind.TIME_OFFSET, EffectKind.EDDY_CURRENT)
    if kind in rate_kinds and single_axis and stats.rate_cv < 0.05:
        return (
            "the sensor turned at a steady rate about one axis: a time offset then looks the "
            "same as a fixed turn of the heading, which the misalignment absorbs; vary the "
            "rate or turn about more than one axis"
        )
    if kind is EffectKind.HEADING_DRIFT:
        if horizontal_fraction is not None and horizontal_fraction < MIN_HORIZONTAL_FRACTION:
            return (
                f"the field is nearly vertical (horizontal part {100 * horizontal_fraction:.1f} "
                "% of |B|): a heading error hardly changes it"
            )
        if stats.total_turn_deg < 20.0:
            return (
                "the platform hardly turned: a slow heading error cannot be told from a slow "
                "change of the field or of the offset"
            )
    if kind is EffectKind.FIELD_DRIFT and stats.total_turn_deg < 20.0:
        return (
            "the platform hardly turned: a slow field change cannot be told from a slow change "
            "of attitude or offset"
        )
    if efficiency < CONFOUND_RATIO:
        which = {
            EffectKind.FIELD_DRIFT: "slow attitude changes and the field",
            EffectKind.SOFT_IRON: "the field magnitude and the misalignment",
            EffectKind.EDDY_CURRENT: "the time offset and the misalignment",
            EffectKind.HEADING_DRIFT: "the field and the misalignment",
        }.get(kind, "terms already in the model")
        return (
            f"the motion leaves this term looking like {which}: it cannot be told apart from "
            "them in this recording"
        )
    return None

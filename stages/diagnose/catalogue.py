"""The catalogue of effects: names, explanations, identifiability.

How a finding is explained (``explanation``: what each effect is, how it shows and what
its fitted values suggest are its module's, ``pipeline.model.effects``), and whether the
motion of a recording can determine it (``motion_stats``, ``identifiability_reason``: what
each effect needs of the motion is its module's too, ``Effect.undetermined``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.core.geometry import quat_to_matrix
from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects import EFFECTS
from stages.diagnose.model import (
    F64,
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


@dataclass(frozen=True)
class _Motion:
    """A recording's motion as an effect judges it (:class:`pipeline.model.effects.base.Motion`)."""

    stats: MotionStats
    data: FitData

    @property
    def total_turn_deg(self) -> float:
        """The integrated rotation angle, deg."""
        return self.stats.total_turn_deg

    @property
    def axis_spread(self) -> float:
        """The angular velocity's second-largest / largest moment."""
        return self.stats.axis_spread

    @property
    def rate_cv(self) -> float:
        """The rotation rate's coefficient of variation."""
        return self.stats.rate_cv

    @property
    def has_positions(self) -> bool:
        """The data carry positions."""
        return self.data.p_m is not None

    @property
    def field_known(self) -> bool:
        """A reference field is given."""
        return self.data.B_known_enu_nT is not None

    def position_confounding(self) -> tuple[float, float]:
        """Return :func:`position_confounding` of the data."""
        return position_confounding(self.data)


def identifiability_reason(
    kind: EffectKind, stats: MotionStats, data: FitData, efficiency: float,
    horizontal_fraction: float | None = None,
) -> str | None:
    """Why ``kind`` cannot be determined from this recording, or None if it can.

    What the motion must contain is the effect's own (:meth:`Effect.undetermined`).

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
    return EFFECTS[kind].undetermined(_Motion(stats, data), efficiency, horizontal_fraction)

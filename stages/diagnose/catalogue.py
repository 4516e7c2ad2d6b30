"""The catalogue of effects: names, explanations, identifiability.

How a finding is explained (``explanation``; what each effect is and how it shows are its
module's, ``pipeline.model.effects``), and whether the motion of a recording can
determine it (``motion_stats``, ``identifiability_reason``).
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
    rot_z,
)

# Rate of change of the geomagnetic field: about 0.1 nT/min for the quiet diurnal variation,
# rarely above 10 nT/min at mid latitudes even in a storm. A fitted drift much faster than
# that is more likely the sensor moving through a spatially varying field.
GEOMAGNETIC_RATE_NT_MIN = 10.0


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
    info = EFFECTS[kind]
    text = f"{info.physics}; signature: {info.signature}"
    if kind is EffectKind.FIELD_DRIFT:
        p2p = float(np.max(params["peak_to_peak_nT"]))
        rate = p2p / max(duration_s / 60.0, 1e-9)
        text += (
            f". The fitted change reaches {p2p:.0f} nT over {duration_s:.0f} s "
            f"(about {rate:.1f} nT/min); "
        )
        if rate > GEOMAGNETIC_RATE_NT_MIN:
            text += (
                f"that is faster than geomagnetic variation (below ~{GEOMAGNETIC_RATE_NT_MIN:.0f} "
                "nT/min outside severe storms), so the sensor most likely moved through a "
                "spatially varying field"
            )
        else:
            text += "that is within the range of diurnal or storm-time geomagnetic variation"
        if note is None:
            text += (
                ". A spatial field gradient cannot be separated from a drift in time without "
                "the sensor's positions, which this recording does not carry: the term models "
                "both"
            )
        else:
            text += ". " + note
    if kind is EffectKind.LOCAL_SOURCE:
        pos = ", ".join(f"{x:.2f}" for x in params["position_m"])
        m = float(np.linalg.norm(params["moment_Am2"]))
        frame = ("the attitude source's own frame (the motion-capture room)"
                 if params.get("position_frame") == "attitude_source_local" else "local ENU")
        text += f". Located at ({pos}) m in {frame}, moment {m:.3g} A m^2"
        if params.get("closest_approach_m") is not None:
            text += (f"; the sensor came closest, {100 * params['closest_approach_m']:.0f} cm, "
                     f"at {params['closest_approach_s']:.1f} s")
        text += (
            ". It belongs to the surroundings, not to the sensor: the restored field keeps it "
            "(a survey maps it); calibrate away from it, or keep it in the model"
        )
    if kind is EffectKind.FIELD_MAP:
        pp = [float(x) for x in params["peak_to_peak_nT"]]
        dom = np.asarray(params["domain_m"], dtype=float)
        frame = ("the attitude source's own frame (the motion-capture room)"
                 if params.get("position_frame") == "attitude_source_local" else "local ENU")
        text += (
            f". Beyond the linear gradient the field changes by up to {max(pp):.0f} nT "
            "(range of E, N, U over the places visited: " + ", ".join(f"{x:.0f}" for x in pp)
            + f" nT), modelled as minus the gradient of a potential in {params['n_basis']} "
            "Laplace eigenfunctions of a box of " + " x ".join(
                f"{b - a:.2f}" for a, b in dom) + f" m in {frame} (Solin et al. 2018), "
            f"GP length scale {params['length_scale_m']:.2f} m. It belongs to the "
            "surroundings, not to the sensor: the restored field keeps it. Calibrate where the "
            "field is uniform (or turn the sensor in place), or keep the positions and this "
            "term in the model"
        )
    if kind is EffectKind.LEVER_ARM:
        lv = np.asarray(params["lever_arm_body_m"], dtype=float)
        text += (
            f". The magnetometer sits {100 * float(np.linalg.norm(lv)):.1f} cm from the tracked "
            "point, at (" + ", ".join(f"{100 * x:+.1f}" for x in lv) + ") cm in the body "
            "frame; set this offset in the survey's lever-arm configuration"
        )
    if kind is EffectKind.HEADING_DRIFT:
        text += (
            f". The attitude's heading error changes by {params['peak_to_peak_deg']:.3g} deg "
            f"over {duration_s:.0f} s (a mean rate of {params['rate_deg_per_h']:.3g} deg/h). "
            "A field that turns about Up without changing its magnitude would give the same "
            "readings; the field does not do that by itself (diurnal and storm variations "
            "change |B| and Up), an attitude source's heading does. Check the source's heading "
            "aiding (magnetometer, GNSS dual antenna, mocap frame) and its gyro bias"
        )
    if kind is EffectKind.FIELD_GRADIENT:
        G = np.asarray(params["G_nT_per_m"], dtype=float)
        frob = float(np.linalg.norm(G))
        text += (
            f". The fitted gradient is {frob / 1e3:.2f} uT/m (Frobenius norm of G), "
            f"{float(np.max(np.abs(G))) / 1e3:.2f} uT/m at most per component, about the "
            "mean position"
        )
        if params.get("position_frame") == "attitude_source_local":
            Q = yaw_of_gradient(G)
            text += (
                "; the positions are in the attitude source's own frame (third axis up, "
                "horizontal axes of unknown bearing), so G is G_enu Q with Q a rotation about "
                f"Up, found at {np.degrees(Q):.0f} deg (where G_enu Q^T is most nearly "
                "symmetric)"
            )
        text += (
            ". Calibrate where the field is uniform (away from steel, or with the sensor kept "
            "at one place while it turns), or keep the positions and this term in the model"
        )
    if kind is EffectKind.AXIS_TILT:
        text += (
            f". The axis leans {params['tilt_deg']:.3g} deg towards bearing "
            f"{params['azimuth_deg']:.0f} deg. With the misalignment estimated, the readings fix "
            "only the angle between the rotation axis and the field: every axis on that cone "
            "around B fits equally (a lean across the field's bearing turns B about the axis, "
            "which the misalignment absorbs), and the one of least tilt, leaning along the "
            "field's bearing, is reported. The true tilt is at least this large; a mounting "
            "known from another calibration would determine its direction"
        )
    return text


def yaw_of_gradient(M: F64) -> float:
    """Rotation about Up (rad) that makes ``M Q^T`` symmetric: the position frame's yaw.

    For ``M = G_enu Rz(a)`` with ``G_enu`` symmetric, ``M Rz(a)^T`` is symmetric; the
    antisymmetric part of ``M Rz(b)^T`` is checked on a fine grid of ``b`` (defined up to
    half a turn when G has no vertical-horizontal coupling).
    """
    b = np.radians(np.arange(0.0, 360.0, 0.5))
    asym = [np.linalg.norm(M @ rot_z(x).T - (M @ rot_z(x).T).T) for x in b]
    return float(b[int(np.argmin(asym))])


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
            f"the platform turned only {stats.total_turn_deg:.0f} deg in total: without rotation "
            "every field-like term is the same constant as B_enu"
        )
    if kind is EffectKind.AXIS_TILT:
        if data.B_known_enu_nT is None:
            return (
                "a tilt of the rotation axis is absorbed exactly by the misalignment and the field "
                "while the field is estimated; give a reference field to determine it"
            )
    if kind is EffectKind.HARD_IRON and single_axis and data.B_known_enu_nT is None:
        return (
            "rotation about a single axis only (axis spread "
            f"{stats.axis_spread:.3f}): the offset component along that axis is confounded with "
            "the unknown field; rotate about a second axis or give a reference field"
        )
    rate_kinds = (EffectKind.TIME_OFFSET, EffectKind.EDDY_CURRENT)
    if kind in rate_kinds and single_axis and stats.rate_cv < 0.05:
        return (
            f"rotation at a constant rate about one axis (rate CV {stats.rate_cv:.3f}): a time "
            "offset equals a fixed heading rotation, absorbed by the misalignment; vary the "
            "rotation rate or rotate about more than one axis"
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
            f"the motion leaves this term confounded with {which} (only {efficiency:.1e} of its "
            "weakest combination is independent of them)"
        )
    return None

"""Independent recordings for the diagnosis (issue 15 A): no magalign model code.

Every recording is made here from first principles with ``scipy.spatial.transform``
(``Rotation``) and written with the ``mcap_ros2`` writer from hand-written message
definitions; nothing of ``pipeline.app.simulate``, ``stages.diagnose.model``,
``pipeline.io.messages`` or ``pipeline.io.mcap_write`` is used, so a shared mistake in
magalign's model or writer cannot hide here.

The physics (CONVENTIONS, "Measurement model"), for a magnetometer sample stamped ``t``::

    t_s    = t - tau                                        sensing time
    b(t)   = C_true(t_s).T @ B_enu(t_s, p(t_s))            body frame, nT
    y0(t)  = D @ R_body_mag.T @ b(t)
    y(t)   = y0 + o + o_step 1[t in windows] + E_s @ dy0/dt + noise

with ``C_true`` the true attitude; the attitude source reports ``Rz(h(t)) C_true(t) exp(n)``
(``h`` the heading drift, ``n`` its noise). ``dy0/dt`` is a central difference of the
continuous motion (step 0.1 ms), not of the samples.

Space: ``p(t)`` is the tracked point of the position source (what the file carries); the
magnetometer sits at ``p(t) + C_true(t) @ l`` (``lever_arm``, ``l = 0`` without it), and every
spatial term of ``B_enu`` (``field_gradient``, ``local_source``: a point dipole fixed in the
surroundings; ``field_map``: a smooth non-linear field, the sum of distant point dipoles,
each minus the gradient of its own closed-form potential ``100 nT (m.r) / r^3``) is
evaluated there. Paths (``Spec.path``): ``lissajous`` (the original motion),
``survey`` (parallel lines walked with the heading along the track), ``translate`` (a lab
recording that moves the sensor but barely turns it) and ``handheld`` (a sensor carried by
hand through a room's volume, turning as it goes). Positions are written as PoseStamped
(local metres, optionally in a frame rotated about Up), INSPVA or NavSatFix (WGS-84 geodetic,
flat-earth tangent plane at ``Spec.geo_origin``). :func:`truth` states what went in.

Sizes are multiples of the detection threshold, computed here independently (the same
definition as ``pipeline.app.challenge``): the noise-free signature ``d`` of the effect, with the
part that a change of ``R_body_mag`` and ``B_enu`` absorbs removed by least squares (their
Jacobian by finite differences of this module's own model), gives ``lambda = |d_perp|^2 /
var``; the threshold is ``lambda_thr = k ln(3N) + 20`` (the BIC gate) and the strength
``sqrt(lambda / lambda_thr)``. Linear effects are scaled to a target strength.

The module is imported by tests and by ``bench/diagnose.py`` as ``indep_gen``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from mcap_ros2.writer import Writer
from scipy.spatial.transform import Rotation

# ----------------------------------------------------------------------------- message texts

_HEADER = """================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""
_VEC = """================================================================================
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
"""
_QUAT = """================================================================================
MSG: geometry_msgs/Quaternion
float64 x
float64 y
float64 z
float64 w
"""
MSGDEFS = {
    "sensor_msgs/msg/MagneticField": "std_msgs/Header header\ngeometry_msgs/Vector3 "
    "magnetic_field\nfloat64[9] magnetic_field_covariance\n" + _HEADER + _VEC,
    "sensor_msgs/msg/Imu": "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\n"
    "float64[9] orientation_covariance\ngeometry_msgs/Vector3 angular_velocity\n"
    "float64[9] angular_velocity_covariance\ngeometry_msgs/Vector3 linear_acceleration\n"
    "float64[9] linear_acceleration_covariance\n" + _HEADER + _QUAT + _VEC,
    "geometry_msgs/msg/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose\n"
    + _HEADER + """================================================================================
MSG: geometry_msgs/Pose
geometry_msgs/Point position
geometry_msgs/Quaternion orientation
================================================================================
MSG: geometry_msgs/Point
float64 x
float64 y
float64 z
""" + _QUAT,
    "geometry_msgs/msg/QuaternionStamped": "std_msgs/Header header\n"
    "geometry_msgs/Quaternion quaternion\n" + _HEADER + _QUAT,
    # NovAtel's driver (novatel_oem7_msgs), the definition as the driver publishes it
    "novatel_oem7_msgs/msg/INSPVA": """std_msgs/Header header
Oem7Header nov_header
float64 latitude
float64 longitude
float64 height
float64 north_velocity
float64 east_velocity
float64 up_velocity
float64 roll
float64 pitch
float64 azimuth
InertialSolutionStatus status
""" + _HEADER + """================================================================================
MSG: novatel_oem7_msgs/Oem7Header
string message_name
uint16 message_id
uint8 message_type
uint32 sequence_number
uint8 time_status
uint16 gps_week_number
uint32 gps_week_milliseconds
================================================================================
MSG: novatel_oem7_msgs/InertialSolutionStatus
uint32 status
""",
}
# ROS 2 sensor_msgs (Humble), with the NavSatStatus it nests; the constants are part of the
# definition a reader parses, so they are written as the package states them
MSGDEFS["sensor_msgs/msg/NavSatFix"] = """std_msgs/Header header
sensor_msgs/NavSatStatus status
float64 latitude
float64 longitude
float64 altitude
float64[9] position_covariance
uint8 COVARIANCE_TYPE_UNKNOWN = 0
uint8 COVARIANCE_TYPE_APPROXIMATED = 1
uint8 COVARIANCE_TYPE_DIAGONAL_KNOWN = 2
uint8 COVARIANCE_TYPE_KNOWN = 3
uint8 position_covariance_type
""" + _HEADER + """================================================================================
MSG: sensor_msgs/NavSatStatus
int8 STATUS_NO_FIX =  -1
int8 STATUS_FIX =      0
int8 STATUS_SBAS_FIX = 1
int8 STATUS_GBAS_FIX = 2
int8 status
uint16 SERVICE_GPS =     1
uint16 SERVICE_GLONASS = 2
uint16 SERVICE_COMPASS = 4
uint16 SERVICE_GALILEO = 8
uint16 service
"""
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
ATTITUDE_TYPES = ("sensor_msgs/msg/Imu", "geometry_msgs/msg/PoseStamped",
                  "geometry_msgs/msg/QuaternionStamped", "novatel_oem7_msgs/msg/INSPVA")

#: Number of parameters of the term magalign reports for each effect (for the threshold).
K_PARAMS = {"hard_iron": 3, "soft_iron": 5, "time_offset": 1, "eddy_current": 9,
            "field_drift": 12, "disturbance": 15, "hard_iron_step": 3, "field_gradient": 6,
            "heading_drift": 2, "sample_hold": 1, "local_source": 6, "lever_arm": 3,
            "field_map": 27}

#: Paths (``Spec.path``) and position sources (``Spec.position_type``).
PATHS = ("lissajous", "survey", "translate", "handheld")
POSITION_TYPES = ("pose", "inspva", "navsatfix")

#: mu0 / 4 pi in nT m / A: the dipole field is ``MU0_4PI_NT * (3 (m.u) u - m) / r^3`` with m
#: in A m^2 and r in m (1e-7 T m / A = 100 nT m / A).
MU0_4PI_NT = 100.0
#: WGS-84 semi-major axis (m) and flattening.
WGS84_A = 6_378_137.0
WGS84_F = 1.0 / 298.257223563

_SURVEY_ACCEL_S = 3.0  # from rest to walking speed at the start of the first line

T0_NS = 1_767_225_600_000_000_000  # 2026-01-01T00:00:00Z


# ----------------------------------------------------------------------------- specification


@dataclass
class Spec:
    """One recording.

    Attributes
    ----------
    name : str
    seed : int
    duration_s : float
    mag_rate_hz, att_rate_hz : float
        Message rates of the two streams.
    att_phase_s : float
        Delay of the first attitude sample after the first magnetometer sample.
    att_jitter_s : float
        Standard deviation of the attitude sampling instants about the nominal grid (the
        stamps are the true instants).
    att_type : str
        One of :data:`ATTITUDE_TYPES`.
    motion : str
        ``multi`` (yaw turn plus swings about all three axes) or ``single`` (variable-rate
        turn about Up only).
    freqs_hz : tuple of float
        Swing frequencies of yaw, pitch, roll (0.05-2 Hz).
    amps_deg : tuple of float
        Swing amplitudes of yaw, pitch, roll.
    yaw_rate_deg_s : float
        Steady turn rate about Up.
    vib_deg, vib_hz : float
        Vibration amplitude (all three axes) and frequency.
    att_noise_deg, mag_noise_nT : float
        White noise of the attitude (each axis) and of the magnetometer (each component).
    B_enu_nT : tuple
    rotvec_body_mag_deg : tuple
    effects : dict
        Effect name -> parameters (see :func:`effect_params`).
    positions : bool
        Write positions (PoseStamped; INSPVA / NavSatFix with ``position_type``).
    path : str
        One of :data:`PATHS`. ``lissajous``: the tracked point on a Lissajous figure
        (+-0.2-0.4 m) with the attitude of ``motion``. ``survey``: parallel lines along north
        (``survey_*``), the heading along the track (body frame x right, y forward, z up), and
        swings of ``swing_deg`` at ``freqs_hz``. ``translate``: +-``translate_amp_m`` in each
        ENU axis at 0.1-0.3 Hz, a fixed heading and swings of ``swing_deg`` at ``freqs_hz``.
        ``handheld``: the tracked point wanders through the box ``handheld_box_m``
        (:func:`position_m`) with the attitude of ``lissajous`` (``motion``, ``amps_deg``,
        ``yaw_rate_deg_s``). ``motion`` and ``amps_deg`` / ``yaw_rate_deg_s`` belong to
        ``lissajous`` and ``handheld`` only.
    swing_deg : tuple of float
        Yaw, pitch, roll swing amplitudes of ``survey`` and ``translate``, deg.
    survey_line_m, survey_spacing_m, survey_speed_m_s, survey_height_m : float
        Line length (m, along north), spacing between lines (m, eastwards), walking speed
        (m/s) and the constant height of the tracked point (m, ENU up).
    survey_calibration_s : float
        Length of the calibration manoeuvre before the walk (0: none): standing on the
        first line's start, a roll and a pitch (``survey_calibration_tilt_deg``) at each of
        the headings north, east, south, west, each followed by a quarter turn clockwise.
    survey_calibration_tilt_deg : tuple of float
        Roll and pitch amplitudes of the calibration manoeuvre, deg (default +-10 and +-5).
    translate_amp_m : float
        Amplitude of each ENU axis of the ``translate`` path, m.
    position_type : str
        One of :data:`POSITION_TYPES`: ``pose`` (PoseStamped local metres, the default),
        ``inspva`` (INSPVA latitude / longitude / height: ``att_type`` must be INSPVA) or
        ``navsatfix`` (a ``/gps/fix`` NavSatFix channel at ``fix_rate_hz``; ``att_type`` must
        be Imu or QuaternionStamped).
    geo_origin : tuple of float
        Latitude (deg), longitude (deg), ellipsoidal height (m, WGS-84) of the ENU origin of
        the geodetic position types.
    fix_rate_hz : float
        Rate of the NavSatFix channel.
    position_frame_yaw_deg : float
        PoseStamped positions are written in a frame rotated about Up by this angle from ENU
        (a motion-capture room): ``p_written = Rz(yaw).T @ p_enu``. ``pose`` only.
    handheld_box_m : tuple of 3 (low, high)
        ENU extent (m) of the ``handheld`` path per axis: it reaches near each face and
        stays inside.

    """

    name: str
    seed: int
    duration_s: float = 60.0
    mag_rate_hz: float = 100.0
    att_rate_hz: float = 100.0
    att_phase_s: float = 0.0
    att_jitter_s: float = 0.0
    att_type: str = "geometry_msgs/msg/PoseStamped"
    motion: str = "multi"
    freqs_hz: tuple = (0.07, 0.15, 0.11)
    amps_deg: tuple = (30.0, 25.0, 25.0)
    yaw_rate_deg_s: float = 8.0
    vib_deg: float = 0.0
    vib_hz: float = 5.0
    att_noise_deg: float = 0.005
    mag_noise_nT: float = 1.0
    B_enu_nT: tuple = (800.0, 20000.0, -44000.0)
    rotvec_body_mag_deg: tuple = (1.0, -1.5, 2.0)
    effects: dict = field(default_factory=dict)
    positions: bool = True
    path: str = "lissajous"
    swing_deg: tuple = (1.0, 2.0, 3.0)
    survey_line_m: float = 30.0
    survey_spacing_m: float = 2.0
    survey_speed_m_s: float = 1.5
    survey_height_m: float = 1.0
    survey_calibration_s: float = 0.0
    survey_calibration_tilt_deg: tuple = (10.0, 5.0)
    translate_amp_m: float = 0.5
    position_type: str = "pose"
    geo_origin: tuple = (52.5, 13.3, 40.0)
    fix_rate_hz: float = 10.0
    position_frame_yaw_deg: float = 0.0
    handheld_box_m: tuple = ((0.0, 2.0), (0.0, 2.0), (0.3, 1.0))


#: Spec fields added after the first corpora: left out of a key file while at their
#: defaults, so that the key of a recording without them stays as it was.
_NEW_FIELDS = ("path", "swing_deg", "survey_line_m", "survey_spacing_m", "survey_speed_m_s",
               "survey_height_m", "survey_calibration_s", "translate_amp_m", "position_type",
               "geo_origin", "fix_rate_hz", "position_frame_yaw_deg", "handheld_box_m",
               "survey_calibration_tilt_deg")


def check_spec(spec: Spec) -> None:
    """Raise ``ValueError`` for a combination of options the generator cannot write."""
    if spec.path not in PATHS:
        raise ValueError(f"path {spec.path!r}: not one of {PATHS}")
    if spec.position_type not in POSITION_TYPES:
        raise ValueError(f"position_type {spec.position_type!r}: not one of {POSITION_TYPES}")
    if spec.position_type == "inspva" and spec.att_type != "novatel_oem7_msgs/msg/INSPVA":
        raise ValueError("position_type inspva needs att_type novatel_oem7_msgs/msg/INSPVA")
    if spec.position_type == "navsatfix" and spec.att_type not in (
            "sensor_msgs/msg/Imu", "geometry_msgs/msg/QuaternionStamped"):
        # a PoseStamped beside the fixes would carry a position that means nothing
        raise ValueError("position_type navsatfix needs att_type sensor_msgs/msg/Imu or "
                         "geometry_msgs/msg/QuaternionStamped")
    if spec.position_frame_yaw_deg != 0.0 and spec.position_type != "pose":
        raise ValueError("position_frame_yaw_deg applies to position_type pose only")
    if spec.path == "survey" and _SURVEY_ACCEL_S * spec.survey_speed_m_s / 2 >= \
            spec.survey_line_m:
        raise ValueError("survey_line_m too short for the start from rest")


# ----------------------------------------------------------------------------- physics


def _angles(spec: Spec, t_s: np.ndarray) -> np.ndarray:
    """Yaw, pitch, roll (rad) of the true attitude at ``t_s``, (N, 3)."""
    if spec.path not in ("lissajous", "handheld"):
        return _path_angles(spec, t_s)
    f = np.asarray(spec.freqs_hz, dtype=float)
    a = np.radians(spec.amps_deg)
    ph = np.random.default_rng(spec.seed + 1).uniform(0, 2 * np.pi, 6)
    t = np.asarray(t_s, dtype=float)
    yaw = np.radians(spec.yaw_rate_deg_s) * t + a[0] * np.sin(2 * np.pi * f[0] * t + ph[0])
    if spec.motion == "single":
        pitch = roll = np.zeros_like(t)
    else:
        pitch = a[1] * np.sin(2 * np.pi * f[1] * t + ph[1])
        roll = a[2] * np.sin(2 * np.pi * f[2] * t + ph[2])
    out = np.stack([yaw, pitch, roll], axis=-1)
    if spec.vib_deg > 0:
        v = np.radians(spec.vib_deg)
        out += v * np.sin(2 * np.pi * spec.vib_hz * t[:, None] + ph[3:6])
        if spec.motion == "single":
            out[:, 1:] = 0.0
    return out


def _smoothstep(u: np.ndarray) -> np.ndarray:
    """``u - sin(2 pi u) / (2 pi)`` on [0, 1], 0 below, 1 above.

    First and second derivatives vanish at both ends: joined to constants it is C2, so a
    turn or a start built from it has no step in angular rate or acceleration.
    """
    u = np.clip(u, 0.0, 1.0)
    return u - np.sin(2 * np.pi * u) / (2 * np.pi)


def _survey_track(spec: Spec, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position (ENU m), velocity (ENU m/s) and track yaw (rad) of the survey, closed form.

    Timeline (``Tc = survey_calibration_s``): at rest at (0, 0, height) until ``Tc`` (the
    calibration turns happen there); from rest to ``v`` along north in 3 s (speed
    ``v * _smoothstep``); then lines of ``survey_line_m`` joined by turns of duration ``T =
    8 s / (3 v)`` (``s`` the spacing) in which, with ``u = tau / T``,

        v_east  = v sin^4(pi u)                       (area 3/8 v T = s)
        v_north = +-v (1 - 2 u + sin(2 pi u) / pi)    (+-v at the ends, returns to the line end)

    Both components are C2 at the joins (value, first and second derivatives match a
    straight line), so position is C3 and the track heading ``atan2`` of the velocity C2;
    the speed stays within 0.8-1 v. Lines alternate north / south, stepping east. The yaw is
    that of the forward (y) body axis: 0 north, -pi south (it stays in [-pi, 0], no wrap).
    """
    t = np.asarray(t_s, dtype=float)
    v, L, s = spec.survey_speed_m_s, spec.survey_line_m, spec.survey_spacing_m
    Ta = _SURVEY_ACCEL_S
    Tt = 8.0 * s / (3.0 * v)
    d_acc = v * Ta / 2.0
    T1 = (L - d_acc) / v  # rest of the first line at full speed
    Tcyc = Tt + L / v
    tau = t - max(spec.survey_calibration_s, 0.0)
    x, y = np.zeros_like(t), np.zeros_like(t)
    vx, vy = np.zeros_like(t), np.zeros_like(t)
    m = (tau >= 0) & (tau < Ta)
    u = tau[m] / Ta
    y[m] = v * Ta * (u**2 / 2 + (np.cos(2 * np.pi * u) - 1) / (4 * np.pi**2))
    vy[m] = v * _smoothstep(u)
    m = (tau >= Ta) & (tau < Ta + T1)
    y[m] = d_acc + v * (tau[m] - Ta)
    vy[m] = v
    r = tau - Ta - T1
    on = r >= 0
    k = np.floor(r[on] / Tcyc)
    rr = r[on] - k * Tcyc
    d = np.where(k % 2 == 0, 1.0, -1.0)  # direction of the line that ends at this turn
    y_end = np.where(k % 2 == 0, L, 0.0)
    x0 = k * s
    turn = rr < Tt
    u = rr / Tt
    xs = np.where(turn, x0 + 8.0 * s / 3.0 * (3 * u / 8 - np.sin(2 * np.pi * u) / (4 * np.pi)
                                            + np.sin(4 * np.pi * u) / (32 * np.pi)), x0 + s)
    ys = np.where(turn, y_end + d * v * Tt * (u - u**2 + (1 - np.cos(2 * np.pi * u))
                                              / (2 * np.pi**2)),
                  y_end - d * v * (rr - Tt))
    vxs = np.where(turn, v * np.sin(np.pi * u) ** 4, 0.0)
    vys = np.where(turn, d * v * (1 - 2 * u + np.sin(2 * np.pi * u) / np.pi), -d * v)
    x[on], y[on], vx[on], vy[on] = xs, ys, vxs, vys
    # before and during the start the track is north (yaw 0); atan2 is undefined at rest
    yaw = np.where(tau < Ta, 0.0, np.arctan2(vy, vx) - np.pi / 2)
    pos = np.stack([x, y, np.full_like(t, spec.survey_height_m)], axis=-1)
    vel = np.stack([vx, vy, np.zeros_like(t)], axis=-1)
    return pos, vel, yaw


def _survey_calibration(spec: Spec, t_s: np.ndarray) -> np.ndarray:
    """Yaw, pitch, roll (rad) added by the calibration manoeuvre at the survey's start.

    Four segments of ``Tc / 4``: roll ``a sin^3`` over the first 30 % (+a then -a), pitch
    ``b sin^3`` over the next 30 % (``a``, ``b``: ``survey_calibration_tilt_deg``), a
    clockwise quarter turn (yaw ``-pi/2 * _smoothstep``) over the last 40 %. ``sin^3`` and
    the smoothstep have zero first and second derivatives at their ends: the manoeuvre is C2
    in angle. After it the yaw is
    -2 pi (north again), so the walk continues without a jump.
    """
    t = np.asarray(t_s, dtype=float)
    out = np.zeros((len(t), 3))
    Tc = spec.survey_calibration_s
    if Tc <= 0:
        return out
    Ts = Tc / 4.0
    inside = (t >= 0) & (t < Tc)
    k = np.clip(np.floor(t / Ts), 0, 3)
    tau = t - k * Ts
    u_roll = tau / (0.3 * Ts)
    u_pitch = (tau - 0.3 * Ts) / (0.3 * Ts)
    u_turn = (tau - 0.6 * Ts) / (0.4 * Ts)
    roll = np.where((u_roll >= 0) & (u_roll < 1), np.sin(2 * np.pi * u_roll) ** 3, 0.0)
    pitch = np.where((u_pitch >= 0) & (u_pitch < 1), np.sin(2 * np.pi * u_pitch) ** 3, 0.0)
    out[:, 0] = np.where(inside, -np.pi / 2 * (k + _smoothstep(u_turn)),
                         np.where(t >= Tc, -2 * np.pi, 0.0))
    roll_deg, pitch_deg = spec.survey_calibration_tilt_deg
    out[:, 1] = np.where(inside, np.radians(pitch_deg) * pitch, 0.0)
    out[:, 2] = np.where(inside, np.radians(roll_deg) * roll, 0.0)
    return out


def _path_angles(spec: Spec, t_s: np.ndarray) -> np.ndarray:
    """Yaw, pitch, roll (rad) of the ``survey`` and ``translate`` paths, (N, 3).

    A base heading (the survey's track plus its calibration manoeuvre; a fixed heading drawn
    from the seed for ``translate``) plus swings of ``swing_deg`` at ``freqs_hz`` with the
    phases of the ``lissajous`` swings, and the vibration of ``vib_deg``.
    """
    t = np.asarray(t_s, dtype=float)
    f = np.asarray(spec.freqs_hz, dtype=float)
    a = np.radians(spec.swing_deg)
    ph = np.random.default_rng(spec.seed + 1).uniform(0, 2 * np.pi, 6)
    out = a * np.sin(2 * np.pi * f * t[:, None] + ph[:3])
    if spec.path == "survey":
        out[:, 0] += _survey_track(spec, t)[2]
        out += _survey_calibration(spec, t)
    else:
        out[:, 0] += np.random.default_rng(spec.seed + 5).uniform(-np.pi, np.pi)
    if spec.vib_deg > 0:
        out += np.radians(spec.vib_deg) * np.sin(2 * np.pi * spec.vib_hz * t[:, None] + ph[3:6])
    return out


def true_attitude(spec: Spec, t_s: np.ndarray) -> Rotation:
    """``C_enu_body`` at ``t_s``: ``Rz(yaw) Rx(pitch) Ry(roll)`` (CONVENTIONS Euler order)."""
    return Rotation.from_euler("ZXY", _angles(spec, t_s))


def heading_error_rad(spec: Spec, t_s: np.ndarray) -> np.ndarray:
    """Heading error ``h(t)`` of the attitude source (``heading_drift``), rad."""
    p = spec.effects.get("heading_drift")
    if p is None:
        return np.zeros(np.shape(t_s))
    t = np.asarray(t_s, dtype=float)
    return np.radians(p["rate_deg_per_h"] / 3600.0 * t + p.get("quad_deg_per_h2", 0.0)
                      / 3600.0**2 * t**2)


def position_m(spec: Spec, t_s: np.ndarray) -> np.ndarray:
    """Position of the tracked point (what the position source reports), ENU m, (N, 3).

    ``lissajous``: a Lissajous path that revisits places; ``survey``: see
    :func:`_survey_track`; ``translate``: +-``translate_amp_m`` about (1, 2, 1.2) m at 0.1-0.3
    Hz per axis; ``handheld``: per axis ``c + h (0.6 sin(2 pi f1 t + a) + 0.4 sin(2 pi f2 t +
    b))`` with ``c``, ``h`` the centre and half width of ``handheld_box_m``, ``f1`` 0.03-0.07
    Hz and ``f2`` 0.1-0.2 Hz drawn per axis from the seed: smooth (under 0.8 m/s along each
    axis of a 2 m box), inside the box, and crossing its own track again and again (incommensurate
    frequencies). Without ``lever_arm`` it is also the magnetometer's position.
    """
    if spec.path == "handheld":
        rng = np.random.default_rng(spec.seed + 2)
        f1, f2 = rng.uniform(0.03, 0.07, 3), rng.uniform(0.1, 0.2, 3)
        a, b = rng.uniform(0, 2 * np.pi, 3), rng.uniform(0, 2 * np.pi, 3)
        box = np.asarray(spec.handheld_box_m, dtype=float)
        c, h = box.mean(axis=1), 0.5 * (box[:, 1] - box[:, 0])
        t = np.asarray(t_s, dtype=float)[:, None]
        return c + h * (0.6 * np.sin(2 * np.pi * f1 * t + a)
                        + 0.4 * np.sin(2 * np.pi * f2 * t + b))
    if spec.path == "survey":
        return _survey_track(spec, t_s)[0]
    if spec.path == "translate":
        rng = np.random.default_rng(spec.seed + 2)
        f = rng.uniform(0.1, 0.3, 3)
        ph = rng.uniform(0, 2 * np.pi, 3)
        t = np.asarray(t_s, dtype=float)[:, None]
        return np.array([1.0, 2.0, 1.2]) + spec.translate_amp_m * np.sin(2 * np.pi * f * t + ph)
    rng = np.random.default_rng(spec.seed + 2)
    amp = rng.uniform(0.2, 0.4, 3)
    per = rng.uniform(5.0, 13.0, 3)
    ph = rng.uniform(0, 2 * np.pi, 3)
    t = np.asarray(t_s, dtype=float)[:, None]
    return np.array([1.0, 2.0, 1.2]) + amp * np.sin(2 * np.pi * t / per + ph)


def velocity_m_s(spec: Spec, t_s: np.ndarray) -> np.ndarray:
    """Velocity of the tracked point, ENU m/s, (N, 3) (central difference, step 1 ms).

    The paths are analytic; the truncation error is below 1e-6 m/s for these motions.
    """
    t = np.asarray(t_s, dtype=float)
    h = 1e-3
    return (position_m(spec, t + h) - position_m(spec, t - h)) / (2 * h)


def sensor_position_m(spec: Spec, t_s: np.ndarray) -> np.ndarray:
    """Position of the magnetometer, ENU m, (N, 3): ``p(t) + C_true(t) @ lever_arm_body_m``.

    The true attitude (not the reported one, which carries the heading drift and noise)
    carries the lever arm: the sensor is where it is, whatever the INS says.
    """
    p = position_m(spec, t_s)
    la = spec.effects.get("lever_arm")
    if la is None:
        return p
    return p + true_attitude(spec, t_s).apply(np.asarray(la["lever_arm_body_m"], float))


def dipole_field_nT(moment_Am2: np.ndarray, r_vec_m: np.ndarray) -> np.ndarray:
    """Field of a point dipole, nT: ``100 nT * (3 (m.u) u - m) / r^3``.

    Parameters
    ----------
    moment_Am2 : array_like, shape (3,) or (N, 3)
        Dipole moment ``m``, A m^2, in the frame of ``r_vec_m`` (ENU here).
    r_vec_m : array_like, shape (3,) or (N, 3)
        Vector from the dipole to the point of evaluation, m (``r > 0``).

    Returns
    -------
    ndarray, shape (N, 3) (or (3,) when both inputs are single vectors)
        The field in the same frame, nT (``mu0 / 4 pi = 1e-7 T m / A = 100 nT m / A``).

    """
    m = np.asarray(moment_Am2, dtype=float)
    r = np.asarray(r_vec_m, dtype=float)
    rn = np.linalg.norm(r, axis=-1, keepdims=True)
    u = r / rn
    mu = np.sum(m * u, axis=-1, keepdims=True)
    return MU0_4PI_NT * (3.0 * mu * u - m) / rn**3


def source_presence(params: dict[str, Any], t_s: np.ndarray) -> np.ndarray:
    """Presence (0-1) of the ``local_source`` at times ``t_s`` (s from the first mag sample).

    Inside a window ``[a, b)`` of ``windows_s`` it is 1, outside 0 (half-open windows, as in
    CONVENTIONS); with ``ramp_s`` it rises and falls as a raised cosine over ``ramp_s`` inside
    each window's edges (no step in the field). Without ``windows_s`` it is present always.
    """
    t = np.asarray(t_s, dtype=float)
    win = params.get("windows_s")
    if win is None:
        return np.ones_like(t)
    ramp = float(params.get("ramp_s", 0.0))
    out = np.zeros_like(t)
    for a, b in win:
        inside = (t >= a) & (t < b)
        if ramp > 0:
            x = np.clip(np.minimum(t - a, b - t) / min(ramp, (b - a) / 2), 0.0, 1.0)
            w = 0.5 - 0.5 * np.cos(np.pi * x)
        else:
            w = np.ones_like(t)
        out = np.maximum(out, np.where(inside, w, 0.0))
    return out


def source_field_nT(spec: Spec, t_s: np.ndarray) -> np.ndarray:
    """Field of the ``local_source`` at the magnetometer, ENU nT, at sensing times, (N, 3)."""
    p = spec.effects["local_source"]
    t = np.asarray(t_s, dtype=float)
    r = sensor_position_m(spec, t) - np.asarray(p["position_m"], float)
    return source_presence(p, t)[:, None] * dipole_field_nT(np.asarray(p["moment_Am2"], float),
                                                            r)


def dipole_potential_nTm(moment_Am2: np.ndarray, r_vec_m: np.ndarray) -> np.ndarray:
    """Scalar potential of a point dipole, nT m: ``100 nT (m.r) / r^3``, (N,).

    Its field is minus its gradient (:func:`dipole_field_nT`): the magnetic scalar
    potential ``(m.r) / (4 pi r^3)`` times ``mu0``.
    """
    m = np.asarray(moment_Am2, dtype=float)
    r = np.asarray(r_vec_m, dtype=float)
    rn = np.linalg.norm(r, axis=-1)
    return MU0_4PI_NT * np.sum(m * r, axis=-1) / rn**3


def smooth_field_at(params: dict[str, Any], x_enu_m: np.ndarray) -> np.ndarray:
    """Field of the ``field_map`` effect at ENU points ``x_enu_m`` (N, 3), nT, (N, 3).

    ``params["dipoles"]``: a list of ``{position_m (ENU), moment_Am2}``, placed far from the
    path (metres to tens of metres), so that their sum is smooth over the area the sensor
    covers and far from linear across it.
    """
    x = np.asarray(x_enu_m, dtype=float).reshape(-1, 3)
    B = np.zeros_like(x)
    for d in params["dipoles"]:
        B += dipole_field_nT(np.asarray(d["moment_Am2"], float),
                             x - np.asarray(d["position_m"], float))
    return B


def smooth_potential_at(params: dict[str, Any], x_enu_m: np.ndarray) -> np.ndarray:
    """Potential of the ``field_map`` effect at ``x_enu_m`` (N, 3), nT m: the field is ``-grad``."""
    x = np.asarray(x_enu_m, dtype=float).reshape(-1, 3)
    return sum((dipole_potential_nTm(np.asarray(d["moment_Am2"], float),
                                     x - np.asarray(d["position_m"], float))
                for d in params["dipoles"]), np.zeros(len(x)))


def field_enu(spec: Spec, t_s: np.ndarray) -> np.ndarray:
    """Field at the sensor, ENU nT, at sensing times ``t_s`` (N, 3).

    Spatial terms are evaluated at the magnetometer (:func:`sensor_position_m`); the
    gradient's reference point is the mean of the tracked point over the recording.
    """
    t = np.asarray(t_s, dtype=float)
    B = np.broadcast_to(np.asarray(spec.B_enu_nT, float), (len(t), 3)).copy()
    e = spec.effects
    if "field_drift" in e:
        p = e["field_drift"]
        B += np.asarray(p["amp_nT"])[None, :] * np.sin(
            2 * np.pi * t[:, None] / p["period_s"] + np.asarray(p["phase_rad"])[None, :])
    if "disturbance" in e:
        p = e["disturbance"]
        (a, b), = p["windows_s"]
        x = np.clip((t - a) / (b - a), 0.0, 1.0)
        B += p["peak_nT"] * np.sin(np.pi * x)[:, None] ** 2 * np.asarray(p["direction_enu"])
    if "field_gradient" in e:
        pos = sensor_position_m(spec, t)
        ref = position_m(spec, np.linspace(0, spec.duration_s, 4001)).mean(axis=0)
        B += (pos - ref) @ np.asarray(e["field_gradient"]["G_nT_per_m"]).T
    if "local_source" in e:
        B += source_field_nT(spec, t)
    if "field_map" in e:
        B += smooth_field_at(e["field_map"], sensor_position_m(spec, t))
    return B


def _y0(spec: Spec, t_sense: np.ndarray) -> np.ndarray:
    """Undisturbed reading ``D R.T C.T B`` at sensing times, mag frame nT (N, 3)."""
    R = Rotation.from_rotvec(np.radians(spec.rotvec_body_mag_deg))
    b = true_attitude(spec, t_sense).inv().apply(field_enu(spec, t_sense))
    m = R.inv().apply(b)
    D = np.asarray(spec.effects.get("soft_iron", {}).get("D", np.eye(3)))
    return m @ D.T


def clean_readings(spec: Spec, t_s: np.ndarray) -> np.ndarray:
    """Noise-free magnetometer readings at stamps ``t_s`` (s from the first sample)."""
    e = spec.effects
    tau = e.get("time_offset", {}).get("time_offset_s", 0.0)
    ts = np.asarray(t_s, dtype=float) - tau
    y = _y0(spec, ts)
    if "eddy_current" in e:
        h = 1e-4
        ydot = (_y0(spec, ts + h) - _y0(spec, ts - h)) / (2 * h)
        y = y + ydot @ np.asarray(e["eddy_current"]["E_s"]).T
    if "hard_iron" in e:
        y = y + np.asarray(e["hard_iron"]["offset_nT"])
    if "hard_iron_step" in e:
        p = e["hard_iron_step"]
        (a, b), = p["windows_s"]
        if "moment_Am2" in p:
            y = y + magnet_carried_nT(ts, p)
        else:
            y = y + ((ts >= a) & (ts < b))[:, None] * np.asarray(p["offset_nT"])
    return y


def magnet_carried_nT(t_s: np.ndarray, p: dict) -> np.ndarray:
    """Field of a magnet carried onto the platform, left there and carried away, mag frame.

    A point dipole of ``moment_Am2`` (mag frame) rests at ``rest_m`` (mag frame, from the
    sensor) inside ``windows_s``. Over ``carry_s`` before the window opens it comes in from
    far away along ``carry_dir_m`` (mag frame, m), at ``rest + carry_dir (1 / s(u) - 1)``
    with ``s`` a smoothstep of the time ``u`` into the carry, and over ``carry_s`` after the
    window it leaves the same way: its field turns as well as grows, and it falls to zero
    smoothly far away (no jump in the field at any time). The field at the sensor is
    ``100 nT (3 (m.u) u - m) / r^3`` (m in A m^2, r in m, u from the magnet to the sensor),
    written here without magalign's code.
    """
    (a, b), = p["windows_s"]
    T = float(p["carry_s"])
    rest = np.asarray(p["rest_m"], dtype=float)
    m = np.asarray(p["moment_Am2"], dtype=float)
    lateral = np.asarray(p["carry_dir_m"], dtype=float)
    sig = np.zeros(len(t_s))
    sig[(t_s >= a) & (t_s < b)] = 1.0
    on = (t_s >= a - T) & (t_s < a)
    sig[on] = _smoothstep((t_s[on] - (a - T)) / T)
    off = (t_s >= b) & (t_s < b + T)
    sig[off] = 1.0 - _smoothstep((t_s[off] - b) / T)
    out = np.zeros((len(t_s), 3))
    near = sig > 1e-6
    pos = rest[None, :] + lateral[None, :] * (1.0 / sig[near] - 1.0)[:, None]
    r = np.linalg.norm(pos, axis=1)
    u = -pos / r[:, None]
    out[near] = 100.0 * (3.0 * (u @ m)[:, None] * u - m[None, :]) / r[:, None] ** 3
    return out


def mag_stamps_s(spec: Spec) -> np.ndarray:
    """Magnetometer stamps, s from the first sample."""
    return np.arange(0.0, spec.duration_s, 1.0 / spec.mag_rate_hz)


def att_stamps_s(spec: Spec) -> np.ndarray:
    """Attitude sampling instants (= stamps), s: rate, phase and jitter of the spec."""
    rng = np.random.default_rng(spec.seed + 3)
    t = np.arange(spec.att_phase_s - 1.0 / spec.att_rate_hz,
                  spec.duration_s + 2.0 / spec.att_rate_hz, 1.0 / spec.att_rate_hz)
    if spec.att_jitter_s > 0:
        t = t + np.clip(rng.normal(0, spec.att_jitter_s, len(t)), -0.3 / spec.att_rate_hz,
                        0.3 / spec.att_rate_hz)
    return t


def fix_stamps_s(spec: Spec) -> np.ndarray:
    """NavSatFix stamps, s from the first magnetometer sample (``fix_rate_hz``)."""
    return np.arange(0.0, spec.duration_s, 1.0 / spec.fix_rate_hz)


def readings(spec: Spec) -> dict[str, Any]:
    """Everything written: stamps (s), readings (nT), reported attitude, positions.

    Keys ``t_mag_s``, ``mag_nT``, ``t_att_s``, ``att`` (reported ``C_enu_body``), ``pos_m``
    (tracked point at the attitude stamps, ENU m); with ``position_type`` ``navsatfix`` also
    ``t_fix_s`` and ``fix_pos_m`` (tracked point at the fix stamps, ENU m).
    """
    check_spec(spec)
    rng = np.random.default_rng(spec.seed)
    tm = mag_stamps_s(spec)
    y = clean_readings(spec, tm)
    if "sample_hold" in spec.effects:
        # the sensor converts at its native rate; each message repeats the last conversion
        nat = spec.effects["sample_hold"]["native_rate_hz"]
        tc = np.arange(-1.0 / nat, spec.duration_s + 1.0 / nat, 1.0 / nat)
        yc = clean_readings(spec, tc)
        y = yc[np.searchsorted(tc, tm, side="right") - 1]
        y = y + rng.normal(0, spec.mag_noise_nT, (len(tc), 3))[
            np.searchsorted(tc, tm, side="right") - 1]
    else:
        y = y + rng.normal(0, spec.mag_noise_nT, y.shape)
    ta = att_stamps_s(spec)
    C = true_attitude(spec, ta)
    rep = Rotation.from_rotvec(np.stack([0 * ta, 0 * ta, heading_error_rad(spec, ta)], -1)) * C
    if spec.att_noise_deg > 0:
        rep = rep * Rotation.from_rotvec(rng.normal(0, np.radians(spec.att_noise_deg),
                                                    (len(ta), 3)))
    out: dict[str, Any] = {"t_mag_s": tm, "mag_nT": y, "t_att_s": ta, "att": rep,
                           "pos_m": position_m(spec, ta)}
    if spec.position_type == "navsatfix":
        tf = fix_stamps_s(spec)
        out["t_fix_s"] = tf
        out["fix_pos_m"] = position_m(spec, tf)
    return out


# ----------------------------------------------------------------------------- geodesy


def wgs84_radii_m(lat_deg: float) -> tuple[float, float]:
    """Prime-vertical ``N`` and meridian ``M`` radii of curvature of WGS-84 at ``lat_deg``, m."""
    e2 = WGS84_F * (2.0 - WGS84_F)
    s2 = np.sin(np.radians(lat_deg)) ** 2
    N = WGS84_A / np.sqrt(1.0 - e2 * s2)
    M = WGS84_A * (1.0 - e2) / (1.0 - e2 * s2) ** 1.5
    return float(N), float(M)


def enu_to_geodetic(p_enu_m: np.ndarray, origin: tuple) -> np.ndarray:
    """ENU metres about ``origin`` to WGS-84 latitude (deg), longitude (deg), height (m).

    Flat earth on the tangent plane at ``origin = (lat_deg, lon_deg, height_m)``: north
    ``/ (M + h0)``, east ``/ ((N + h0) cos lat0)``, up added to the height. Within 100 m of
    the origin it departs from the exact conversion by under 1 mm (the Earth's curvature,
    ``d^2 / 2R``: 0.8 mm at 100 m, 3 mm at 200 m).

    Returns
    -------
    ndarray, shape (N, 3)

    """
    lat0, lon0, h0 = (float(x) for x in origin)
    N, M = wgs84_radii_m(lat0)
    p = np.asarray(p_enu_m, dtype=float).reshape(-1, 3)
    lat = lat0 + np.degrees(p[:, 1] / (M + h0))
    lon = lon0 + np.degrees(p[:, 0] / ((N + h0) * np.cos(np.radians(lat0))))
    return np.stack([lat, lon, h0 + p[:, 2]], axis=-1)


def geodetic_to_enu(llh: np.ndarray, origin: tuple) -> np.ndarray:
    """Inverse of :func:`enu_to_geodetic` (same flat earth), ENU m, (N, 3)."""
    lat0, lon0, h0 = (float(x) for x in origin)
    N, M = wgs84_radii_m(lat0)
    g = np.asarray(llh, dtype=float).reshape(-1, 3)
    return np.stack([np.radians(g[:, 1] - lon0) * (N + h0) * np.cos(np.radians(lat0)),
                     np.radians(g[:, 0] - lat0) * (M + h0), g[:, 2] - h0], axis=-1)


# ----------------------------------------------------------------------------- writing


def _stamp(t_ns: int) -> dict[str, int]:
    return {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}


def write_streams(path: Path, t_mag_s, mag_nT, t_att_s, att: Rotation, att_type: str,
                  pos_m: np.ndarray | None = None, *, mag_topic: str = "/imu/mag",
                  att_topic: str = "/attitude", geo: np.ndarray | None = None,
                  vel_enu: np.ndarray | None = None,
                  fix: tuple[np.ndarray, np.ndarray] | None = None,
                  fix_topic: str = "/gps/fix", chunk_size: int = 256 * 1024) -> Path:
    """Write a magnetometer and an attitude stream with the ``mcap_ros2`` writer.

    Stamps are ``T0 + t`` (ns); log time is the stamp plus 2 ms; the field is written in
    tesla (REP-145).

    Parameters
    ----------
    pos_m : ndarray, shape (N_att, 3), optional
        PoseStamped positions, m, in the frame they are to be written in.
    geo : ndarray, shape (N_att, 3), optional
        INSPVA latitude (deg), longitude (deg), height (m); without it the INSPVA carries a
        fixed position (52.5, 13.3, 40.0).
    vel_enu : ndarray, shape (N_att, 3), optional
        INSPVA east, north, up velocities, m/s (zero without).
    fix : (t_s, llh), optional
        A NavSatFix channel on ``fix_topic``: stamps (s) and latitude (deg), longitude (deg),
        ellipsoidal height (m), status STATUS_FIX with service GPS.

    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tm = T0_NS + np.round(np.asarray(t_mag_s) * 1e9).astype(np.int64)
    ta = T0_NS + np.round(np.asarray(t_att_s) * 1e9).astype(np.int64)
    q = att.as_quat()  # x, y, z, w
    msgs: list[tuple[int, int, dict]] = []  # (log ns, stream, message)
    for k in range(len(tm)):
        m = mag_nT[k] * 1e-9
        msgs.append((int(tm[k]) + 2_000_000, 0, {
            "header": {"stamp": _stamp(int(tm[k])), "frame_id": "mag"},
            "magnetic_field": {"x": float(m[0]), "y": float(m[1]), "z": float(m[2])},
            "magnetic_field_covariance": [0.0] * 9}))
    if att_type == "novatel_oem7_msgs/msg/INSPVA":
        # NovAtel: C = Rz(-azimuth) Rx(pitch) Ry(roll), azimuth clockwise from north
        zxy = att.as_euler("ZXY", degrees=True)
        az = np.mod(-zxy[:, 0], 360.0)
    for k in range(len(ta)):
        qq = {"x": float(q[k, 0]), "y": float(q[k, 1]), "z": float(q[k, 2]),
              "w": float(q[k, 3])}
        hdr = {"stamp": _stamp(int(ta[k])), "frame_id": "body"}
        if att_type == "sensor_msgs/msg/Imu":
            z3 = {"x": 0.0, "y": 0.0, "z": 0.0}
            msg = {"header": hdr, "orientation": qq, "orientation_covariance": [0.0] * 9,
                   "angular_velocity": z3, "angular_velocity_covariance": [-1.0] + [0.0] * 8,
                   "linear_acceleration": z3,
                   "linear_acceleration_covariance": [-1.0] + [0.0] * 8}
        elif att_type == "geometry_msgs/msg/PoseStamped":
            p = pos_m[k] if pos_m is not None else np.zeros(3)
            msg = {"header": hdr, "pose": {
                "position": {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])},
                "orientation": qq}}
        elif att_type == "geometry_msgs/msg/QuaternionStamped":
            msg = {"header": hdr, "quaternion": qq}
        elif att_type == "novatel_oem7_msgs/msg/INSPVA":
            msg = {"header": hdr,
                   "nov_header": {"message_name": "INSPVA", "message_id": 507,
                                  "message_type": 0, "sequence_number": k, "time_status": 180,
                                  "gps_week_number": 2400, "gps_week_milliseconds": 0},
                   "latitude": 52.5, "longitude": 13.3, "height": 40.0,
                   "north_velocity": 0.0, "east_velocity": 0.0, "up_velocity": 0.0,
                   "roll": float(zxy[k, 2]), "pitch": float(zxy[k, 1]),
                   "azimuth": float(az[k]), "status": {"status": 3}}
        else:
            raise ValueError(att_type)
        if att_type == "novatel_oem7_msgs/msg/INSPVA" and geo is not None:
            msg.update(latitude=float(geo[k, 0]), longitude=float(geo[k, 1]),
                       height=float(geo[k, 2]))
        if att_type == "novatel_oem7_msgs/msg/INSPVA" and vel_enu is not None:
            msg.update(east_velocity=float(vel_enu[k, 0]), north_velocity=float(vel_enu[k, 1]),
                       up_velocity=float(vel_enu[k, 2]))
        msgs.append((int(ta[k]) + 2_000_000, 1, msg))
    if fix is not None:
        tf = T0_NS + np.round(np.asarray(fix[0]) * 1e9).astype(np.int64)
        llh = np.asarray(fix[1], dtype=float)
        # 1 cm horizontal, 2 cm vertical: a nominal RTK covariance (the fixes are exact)
        cov = [1e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, 4e-4]
        for k in range(len(tf)):
            msgs.append((int(tf[k]) + 2_000_000, 2, {
                "header": {"stamp": _stamp(int(tf[k])), "frame_id": "gps"},
                "status": {"status": 0, "service": 1},
                "latitude": float(llh[k, 0]), "longitude": float(llh[k, 1]),
                "altitude": float(llh[k, 2]), "position_covariance": cov,
                "position_covariance_type": 2}))
    msgs.sort(key=lambda x: x[0])
    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=chunk_size)
        schemas = [w.register_msgdef("sensor_msgs/msg/MagneticField",
                                     MSGDEFS["sensor_msgs/msg/MagneticField"]),
                   w.register_msgdef(att_type, MSGDEFS[att_type])]
        topics: tuple[str, ...] = (mag_topic, att_topic)
        if fix is not None:
            schemas.append(w.register_msgdef(NAVSATFIX, MSGDEFS[NAVSATFIX]))
            topics = (mag_topic, att_topic, fix_topic)
        for i, (log, s, msg) in enumerate(msgs):
            w.write_message(topics[s], schemas[s], msg, log_time=log, publish_time=log,
                            sequence=i)
        w.finish()
    return path


def write(spec: Spec, path: Path, truth_path: Path | None = None,
          chunk_size: int = 256 * 1024) -> Path:
    """Make the recording of ``spec`` and write it.

    With ``truth_path``, :func:`truth` is written there as JSON too (keep it outside a folder
    a program under test reads, as the corpus key is). ``chunk_size``: the MCAP chunk size,
    bytes (small: many chunks, as a reader of ranges sees a long recording).
    """
    r = readings(spec)
    pos = r["pos_m"] if (spec.positions and spec.att_type == "geometry_msgs/msg/PoseStamped"
                         and spec.position_type == "pose") else None
    if pos is not None and spec.position_frame_yaw_deg != 0.0:
        pos = _frame_rotation(spec).inv().apply(pos)
    geo = vel = fix = None
    if spec.positions and spec.position_type == "inspva":
        geo = enu_to_geodetic(r["pos_m"], spec.geo_origin)
        vel = velocity_m_s(spec, r["t_att_s"])
    if spec.positions and spec.position_type == "navsatfix":
        fix = (r["t_fix_s"], enu_to_geodetic(r["fix_pos_m"], spec.geo_origin))
    out = write_streams(path, r["t_mag_s"], r["mag_nT"], r["t_att_s"], r["att"],
                        spec.att_type, pos, geo=geo, vel_enu=vel, fix=fix,
                        chunk_size=chunk_size)
    if truth_path is not None:
        tp = Path(truth_path)
        tp.parent.mkdir(parents=True, exist_ok=True)
        tp.write_text(json.dumps(truth(spec), indent=1))
    return out


# ----------------------------------------------------------------------------- truth


def _frame_rotation(spec: Spec) -> Rotation:
    """``Q``: written PoseStamped frame to ENU, ``p_enu = Q @ p_written`` (about Up)."""
    return Rotation.from_euler("z", spec.position_frame_yaw_deg, degrees=True)


def closest_approach(spec: Spec) -> tuple[float, float] | None:
    """Closest approach of the magnetometer to the ``local_source`` while it is present.

    Returns
    -------
    (distance_m, time_s) or None
        Distance (m) and true time (s on the clock of the stamps, 0 at the first
        magnetometer sample) within ``[0, duration_s)``; None without the effect or when the
        source is never present. A search on a 10 ms grid refined on a 0.1 ms grid.
    """
    p = spec.effects.get("local_source")
    if p is None:
        return None
    src = np.asarray(p["position_m"], float)

    def dist(t: np.ndarray) -> np.ndarray:
        d = np.linalg.norm(sensor_position_m(spec, t) - src, axis=1)
        return np.where(source_presence(p, t) > 0, d, np.inf)

    t = np.arange(0.0, spec.duration_s, 0.01)
    d = dist(t)
    if not np.isfinite(d).any():
        return None
    i = int(np.argmin(d))
    tf = np.arange(max(t[i] - 0.01, 0.0), min(t[i] + 0.01, spec.duration_s), 1e-4)
    df = dist(tf)
    j = int(np.argmin(df))
    return (float(df[j]), float(tf[j])) if df[j] < d[i] else (float(d[i]), float(t[i]))


def _llh_dict(g: np.ndarray | tuple) -> dict[str, float]:
    return {"lat_deg": float(g[0]), "lon_deg": float(g[1]), "height_m": float(g[2])}


def truth(spec: Spec) -> dict[str, Any]:
    """What went into the recording of ``spec`` beyond the spec itself, as JSON-ready values.

    Keys: ``format`` (``indep_gen.truth/1``); ``path``; ``position_type``;
    ``position_frame`` (``attitude_source_local`` for PoseStamped positions, ``enu`` for
    geodetic ones, None when no positions are written); ``position_frame_yaw_deg``;
    ``geo_origin`` (``{lat_deg, lon_deg, height_m}`` of the generator's ENU origin; None for
    local positions); ``position_origin`` (the first written position as ``{lat_deg,
    lon_deg, height_m}``: the origin CONVENTIONS gives a geodetic source; None otherwise);
    ``first_position_enu_m`` (that position in the generator's ENU, m); and ``effects``:

    - ``local_source``: the CONVENTIONS params ``position_m`` (in ``position_frame``, from
      ``position_origin`` for geodetic positions: what a correct diagnosis reports),
      ``position_frame``, ``position_origin``, ``moment_Am2`` (ENU), ``windows_s`` (None:
      always present), ``closest_approach_m`` / ``closest_approach_s`` (of the
      magnetometer, see :func:`closest_approach`); plus ``position_enu_m`` (the generator's
      ENU) and ``ramp_s``.
    - ``lever_arm``: ``lever_arm_body_m``.
    """
    pt = spec.position_type
    frame: str | None = None
    first: np.ndarray | None = None
    origin: dict[str, float] | None = None
    if spec.positions and pt == "pose" and spec.att_type == "geometry_msgs/msg/PoseStamped":
        frame = "attitude_source_local"
    elif spec.positions and pt in ("inspva", "navsatfix"):
        frame = "enu"
        t1 = att_stamps_s(spec)[:1] if pt == "inspva" else fix_stamps_s(spec)[:1]
        first = position_m(spec, t1)[0]
        origin = _llh_dict(enu_to_geodetic(first, spec.geo_origin)[0])
    geodetic = pt in ("inspva", "navsatfix")
    out: dict[str, Any] = {
        "format": "indep_gen.truth/1", "path": spec.path, "position_type": pt,
        "position_frame": frame, "position_frame_yaw_deg": float(spec.position_frame_yaw_deg),
        "geo_origin": _llh_dict(spec.geo_origin) if geodetic else None,
        "position_origin": origin,
        "first_position_enu_m": None if first is None else first.tolist(), "effects": {}}
    ls = spec.effects.get("local_source")
    if ls is not None:
        src = np.asarray(ls["position_m"], float)
        if frame == "attitude_source_local":
            pos = _frame_rotation(spec).inv().apply(src)
        elif frame == "enu" and first is not None:
            pos = src - first
        else:
            pos = src
        ca = closest_approach(spec)
        out["effects"]["local_source"] = {
            "position_m": pos.tolist(), "position_frame": frame, "position_origin": origin,
            "moment_Am2": [float(x) for x in ls["moment_Am2"]],
            "windows_s": None if ls.get("windows_s") is None
            else [[float(a), float(b)] for a, b in ls["windows_s"]],
            "closest_approach_m": None if ca is None else ca[0],
            "closest_approach_s": None if ca is None else ca[1],
            "position_enu_m": src.tolist(), "ramp_s": float(ls.get("ramp_s", 0.0))}
    la = spec.effects.get("lever_arm")
    if la is not None:
        out["effects"]["lever_arm"] = {
            "lever_arm_body_m": [float(x) for x in la["lever_arm_body_m"]]}
    fm = spec.effects.get("field_map")
    if fm is not None:
        # what the map adds at the magnetometer over the recording (ENU, nT); the linear part
        # of it (about the mean position) is the gradient's, the rest the map's
        t = mag_stamps_s(spec) - spec.effects.get("time_offset", {}).get("time_offset_s", 0.0)
        x = sensor_position_m(spec, t)
        f = smooth_field_at(fm, x)
        X = np.column_stack([np.ones(len(x)), x - x.mean(axis=0)])
        beyond = f - X @ np.linalg.lstsq(X, f, rcond=None)[0]
        out["effects"]["field_map"] = {
            "dipoles": [{"position_m": [float(v) for v in d["position_m"]],
                         "moment_Am2": [float(v) for v in d["moment_Am2"]]}
                        for d in fm["dipoles"]],
            "peak_to_peak_nT": (f.max(axis=0) - f.min(axis=0)).tolist(),
            "beyond_linear_rms_nT": float(np.sqrt(np.mean(beyond**2)))}
    return out


def _uses_new_options(s: Spec) -> bool:
    """Whether ``s`` uses an option added after the first corpora (it then gets a truth)."""
    defaults = Spec(name="", seed=0)
    return any(getattr(s, f) != getattr(defaults, f) for f in _NEW_FIELDS) or \
        "local_source" in s.effects or "lever_arm" in s.effects or "field_map" in s.effects


# ----------------------------------------------------------------------------- strength


def _baseline_prediction(spec: Spec, t_s: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """Baseline model (R, B only) at the reported noise-free attitude, perturbed by ``dx``."""
    R = Rotation.from_rotvec(dx[:3]) * Rotation.from_rotvec(np.radians(spec.rotvec_body_mag_deg))
    C = Rotation.from_rotvec(np.stack([0 * t_s, 0 * t_s, heading_error_rad(spec, t_s)], -1)) \
        * true_attitude(spec, t_s)
    B = np.asarray(spec.B_enu_nT, float) + dx[3:]
    return R.inv().apply(C.inv().apply(np.tile(B, (len(t_s), 1))))


def strength(spec: Spec, kind: str) -> float:
    """Amplitude of the effects of ``spec`` as a multiple of the detection threshold.

    See the module docstring; ``kind`` selects ``k`` (the reported term's parameter count).
    """
    t = mag_stamps_s(spec)
    base = replace(spec, effects={})
    y = readings(replace(spec, mag_noise_nT=0.0, att_noise_deg=0.0))["mag_nT"] \
        if "sample_hold" in spec.effects else clean_readings(spec, t)
    p0 = _baseline_prediction(spec if "heading_drift" in spec.effects else base, t, np.zeros(6))
    d = (y - p0).ravel()
    cols = []
    for i in range(6):
        h = 1e-6 if i < 3 else 1.0
        dx = np.zeros(6)
        dx[i] = h
        cols.append(((_baseline_prediction(base, t, dx) - _baseline_prediction(
            base, t, -dx)) / (2 * h)).ravel())
    J = np.stack(cols, axis=1)
    coef, *_ = np.linalg.lstsq(J, d, rcond=None)
    rem = d - J @ coef
    Bn = float(np.linalg.norm(spec.B_enu_nT))
    var = spec.mag_noise_nT**2 + (Bn * np.radians(spec.att_noise_deg)) ** 2 * (2.0 / 3.0)
    lam = float(rem @ rem) / max(var, 1e-12)
    return float(np.sqrt(lam / (K_PARAMS[kind] * np.log(d.size) + 20.0)))


# ----------------------------------------------------------------------------- effects

#: The effects of the corpus: name -> (reported effect, unit parameters builder).
#: ``eddy_iso`` is the isotropic eddy term ``E_s = e I``, which a time offset ``-e`` explains
#: exactly to first order: the simpler nested term is the right report.
EFFECT_CASES = ("hard_iron", "soft_iron", "time_offset", "eddy_current", "eddy_iso",
                "field_drift", "field_gradient", "disturbance", "hard_iron_step",
                "heading_drift")


def effect_params(case: str, rng: np.random.Generator, a: float, duration_s: float
                  ) -> tuple[str, dict[str, Any], dict[str, Any]]:
    """Parameters of ``case`` at amplitude ``a`` (1 = a nominal size).

    Returns
    -------
    (reported, params, expected)
        The CONVENTIONS name magalign should report, the generator's parameters and the
        reported parameters a correct diagnosis gives.

    """
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    if case == "hard_iron":
        p = {"offset_nT": (50.0 * a * u).tolist()}
        return case, p, p
    if case == "soft_iron":
        A = rng.normal(size=(3, 3))
        S = 0.5 * (A + A.T)
        S -= np.trace(S) / 3 * np.eye(3)
        D = np.eye(3) + 0.004 * a * S / np.linalg.norm(S)
        return case, {"D": D.tolist()}, {"D": D.tolist()}
    if case == "time_offset":
        p = {"time_offset_s": float(rng.choice([-1, 1]) * 0.004 * a)}
        return case, p, p
    if case == "eddy_current":
        s = float(rng.choice([-1, 1]))
        E = np.diag([s, -s, 0.0]) * 0.004 * a
        return case, {"E_s": E.tolist()}, {"E_s": E.tolist()}
    if case == "eddy_iso":
        e = float(rng.choice([-1, 1]) * 0.004 * a)
        return "time_offset", {"E_s": (e * np.eye(3)).tolist()}, {"time_offset_s": -e}
    if case == "field_drift":
        amp = (np.abs(u) * 60.0 + 5.0) * a
        per = float(rng.uniform(1.2, 2.0) * duration_s)
        ph = rng.uniform(0, 2 * np.pi, 3)
        tt = np.linspace(0, duration_s, 2001)
        f = amp * np.sin(2 * np.pi * tt[:, None] / per + ph)
        return case, {"amp_nT": amp.tolist(), "period_s": per, "phase_rad": ph.tolist()}, \
            {"peak_to_peak_nT": (f.max(0) - f.min(0)).tolist()}
    if case == "field_gradient":
        A = rng.normal(size=(3, 3))
        G = 0.5 * (A + A.T)
        G -= np.trace(G) / 3 * np.eye(3)
        G *= 300.0 * a / np.linalg.norm(G)
        return case, {"G_nT_per_m": G.tolist()}, {"G_nT_per_m": G.tolist()}
    if case == "disturbance":
        t0 = float(rng.uniform(0.2, 0.7) * duration_s)
        w = [[t0, t0 + float(rng.uniform(4.0, 8.0))]]
        p = {"windows_s": w, "peak_nT": 200.0 * a, "direction_enu": u.tolist()}
        return case, p, {"windows_s": w, "peak_nT": 200.0 * a}
    if case == "hard_iron_step":
        t0 = float(rng.uniform(0.2, 0.65) * duration_s)
        p = {"windows_s": [[t0, t0 + float(rng.uniform(6.0, 12.0))]],
             "offset_nT": (50.0 * a * u).tolist()}
        return case, p, p
    if case == "heading_drift":
        rate = float(rng.choice([-1, 1]) * 0.03 / duration_s * 3600.0 * a)
        return case, {"rate_deg_per_h": rate}, {
            "rate_deg_per_h": rate, "peak_to_peak_deg": abs(rate) * duration_s / 3600.0}
    raise ValueError(case)


_LIMITS = {"time_offset": 0.1, "eddy_current": 0.1, "eddy_iso": 0.1}


def sized(spec: Spec, case: str, target: float, rng: np.random.Generator
          ) -> tuple[Spec, str, dict, float]:
    """``spec`` with ``case`` added at ``target`` times its detection threshold.

    Effects are linear in their amplitude to first order, so one evaluation at the nominal
    size fixes the scale; lags and eddy constants are capped at 0.1 s.

    Returns
    -------
    (spec, reported, expected params, strength)

    """
    state = rng.bit_generator.state
    rep, p, _ = effect_params(case, rng, 1.0, spec.duration_s)
    key = "eddy_current" if case == "eddy_iso" else rep
    s1 = strength(replace(spec, effects={key: p}), rep)
    a = target / max(s1, 1e-9)
    cap = _LIMITS.get(case)
    if cap is not None:
        a = min(a, cap / 0.004)
    rng.bit_generator.state = state  # same draw, new amplitude
    rep, p, exp = effect_params(case, rng, a, spec.duration_s)
    sp = replace(spec, effects={key: p})
    return sp, rep, exp, strength(sp, rep)


# ----------------------------------------------------------------------------- corpora


def null_specs(n: int, seed: int, duration_s: float = 60.0,
               max_jitter_frac: float = 0.1) -> list[Spec]:
    """``n`` null recordings sweeping rates, phases, jitter, message types, motion, noise.

    Attitude rate 0.25x-4x the magnetometer's (mag 50 or 100 Hz), random phase and jitter up
    to ``max_jitter_frac`` of a period; the four attitude message types in turn; swing frequencies
    0.05-2 Hz (fast swings with small amplitudes: rates up to ~5 rad/s), single-axis in one
    of five, vibration in one of three; attitude noise 0.001-0.05 deg and magnetometer noise
    0.1-20 nT, log-uniform.
    """
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        mag = float(rng.choice([50.0, 100.0]))
        ratio = float(rng.choice([0.25, 0.5, 1.0, 2.0, 4.0]))
        att = mag * ratio
        fast = rng.uniform() < 0.3
        freqs = tuple(rng.uniform(0.5, 2.0, 3) if fast else rng.uniform(0.05, 0.3, 3))
        amps = tuple(rng.uniform(5.0, 20.0, 3) if fast else rng.uniform(10.0, 40.0, 3))
        # a swing must stay below the attitude stream's Nyquist rate with margin
        freqs = tuple(min(f, 0.1 * att) for f in freqs)
        single = i % 5 == 4
        vib = (i % 3 == 2)
        out.append(Spec(
            name=f"null_{i:03d}", seed=int(rng.integers(1 << 30)), duration_s=duration_s,
            mag_rate_hz=mag, att_rate_hz=att,
            att_phase_s=float(rng.uniform(0, 1.0 / att)),
            att_jitter_s=float(rng.uniform(0, max_jitter_frac / att)),
            att_type=ATTITUDE_TYPES[i % 4], motion="single" if single else "multi",
            freqs_hz=freqs, amps_deg=amps, yaw_rate_deg_s=float(rng.uniform(5.0, 20.0)),
            vib_deg=float(rng.uniform(0.01, 0.05)) if vib else 0.0,
            vib_hz=float(min(rng.uniform(4.0, 9.0), 0.2 * att)),
            att_noise_deg=float(np.exp(rng.uniform(np.log(0.001), np.log(0.05)))),
            mag_noise_nT=float(np.exp(rng.uniform(np.log(0.1), np.log(20.0)))),
            B_enu_nT=(float(rng.uniform(-2000, 2000)), float(rng.uniform(15000, 25000)),
                      float(rng.uniform(-48000, -38000))),
            rotvec_body_mag_deg=tuple(rng.uniform(-2.0, 2.0, 3))))
    return out


def effect_specs(seed: int, targets=(2.0, 6.0, 20.0), cases=EFFECT_CASES,
                 duration_s: float = 60.0) -> list[tuple[Spec, str, dict, float]]:
    """Every effect case at each target strength (multiples of its detection threshold).

    Multi-axis motion, mag 100 Hz, attitude 50 Hz (the rate mix of the issue), PoseStamped
    with positions, moderate noise.
    """
    rng = np.random.default_rng(seed)
    out = []
    for case in cases:
        for j, tgt in enumerate(targets):
            base = Spec(name=f"{case}_{j}", seed=int(rng.integers(1 << 30)),
                        duration_s=duration_s, mag_rate_hz=100.0, att_rate_hz=50.0,
                        att_phase_s=float(rng.uniform(0, 0.02)), att_jitter_s=0.0005,
                        freqs_hz=tuple(rng.uniform(0.07, 0.3, 3)),
                        amps_deg=tuple(rng.uniform(15.0, 35.0, 3)),
                        yaw_rate_deg_s=float(rng.uniform(6.0, 15.0)),
                        att_noise_deg=0.005, mag_noise_nT=1.0,
                        B_enu_nT=(float(rng.uniform(-2000, 2000)),
                                  float(rng.uniform(15000, 25000)),
                                  float(rng.uniform(-48000, -38000))),
                        rotvec_body_mag_deg=tuple(rng.uniform(-2.0, 2.0, 3)))
            out.append(sized(base, case, tgt, rng))
    return out


def write_corpus(out_dir: Path, nulls: list[Spec],
                 effects: list[tuple[Spec, str, dict, float]]) -> Path:
    """Write recordings and the key (``pipeline.app.challenge`` key format) beside the folder.

    A recording that uses an option added later (a path other than ``lissajous``, geodetic
    positions, a rotated position frame, ``local_source``, ``lever_arm``) also gets
    ``truth`` (:func:`truth`) in its key entry. Returns the key path
    ``<out_dir>_key/key.json``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    key: dict[str, Any] = {"format": "magalign.challenge_key/1", "recordings": {}}
    for s in nulls:
        write(s, out / f"{s.name}.mcap")
        key["recordings"][s.name] = {"effects": {}, "strength_x_threshold": {},
                                     "spec": _spec_dict(s)}
        if _uses_new_options(s):
            key["recordings"][s.name]["truth"] = truth(s)
    for s, rep, exp, st in effects:
        write(s, out / f"{s.name}.mcap")
        key["recordings"][s.name] = {"effects": {rep: exp}, "strength_x_threshold": {rep: st},
                                     "spec": _spec_dict(s)}
        if _uses_new_options(s):
            key["recordings"][s.name]["truth"] = truth(s)
    kp = out.parent / f"{out.name}_key" / "key.json"
    kp.parent.mkdir(parents=True, exist_ok=True)
    kp.write_text(json.dumps(key, indent=1))
    return kp


def _spec_dict(s: Spec) -> dict[str, Any]:
    d = dict(s.__dict__)
    defaults = Spec(name="", seed=0)
    for f in _NEW_FIELDS:  # at their defaults they leave the key as it was
        if d[f] == getattr(defaults, f):
            del d[f]
    return json.loads(json.dumps(d, default=lambda x: list(x) if isinstance(x, tuple) else x))

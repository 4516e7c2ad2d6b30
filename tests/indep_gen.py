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
ATTITUDE_TYPES = ("sensor_msgs/msg/Imu", "geometry_msgs/msg/PoseStamped",
                  "geometry_msgs/msg/QuaternionStamped", "novatel_oem7_msgs/msg/INSPVA")

#: Number of parameters of the term magalign reports for each effect (for the threshold).
K_PARAMS = {"hard_iron": 3, "soft_iron": 5, "time_offset": 1, "eddy_current": 9,
            "field_drift": 12, "disturbance": 15, "hard_iron_step": 3, "field_gradient": 6,
            "heading_drift": 2, "sample_hold": 1}

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
        Move through space and write positions (PoseStamped only).

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


# ----------------------------------------------------------------------------- physics


def _angles(spec: Spec, t_s: np.ndarray) -> np.ndarray:
    """Yaw, pitch, roll (rad) of the true attitude at ``t_s``, (N, 3)."""
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
    """Position of the sensor, ENU m (a Lissajous path that revisits places), (N, 3)."""
    rng = np.random.default_rng(spec.seed + 2)
    amp = rng.uniform(0.2, 0.4, 3)
    per = rng.uniform(5.0, 13.0, 3)
    ph = rng.uniform(0, 2 * np.pi, 3)
    t = np.asarray(t_s, dtype=float)[:, None]
    return np.array([1.0, 2.0, 1.2]) + amp * np.sin(2 * np.pi * t / per + ph)


def field_enu(spec: Spec, t_s: np.ndarray) -> np.ndarray:
    """Field at the sensor, ENU nT, at sensing times ``t_s`` (N, 3)."""
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
        pos = position_m(spec, t)
        ref = position_m(spec, np.linspace(0, spec.duration_s, 4001)).mean(axis=0)
        B += (pos - ref) @ np.asarray(e["field_gradient"]["G_nT_per_m"]).T
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
        y = y + ((ts >= a) & (ts < b))[:, None] * np.asarray(p["offset_nT"])
    return y


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


def readings(spec: Spec) -> dict[str, np.ndarray]:
    """Everything written: stamps (s), readings (nT), reported attitude, positions."""
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
    return {"t_mag_s": tm, "mag_nT": y, "t_att_s": ta, "att": rep,
            "pos_m": position_m(spec, ta)}


# ----------------------------------------------------------------------------- writing


def _stamp(t_ns: int) -> dict[str, int]:
    return {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}


def write_streams(path: Path, t_mag_s, mag_nT, t_att_s, att: Rotation, att_type: str,
                  pos_m: np.ndarray | None = None, *, mag_topic: str = "/imu/mag",
                  att_topic: str = "/attitude") -> Path:
    """Write a magnetometer and an attitude stream with the ``mcap_ros2`` writer.

    Stamps are ``T0 + t`` (ns); log time is the stamp plus 2 ms; the field is written in
    tesla (REP-145).
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
        msgs.append((int(ta[k]) + 2_000_000, 1, msg))
    msgs.sort(key=lambda x: x[0])
    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=256 * 1024)
        schemas = [w.register_msgdef("sensor_msgs/msg/MagneticField",
                                     MSGDEFS["sensor_msgs/msg/MagneticField"]),
                   w.register_msgdef(att_type, MSGDEFS[att_type])]
        topics = (mag_topic, att_topic)
        for i, (log, s, msg) in enumerate(msgs):
            w.write_message(topics[s], schemas[s], msg, log_time=log, publish_time=log,
                            sequence=i)
        w.finish()
    return path


def write(spec: Spec, path: Path) -> Path:
    """Make the recording of ``spec`` and write it."""
    r = readings(spec)
    pos = r["pos_m"] if (spec.positions and spec.att_type == "geometry_msgs/msg/PoseStamped") \
        else None
    return write_streams(path, r["t_mag_s"], r["mag_nT"], r["t_att_s"], r["att"],
                         spec.att_type, pos)


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

    Returns the key path ``<out_dir>_key/key.json``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    key: dict[str, Any] = {"format": "magalign.challenge_key/1", "recordings": {}}
    for s in nulls:
        write(s, out / f"{s.name}.mcap")
        key["recordings"][s.name] = {"effects": {}, "strength_x_threshold": {},
                                     "spec": _spec_dict(s)}
    for s, rep, exp, st in effects:
        write(s, out / f"{s.name}.mcap")
        key["recordings"][s.name] = {"effects": {rep: exp}, "strength_x_threshold": {rep: st},
                                     "spec": _spec_dict(s)}
    kp = out.parent / f"{out.name}_key" / "key.json"
    kp.parent.mkdir(parents=True, exist_ok=True)
    kp.write_text(json.dumps(key, indent=1))
    return kp


def _spec_dict(s: Spec) -> dict[str, Any]:
    d = dict(s.__dict__)
    return json.loads(json.dumps(d, default=lambda x: list(x) if isinstance(x, tuple) else x))

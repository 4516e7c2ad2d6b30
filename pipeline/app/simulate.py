"""Synthetic recordings: scenario files, motion profiles, effects, noise.

More in docs/modules.md, ``pipeline.app.simulate``.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from pipeline.core.config import TomlDoc
from pipeline.core.errors import ConfigError
from pipeline.core.geometry import (
    li2020_C_body_enu,
    li2020_euler_to_quat,
    matrix_to_quat,
    novatel_to_quat,
    quat_normalize,
    quat_to_li2020_euler,
    quat_to_novatel,
    so3_exp,
)
from pipeline.core.recording import (
    AngleSeries,
    AttitudeSeries,
    ChannelInfo,
    EncodingFamily,
    Frame,
    PositionFrame,
    PositionSeries,
    Recording,
    Role,
    VectorSeries,
)
from pipeline.io.mcap_decode import WGS84_A_M, WGS84_E2, geodetic_to_local_enu
from pipeline.io.mcap_write import write_recording
from pipeline.model.forward import reading
from pipeline.model.igrf import igrf_enu_nT
from schemas import MessageRole, types_of

F64 = NDArray[np.float64]
#: three components, as TOML vectors are checked to have
_Vec3 = tuple[float, float, float]

# the types a scenario may ask for: those magalign writes (schemas' table)
MAG_TYPES = frozenset(types_of(MessageRole.MAGNETOMETER, written=True))
ATTITUDE_TYPES = frozenset(types_of(MessageRole.ATTITUDE, written=True))
TURNTABLE_TYPES = frozenset(types_of(MessageRole.TURNTABLE, written=True))
POSITION_TYPES = frozenset(types_of(MessageRole.POSITION, written=True))

DEFAULT_START = "2026-01-01T00:00:00Z"
_EDDY_STEP_S = 1e-4  # central-difference step for d/dt(y_mag)


# --- options -----------------------------------------------------------------------------


class Profile(str, enum.Enum):
    """Motion profiles."""

    TURNTABLE = "turntable"
    MULTIAXIS = "multiaxis"
    SURVEY_LINES = "survey_lines"
    STATIC_SWEEP = "static_sweep"


class AttitudeSource(str, enum.Enum):
    """What a turntable run records as its attitude: full attitude or the table angle only."""

    ATTITUDE = "attitude"
    TURNTABLE = "turntable"


class DriftKind(str, enum.Enum):
    """Shape of the slow background-field variation."""

    SINUSOID = "sinusoid"
    RANDOM_WALK = "random_walk"


# --- motion profiles ---------------------------------------------------------------------


def _unit(v: Any) -> F64:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _align(a: F64, b: F64) -> F64:
    """Return the smallest rotation matrix taking unit vector ``a`` to unit vector ``b``."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # Opposite: half a turn about any axis perpendicular to a.
        p = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(p) < 1e-6:
            p = np.cross(a, [0.0, 1.0, 0.0])
        return so3_exp(_unit(p) * math.pi)
    return so3_exp(v / s * math.atan2(s, c))


def _tilt_matrix(tilt_deg: float, azimuth_deg: float) -> F64:
    """Rotation tilting ENU up towards the horizontal direction at ``azimuth_deg``.

    Azimuth is clockwise from north (a compass bearing); the tilted vertical is
    ``[sin t sin a, sin t cos a, cos t]``.
    """
    a = math.radians(azimuth_deg)
    d = np.array([math.sin(a), math.cos(a), 0.0])
    k = np.cross([0.0, 0.0, 1.0], d)  # rotating z about z x d moves it towards d
    return so3_exp(k * math.radians(tilt_deg))


@dataclass(frozen=True)
class Turntable:
    """Rotation about one axis at a constant or sinusoidally modulated rate.

    The true attitude is ``C_enu_body(t) = T @ Rot(axis_enu, theta(t)) @ C0`` with ``C0`` the
    smallest rotation taking ``axis_body`` to ``axis_enu`` and ``T`` the ``axis_tilt`` effect
    (identity without it), so the body rotates about ``axis_body`` while the ENU rotation
    axis is the tilted ``T @ axis_enu`` (Tang 2016). The angle channel reports ``theta``.

    Rate: ``omega(t) = rate (1 + m sin(2 pi t / P))``, integrated analytically.
    """

    rate_deg_s: float = 10.0
    axis_body: tuple[float, float, float] = (0.0, 0.0, 1.0)
    axis_enu: tuple[float, float, float] = (0.0, 0.0, 1.0)
    rate_modulation: float = 0.0
    modulation_period_s: float = 10.0
    initial_angle_deg: float = 0.0
    attitude_source: AttitudeSource = AttitudeSource.ATTITUDE

    def angle_rad(self, t_s: F64) -> F64:
        """Table angle theta(t), rad, unwrapped."""
        w = math.radians(self.rate_deg_s)
        P = self.modulation_period_s
        m = self.rate_modulation
        integ = t_s - m * P / (2 * math.pi) * (np.cos(2 * math.pi * t_s / P) - 1.0)
        return math.radians(self.initial_angle_deg) + w * integ

    def C_enu_body(self, t_s: F64, tilt: F64 | None = None) -> F64:
        """Return the true attitude matrices ``C_enu_body``, shape (N, 3, 3)."""
        n = _unit(self.axis_enu)
        C0 = _align(_unit(self.axis_body), n)
        R = so3_exp(self.angle_rad(t_s)[:, None] * n)
        T = np.eye(3) if tilt is None else tilt
        return T @ R @ C0

    def natural_duration_s(self) -> float | None:
        """None: the duration comes from ``timing.duration_s``."""
        return None


@dataclass(frozen=True)
class Multiaxis:
    """Calibration manoeuvre: heading turning and swinging, pitch and roll swings.

    Li 2020 Euler angles (rad from the deg fields)::

        heading(t) = h0 + yaw_rate t + A_y sin(2 pi t / P_y)
        pitch(t)   = p0 + A_p sin(2 pi t / P_p)
        roll(t)    = r0 + A_r sin(2 pi t / P_r)
    """

    yaw_rate_deg_s: float = 6.0
    yaw_amplitude_deg: float = 30.0
    yaw_period_s: float = 17.0
    pitch_amplitude_deg: float = 20.0
    pitch_period_s: float = 7.0
    roll_amplitude_deg: float = 20.0
    roll_period_s: float = 11.0
    heading0_deg: float = 0.0
    pitch0_deg: float = 0.0
    roll0_deg: float = 0.0

    def euler_rad(self, t_s: F64) -> tuple[F64, F64, F64]:
        """Li 2020 (heading, pitch, roll), rad."""
        d = math.radians
        tau = 2 * math.pi
        h = d(self.heading0_deg) + d(self.yaw_rate_deg_s) * t_s + d(
            self.yaw_amplitude_deg
        ) * np.sin(tau * t_s / self.yaw_period_s)
        p = d(self.pitch0_deg) + d(self.pitch_amplitude_deg) * np.sin(
            tau * t_s / self.pitch_period_s)
        r = d(self.roll0_deg) + d(self.roll_amplitude_deg) * np.sin(tau * t_s / self.roll_period_s)
        return h, p, r

    def C_enu_body(self, t_s: F64, tilt: F64 | None = None) -> F64:
        """Return the true attitude matrices ``C_enu_body``, shape (N, 3, 3)."""
        return np.swapaxes(li2020_C_body_enu(*self.euler_rad(t_s)), -1, -2)

    def natural_duration_s(self) -> float | None:
        """None: the duration comes from ``timing.duration_s``."""
        return None


def _smoothstep(u: F64) -> F64:
    """Rise from 0 to 1 on [0, 1] as a raised cosine (zero slope at both ends)."""
    u = np.clip(u, 0.0, 1.0)
    return 0.5 * (1.0 - np.cos(math.pi * u))


@dataclass(frozen=True)
class SurveyLines:
    """Straight lines joined by smooth turns (a lawnmower pattern), with pitch/roll wobble.

    Line ``k`` flies heading ``heading_deg + turn_deg * (k mod 2)`` (Li 2020 heading,
    counter-clockwise from east seen from above); turns alternate left and right and follow a
    raised-cosine heading change. Wobble: ``pitch = w sin(2 pi t / P)``,
    ``roll = w sin(2 pi t / (0.73 P) + 1)`` (incommensurate, so the swings do not lock).
    """

    heading_deg: float = 0.0
    n_lines: int = 2
    line_duration_s: float = 50.0
    turn_duration_s: float = 10.0
    turn_deg: float = 180.0
    wobble_deg: float = 1.0
    wobble_period_s: float = 5.0

    def euler_rad(self, t_s: F64) -> tuple[F64, F64, F64]:
        """Li 2020 (heading, pitch, roll), rad."""
        cyc = self.line_duration_s + self.turn_duration_s
        k = np.floor(t_s / cyc)
        u = t_s - k * cyc
        base = self.heading_deg + self.turn_deg * np.mod(k, 2.0)
        sign = np.where(np.mod(k, 2.0) == 0, 1.0, -1.0)
        s = _smoothstep((u - self.line_duration_s) / max(self.turn_duration_s, 1e-9))
        h = np.radians(base + sign * self.turn_deg * s)
        w = math.radians(self.wobble_deg)
        P = self.wobble_period_s
        p = w * np.sin(2 * math.pi * t_s / P)
        r = w * np.sin(2 * math.pi * t_s / (0.73 * P) + 1.0)
        return h, p, r

    def C_enu_body(self, t_s: F64, tilt: F64 | None = None) -> F64:
        """Return the true attitude matrices ``C_enu_body``, shape (N, 3, 3)."""
        return np.swapaxes(li2020_C_body_enu(*self.euler_rad(t_s)), -1, -2)

    def natural_duration_s(self) -> float | None:
        """Lines and the turns between them."""
        return self.n_lines * self.line_duration_s + (self.n_lines - 1) * self.turn_duration_s


@dataclass(frozen=True)
class StaticSweep:
    """Fixed pitch and roll, heading stepped through ``n_headings`` values (Li 2020, Sec. 4.1).

    Heading runs linearly, ``heading(t) = start + step t / dwell_s``, so samples at
    ``t = k dwell_s`` see heading ``start + k step`` exactly while the motion stays smooth.
    The duration is ``n_headings * dwell_s``; with both streams at ``1 / dwell_s`` Hz and phase
    0 there is one sample per heading.
    """

    heading_start_deg: float = 0.0
    heading_step_deg: float = 1.0
    n_headings: int = 360
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    dwell_s: float = 1.0

    def euler_rad(self, t_s: F64) -> tuple[F64, F64, F64]:
        """Li 2020 (heading, pitch, roll), rad."""
        h = np.radians(self.heading_start_deg + self.heading_step_deg * t_s / self.dwell_s)
        return h, np.full_like(h, math.radians(self.pitch_deg)), np.full_like(
            h, math.radians(self.roll_deg)
        )

    def C_enu_body(self, t_s: F64, tilt: F64 | None = None) -> F64:
        """Return the true attitude matrices ``C_enu_body``, shape (N, 3, 3)."""
        return np.swapaxes(li2020_C_body_enu(*self.euler_rad(t_s)), -1, -2)

    def natural_duration_s(self) -> float | None:
        """One dwell per heading."""
        return self.n_headings * self.dwell_s


Motion = Turntable | Multiaxis | SurveyLines | StaticSweep
_PROFILE_CLASS: dict[Profile, type] = {
    Profile.TURNTABLE: Turntable,
    Profile.MULTIAXIS: Multiaxis,
    Profile.SURVEY_LINES: SurveyLines,
    Profile.STATIC_SWEEP: StaticSweep,
}


# --- effects -----------------------------------------------------------------------------

Windows = tuple[tuple[float, float], ...]
Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]


@dataclass(frozen=True)
class HardIron:
    """Constant offset ``o``, mag frame, nT."""

    offset_nT: Vec3


@dataclass(frozen=True)
class SoftIron:
    """Symmetric positive-definite ``D``."""

    D: Mat3


@dataclass(frozen=True)
class TimeOffset:
    """``tau``, s; positive when the magnetometer stamps are late."""

    time_offset_s: float


@dataclass(frozen=True)
class EddyCurrent:
    """Extra term ``E_s @ d/dt(y_mag)``, mag frame, s."""

    E_s: Mat3


@dataclass(frozen=True)
class FieldDrift:
    """Slow variation of ``B_enu`` with the given peak-to-peak range per ENU axis."""

    peak_to_peak_nT: Vec3
    kind: DriftKind = DriftKind.SINUSOID
    period_s: float | None = None  # sinusoid period; default: the recording's duration


@dataclass(frozen=True)
class Disturbance:
    """Transient external field (ENU): a ``sin^2`` bell of height ``peak_nT`` in each window."""

    windows_s: Windows
    peak_nT: float
    direction_enu: Vec3 = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class HardIronStep:
    """Offset (mag frame) present only inside the windows; raised-cosine edges of ``edge_s``."""

    windows_s: Windows
    offset_nT: Vec3
    edge_s: float = 0.0


@dataclass(frozen=True)
class AxisTilt:
    """Turntable axis tilted from its nominal direction (Tang 2016); azimuth from north."""

    tilt_deg: float
    azimuth_deg: float


@dataclass(frozen=True)
class FieldGradient:
    """Field varying in space: ``B(p) = B_enu + G (p - p_ref)`` along the trajectory.

    ``G_nT_per_m`` is the ENU gradient (symmetric and traceless: curl- and divergence-free),
    ``reference_position_m`` the ENU point where the field is ``B_enu`` (default: the
    trajectory's centre). Needs a ``[trajectory]``.
    """

    G_nT_per_m: Mat3
    reference_position_m: Vec3 | None = None


@dataclass(frozen=True)
class SimulatedSampleHold:
    """The sensor converts at ``native_rate_hz``; every message repeats the latest conversion."""

    native_rate_hz: float


@dataclass(frozen=True)
class Trajectory:
    """Motion through space: a Lissajous path in ENU, metres.

    ``p_enu(t) = centre + amplitude * sin(2 pi t / period + phase)`` per axis. Positions are
    written into the attitude messages that carry one (``PoseStamped`` in a frame rotated
    about Up by ``frame_yaw_deg`` from ENU, like a motion-capture room; INSPVA as latitude,
    longitude and height about ``origin_lat_lon_deg``).
    """

    amplitude_m: Vec3 = (0.3, 0.3, 0.2)
    period_s: Vec3 = (23.0, 17.0, 11.0)
    phase_rad: Vec3 = (0.0, 1.0, 2.0)
    center_m: Vec3 = (0.0, 0.0, 1.5)
    frame_yaw_deg: float = 0.0
    origin_lat_lon_deg: tuple[float, float] = (52.5, 13.3)

    def p_enu_m(self, t_s: F64) -> F64:
        """ENU positions at ``t_s`` (s from the scenario start), (N, 3), m."""
        t = np.asarray(t_s, dtype=float)[:, None]
        return np.array(self.center_m) + np.array(self.amplitude_m) * np.sin(
            2 * math.pi * t / np.array(self.period_s) + np.array(self.phase_rad))

    def Q_enu_local(self) -> F64:
        """Rotation about Up from the written position frame to ENU (``p_enu = Q p_local``)."""
        a = math.radians(self.frame_yaw_deg)
        return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0],
                         [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Effects:
    """Every CONVENTIONS effect, ``None`` when absent."""

    hard_iron: HardIron | None = None
    soft_iron: SoftIron | None = None
    time_offset: TimeOffset | None = None
    eddy_current: EddyCurrent | None = None
    field_drift: FieldDrift | None = None
    disturbance: Disturbance | None = None
    hard_iron_step: HardIronStep | None = None
    axis_tilt: AxisTilt | None = None
    field_gradient: FieldGradient | None = None
    sample_hold: SimulatedSampleHold | None = None

    def params(self) -> dict[str, dict[str, Any]]:
        """Effect name -> params in CONVENTIONS form (lists, matrices as lists of rows)."""
        out: dict[str, dict[str, Any]] = {}
        conv = {
            "hard_iron": ("offset_nT",),
            "soft_iron": ("D",),
            "time_offset": ("time_offset_s",),
            "eddy_current": ("E_s",),
            "field_drift": ("peak_to_peak_nT",),
            "disturbance": ("windows_s", "peak_nT"),
            "hard_iron_step": ("windows_s", "offset_nT"),
            "axis_tilt": ("tilt_deg", "azimuth_deg"),
            "field_gradient": ("G_nT_per_m", "reference_position_m"),
            "sample_hold": ("native_rate_hz",),
        }
        for name, keys in conv.items():
            eff = getattr(self, name)
            if eff is not None:
                out[name] = {k: _jsonable(getattr(eff, k)) for k in keys}
        return out


def _jsonable(v: Any) -> Any:
    if isinstance(v, tuple | list):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    return float(v) if isinstance(v, int | float | np.floating) else v


# --- the rest of the scenario ------------------------------------------------------------


@dataclass(frozen=True)
class Timing:
    """Stream timing: stamps ``start + phase + k / rate`` for ``phase + k / rate < duration``."""

    start_ns: int
    duration_s: float
    mag_rate_hz: float = 100.0
    mag_phase_s: float = 0.0
    attitude_rate_hz: float = 100.0
    attitude_phase_s: float = 0.0


@dataclass(frozen=True)
class FieldSpec:
    """Background field: a given ENU vector, or the IGRF at a place and date."""

    enu_nT: Vec3 | None = None
    igrf: tuple[float, float, float, str] | None = None  # lat_deg, lon_deg, alt_m, date

    def B_enu_nT(self) -> F64:
        """Return the constant background field, ENU, nT."""
        if self.enu_nT is not None:
            return np.array(self.enu_nT, dtype=float)

        lat, lon, alt, date = self.igrf  # type: ignore[misc]
        return igrf_enu_nT(lat, lon, alt, date)


@dataclass(frozen=True)
class Sensor:
    """Mounting of the magnetometer: ``R_body_mag`` (row-major 3x3)."""

    R_body_mag: Mat3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


@dataclass(frozen=True)
class Noise:
    """White noise: magnetometer per axis (nT), attitude heading and pitch/roll (deg)."""

    mag_sigma_nT: float = 0.0
    heading_sigma_deg: float = 0.0
    pitch_roll_sigma_deg: float = 0.0


@dataclass(frozen=True)
class Output:
    """Message types, topics and logger behaviour of the written recording."""

    mag_type: str = "sensor_msgs/msg/MagneticField"
    attitude_type: str = "sensor_msgs/msg/Imu"
    turntable_type: str = "std_msgs/msg/Float64"
    mag_topic: str = "/mag"
    attitude_topic: str = "/attitude"
    turntable_topic: str = "/turntable"
    frame_id: str = "mag"
    mag_log_delay_s: float = 0.0
    attitude_log_delay_s: float = 0.0
    compression: str = "zstd"
    attitude_variant: str | None = None  # INSPVA header layout: None, novatel_header, no_nov_header

    @property
    def family(self) -> EncodingFamily:
        """JSON when the magnetometer channel is one of magalign's JSON types."""
        return EncodingFamily.JSON if self.mag_type.startswith("magalign.") else EncodingFamily.ROS2


@dataclass(frozen=True)
class Scenario:
    """A complete simulation scenario (docs/modules.md and ``pipeline/scenarios``)."""

    name: str
    motion: Motion
    timing: Timing
    field: FieldSpec
    sensor: Sensor = dataclasses.field(default_factory=Sensor)
    effects: Effects = dataclasses.field(default_factory=Effects)
    noise: Noise = dataclasses.field(default_factory=Noise)
    output: Output = dataclasses.field(default_factory=Output)
    seed: int = 0
    description: str = ""
    path: str = "<dict>"
    trajectory: Trajectory | None = None

    @property
    def profile(self) -> Profile:
        """The motion profile."""
        return next(p for p, c in _PROFILE_CLASS.items() if isinstance(self.motion, c))


# --- parsing -----------------------------------------------------------------------------

_TOP_KEYS = {"name", "description", "seed", "timing", "motion", "field", "sensor", "effects",
             "noise", "output", "trajectory"}
_TIMING_KEYS = {"start", "duration_s", "mag_rate_hz", "mag_phase_s", "attitude_rate_hz",
                "attitude_phase_s"}
_EFFECT_KEYS = {
    "hard_iron": {"offset_nT"},
    "soft_iron": {"D"},
    "time_offset": {"time_offset_s"},
    "eddy_current": {"E_s"},
    "field_drift": {"peak_to_peak_nT", "kind", "period_s"},
    "disturbance": {"windows_s", "peak_nT", "direction_enu"},
    "hard_iron_step": {"windows_s", "offset_nT", "edge_s"},
    "axis_tilt": {"tilt_deg", "azimuth_deg"},
    "field_gradient": {"G_nT_per_m", "reference_position_m"},
    "sample_hold": {"native_rate_hz"},
}


def _table(doc: TomlDoc, key: str, required: bool = False) -> Mapping[str, Any]:
    v = doc.get(key) if required else doc.get(key, None)
    if v is None:
        return {}
    if not isinstance(v, Mapping):
        raise doc.error(key, f"must be a table, got {v!r}")
    return v


def _matrix(doc: TomlDoc, key: str) -> Mat3:
    v = doc.get(key)
    ok = (
        isinstance(v, list) and len(v) == 3
        and all(isinstance(r, list) and len(r) == 3 for r in v)
        and all(isinstance(x, int | float) and not isinstance(x, bool) for r in v for x in r)
    )
    if not ok:
        raise doc.error(key, f"must be a 3x3 matrix (list of 3 rows of 3 numbers), got {v!r}")
    return tuple(tuple(float(x) for x in r) for r in v)  # type: ignore[return-value]


def _windows(doc: TomlDoc, key: str) -> Windows:
    v = doc.get(key)
    if not isinstance(v, list) or not v:
        raise doc.error(key, f"must be a non-empty list of [start, end] pairs, got {v!r}")
    out = []
    for w in v:
        if (not isinstance(w, list) or len(w) != 2
                or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in w)):
            raise doc.error(key, f"each window must be [start_s, end_s], got {w!r}")
        if not w[1] > w[0]:
            raise doc.error(key, f"window {w!r} must have end > start")
        out.append((float(w[0]), float(w[1])))
    return tuple(out)


def _start_ns(doc: TomlDoc, key: str) -> int:
    v = doc.get(key, DEFAULT_START)
    if isinstance(v, str):
        try:
            v = _dt.datetime.fromisoformat(v.strip().replace("Z", "+00:00"))
        except ValueError:
            raise doc.error(key, f"must be an ISO 8601 date-time, got {v!r}") from None
    if isinstance(v, _dt.date) and not isinstance(v, _dt.datetime):
        v = _dt.datetime(v.year, v.month, v.day)
    if not isinstance(v, _dt.datetime):
        raise doc.error(key, f"must be a date-time, got {v!r}")
    if v.tzinfo is None:
        v = v.replace(tzinfo=_dt.timezone.utc)
    epoch = _dt.datetime(1970, 1, 1, tzinfo=_dt.timezone.utc)
    d = v - epoch
    return (d.days * 86400 + d.seconds) * 1_000_000_000 + d.microseconds * 1000


def _parse_motion(doc: TomlDoc) -> Motion:
    tbl = _table(doc, "motion", required=True)
    profile = doc.choice("motion.profile", Profile)
    cls = _PROFILE_CLASS[profile]
    fields = {f.name: f for f in dataclasses.fields(cls)}
    doc.check_keys(tbl, set(fields) | {"profile"}, "motion")
    kw: dict[str, Any] = {}
    for name in fields:
        key = f"motion.{name}"
        if name not in tbl:
            continue
        if name == "attitude_source":
            kw[name] = doc.choice(key, AttitudeSource)
        elif name in ("axis_body", "axis_enu"):
            v = doc.vector(key)
            if np.linalg.norm(v) < 1e-9:
                raise doc.error(key, "must not be the zero vector")
            kw[name] = tuple(v)
        elif name in ("n_lines", "n_headings"):
            v = doc.get(key)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise doc.error(key, f"must be a positive integer, got {v!r}")
            kw[name] = v
        elif name.endswith("_period_s") or name in ("dwell_s", "line_duration_s"):
            kw[name] = doc.number(key, lo=1e-6)
        elif name in ("turn_duration_s",):
            kw[name] = doc.number(key, lo=0.0)
        else:
            kw[name] = doc.number(key)
    return cls(**kw)


def _parse_effects(doc: TomlDoc) -> Effects:
    tbl = _table(doc, "effects")
    doc.check_keys(tbl, set(_EFFECT_KEYS), "effects")
    kw: dict[str, Any] = {}
    for name in tbl:
        p = f"effects.{name}"
        sub = _table(doc, p)
        doc.check_keys(sub, _EFFECT_KEYS[name], p)
        if name == "hard_iron":
            kw[name] = HardIron(cast(_Vec3, tuple(doc.vector(f"{p}.offset_nT"))))
        elif name == "soft_iron":
            D = _matrix(doc, f"{p}.D")
            Da = np.array(D)
            if not np.allclose(Da, Da.T, atol=1e-12):
                raise doc.error(f"{p}.D", "must be symmetric")
            if np.min(np.linalg.eigvalsh(Da)) <= 0:
                raise doc.error(f"{p}.D", "must be positive definite")
            kw[name] = SoftIron(D)
        elif name == "time_offset":
            kw[name] = TimeOffset(doc.number(f"{p}.time_offset_s", lo=-10.0, hi=10.0))
        elif name == "eddy_current":
            kw[name] = EddyCurrent(_matrix(doc, f"{p}.E_s"))
        elif name == "field_drift":
            ptp = doc.vector(f"{p}.peak_to_peak_nT")
            if min(ptp) < 0:
                raise doc.error(f"{p}.peak_to_peak_nT", "must not be negative")
            kind = doc.choice(f"{p}.kind", DriftKind, DriftKind.SINUSOID)
            per = doc.get(f"{p}.period_s", None)
            per = None if per is None else doc.number(f"{p}.period_s", lo=1e-3)
            kw[name] = FieldDrift(cast(_Vec3, tuple(ptp)), kind, per)
        elif name == "disturbance":
            dirn = doc.vector(f"{p}.direction_enu", default=[0.0, 0.0, 1.0])
            if np.linalg.norm(dirn) < 1e-9:
                raise doc.error(f"{p}.direction_enu", "must not be the zero vector")
            kw[name] = Disturbance(
                _windows(doc, f"{p}.windows_s"), doc.number(f"{p}.peak_nT"),
                tuple(_unit(dirn).tolist()),
            )
        elif name == "hard_iron_step":
            wins = _windows(doc, f"{p}.windows_s")
            edge = doc.number(f"{p}.edge_s", 0.0, lo=0.0)
            if any(2 * edge > e - s for s, e in wins):
                raise doc.error(f"{p}.edge_s", "must be at most half of the shortest window")
            kw[name] = HardIronStep(wins, cast(_Vec3, tuple(doc.vector(f"{p}.offset_nT"))), edge)
        elif name == "axis_tilt":
            kw[name] = AxisTilt(
                doc.number(f"{p}.tilt_deg", lo=0.0, hi=90.0), doc.number(f"{p}.azimuth_deg")
            )
        elif name == "field_gradient":
            G = _matrix(doc, f"{p}.G_nT_per_m")
            Ga = np.array(G)
            scale = max(float(np.abs(Ga).max()), 1e-12)
            if not np.allclose(Ga, Ga.T, atol=1e-9 * scale) or abs(np.trace(Ga)) > 1e-9 * scale:
                raise doc.error(f"{p}.G_nT_per_m", "must be symmetric and traceless (a field "
                                "gradient in free space is curl- and divergence-free)")
            ref = doc.get(f"{p}.reference_position_m", None)
            ref = None if ref is None else tuple(doc.vector(f"{p}.reference_position_m"))
            kw[name] = FieldGradient(G, ref)
        elif name == "sample_hold":
            kw[name] = SimulatedSampleHold(doc.number(f"{p}.native_rate_hz", lo=1e-3))
    return Effects(**kw)


def _parse_trajectory(doc: TomlDoc) -> Trajectory | None:
    if doc.get("trajectory", None) is None:
        return None
    tbl = _table(doc, "trajectory")
    names = {f.name for f in dataclasses.fields(Trajectory)}
    doc.check_keys(tbl, names, "trajectory")
    d = Trajectory()
    kw: dict[str, Any] = {}
    for k in ("amplitude_m", "period_s", "phase_rad", "center_m"):
        kw[k] = tuple(doc.vector(f"trajectory.{k}", default=list(getattr(d, k))))
    if min(kw["period_s"]) <= 0:
        raise doc.error("trajectory.period_s", "must be positive")
    kw["frame_yaw_deg"] = doc.number("trajectory.frame_yaw_deg", d.frame_yaw_deg)
    kw["origin_lat_lon_deg"] = tuple(doc.vector("trajectory.origin_lat_lon_deg", 2,
                                                default=list(d.origin_lat_lon_deg)))
    return Trajectory(**kw)


def _parse_sensor(doc: TomlDoc) -> Sensor:
    tbl = _table(doc, "sensor")
    doc.check_keys(tbl, {"misalignment_rotvec_deg", "misalignment_li2020_deg"}, "sensor")
    if len(tbl) > 1:
        raise doc.error("sensor.misalignment_li2020_deg",
                        "give either misalignment_rotvec_deg or misalignment_li2020_deg")
    if "misalignment_rotvec_deg" in tbl:
        R = so3_exp(np.radians(doc.vector("sensor.misalignment_rotvec_deg")))
    elif "misalignment_li2020_deg" in tbl:
        h, p, r = np.radians(doc.vector("sensor.misalignment_li2020_deg"))
        R = li2020_R_body_mag(h, p, r)
    else:
        R = np.eye(3)
    return Sensor(tuple(tuple(float(x) for x in row) for row in R))  # type: ignore[arg-type]


def li2020_R_body_mag(heading: float, pitch: float, roll: float) -> F64:
    """Misalignment from Li 2020 Euler angles (rad): ``R_body_mag = E(h, p, r).T``.

    The angles describe the magnetometer frame relative to the body frame the way attitude
    angles describe the body relative to ENU (``C_mag_body = Ey(roll) Ex(pitch) Ez(heading)``,
    Li 2020 Eq. 7), see docs/modules.md.
    """
    return li2020_C_body_enu(heading, pitch, roll).T.copy()


def _parse_field(doc: TomlDoc) -> FieldSpec:
    tbl = _table(doc, "field", required=True)
    doc.check_keys(tbl, {"enu_nT", "igrf"}, "field")
    if ("enu_nT" in tbl) == ("igrf" in tbl):
        raise doc.error("field", "give exactly one of enu_nT or [field.igrf]")
    if "enu_nT" in tbl:
        return FieldSpec(enu_nT=tuple(doc.vector("field.enu_nT")))  # type: ignore[arg-type]
    sub = _table(doc, "field.igrf")
    doc.check_keys(sub, {"lat_deg", "lon_deg", "alt_m", "date"}, "field.igrf")
    date = doc.get("field.igrf.date")
    if isinstance(date, _dt.date):
        date = date.isoformat()
    if not isinstance(date, str):
        raise doc.error("field.igrf.date", f"must be a date, got {date!r}")
    spec = FieldSpec(igrf=(
        doc.number("field.igrf.lat_deg", lo=-90, hi=90),
        doc.number("field.igrf.lon_deg", lo=-360, hi=360),
        doc.number("field.igrf.alt_m", 0.0, lo=-1e4, hi=1e6),
        date,
    ))
    try:
        spec.B_enu_nT()
    except ConfigError as exc:
        raise doc.error("field.igrf.date", exc.message) from None
    return spec


def _parse_timing(doc: TomlDoc, motion: Motion) -> Timing:
    tbl = _table(doc, "timing")
    doc.check_keys(tbl, _TIMING_KEYS, "timing")
    nat = motion.natural_duration_s()
    if nat is None:
        dur = doc.number("timing.duration_s", lo=1e-6)
    else:
        if "duration_s" in tbl:
            raise doc.error("timing.duration_s", "is set by the motion profile; remove it")
        dur = nat
    default_rate = 1.0 / motion.dwell_s if isinstance(motion, StaticSweep) else 100.0
    return Timing(
        start_ns=_start_ns(doc, "timing.start"),
        duration_s=dur,
        mag_rate_hz=doc.number("timing.mag_rate_hz", default_rate, lo=1e-6, hi=1e6),
        mag_phase_s=doc.number("timing.mag_phase_s", 0.0, lo=0.0),
        attitude_rate_hz=doc.number("timing.attitude_rate_hz", default_rate, lo=1e-6, hi=1e6),
        attitude_phase_s=doc.number("timing.attitude_phase_s", 0.0, lo=0.0),
    )


def _parse_output(doc: TomlDoc) -> Output:
    tbl = _table(doc, "output")
    allowed = {f.name for f in dataclasses.fields(Output)}
    doc.check_keys(tbl, allowed, "output")
    kw: dict[str, Any] = {}
    for name, allowed_types in (("mag_type", MAG_TYPES), ("attitude_type", ATTITUDE_TYPES),
                                ("turntable_type", TURNTABLE_TYPES)):
        if name in tbl:
            v = doc.get(f"output.{name}")
            if v not in allowed_types:
                raise doc.error(f"output.{name}",
                                f"must be one of {', '.join(sorted(allowed_types))}, got {v!r}")
            kw[name] = v
    for name in ("mag_topic", "attitude_topic", "turntable_topic", "frame_id", "compression",
                 "attitude_variant"):
        if name in tbl:
            v = doc.get(f"output.{name}")
            if not isinstance(v, str):
                raise doc.error(f"output.{name}", f"must be a string, got {v!r}")
            kw[name] = v
    for name in ("mag_log_delay_s", "attitude_log_delay_s"):
        if name in tbl:
            kw[name] = doc.number(f"output.{name}", lo=0.0, hi=60.0)
    if kw.get("attitude_variant", "oem7_header") not in ("oem7_header", "novatel_header",
                                                         "no_nov_header"):
        raise doc.error("output.attitude_variant",
                        "must be oem7_header, novatel_header or no_nov_header (INSPVA layouts)")
    if kw.get("attitude_variant") == "oem7_header":
        kw["attitude_variant"] = None  # the writer's default layout
    if "compression" in kw and kw["compression"] not in ("zstd", "lz4", "none"):
        raise doc.error("output.compression", "must be zstd, lz4 or none")
    out = Output(**kw)
    fams = {out.mag_type.startswith("magalign."), out.attitude_type.startswith("magalign.")}
    if len(fams) > 1:
        raise doc.error("output.attitude_type",
                        "magnetometer and attitude types must be of one family (ROS 2 or JSON)")
    return out


def scenario_from_doc(doc: TomlDoc) -> Scenario:
    """Build a :class:`Scenario` from a parsed document; errors name file, key and line."""
    doc.check_keys(doc.data, _TOP_KEYS)
    name = doc.get("name", Path(doc.path).stem if doc.path[:1] != "<" else "scenario")
    if not isinstance(name, str):
        raise doc.error("name", f"must be a string, got {name!r}")
    desc = doc.get("description", "")
    if not isinstance(desc, str):
        raise doc.error("description", f"must be a string, got {desc!r}")
    seed = doc.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise doc.error("seed", f"must be a non-negative integer, got {seed!r}")
    motion = _parse_motion(doc)
    effects = _parse_effects(doc)
    if effects.axis_tilt is not None and not isinstance(motion, Turntable):
        raise doc.error("effects.axis_tilt", "applies to the turntable profile only")
    trajectory = _parse_trajectory(doc)
    if effects.field_gradient is not None and trajectory is None:
        raise doc.error("effects.field_gradient", "needs a [trajectory] (motion through space)")
    noise_tbl = _table(doc, "noise")
    doc.check_keys(noise_tbl, {"mag_sigma_nT", "heading_sigma_deg", "pitch_roll_sigma_deg"},
                   "noise")
    noise = Noise(
        doc.number("noise.mag_sigma_nT", 0.0, lo=0.0),
        doc.number("noise.heading_sigma_deg", 0.0, lo=0.0),
        doc.number("noise.pitch_roll_sigma_deg", 0.0, lo=0.0),
    )
    return Scenario(
        name=name,
        motion=motion,
        timing=_parse_timing(doc, motion),
        field=_parse_field(doc),
        sensor=_parse_sensor(doc),
        effects=effects,
        noise=noise,
        output=_parse_output(doc),
        seed=seed,
        description=desc,
        path=doc.path,
        trajectory=trajectory,
    )


def load_scenario(path: str | Path) -> Scenario:
    """Read a scenario TOML file.

    Raises
    ------
    ConfigError
        Naming the file, the key and its line for anything missing, unknown or out of range.

    """
    return scenario_from_doc(TomlDoc.load(path))


def scenario_from_dict(d: dict[str, Any], path: str = "<dict>") -> Scenario:
    """Build a :class:`Scenario` from a dict laid out like the TOML file (generated ones)."""
    if not isinstance(d, Mapping):
        raise ConfigError("a scenario must be a table", path=path)
    return scenario_from_doc(TomlDoc(path, dict(d), ""))


# --- simulation --------------------------------------------------------------------------


@dataclass(frozen=True)
class Truth:
    """Every true value behind a simulated recording.

    Attributes
    ----------
    R_body_mag : ndarray (3, 3)
    B_enu_nT : ndarray (3,)
        Constant background field (without drift or disturbance).
    D : ndarray (3, 3) or None
    offset_nT : ndarray (3,) or None
    time_offset_s : float
        ``tau`` (0 without the time_offset effect).
    effects : dict
        Effect name -> CONVENTIONS params.
    axis_tilt : dict or None
        ``{tilt_deg, azimuth_deg, axis_enu}`` (``axis_enu``: the true, tilted rotation axis).
    mag_t_ns : ndarray (N,) int64
        Magnetometer stamps.
    q_enu_body_true : ndarray (N, 4)
        True attitude at the magnetometer stamps ``t``.
    q_enu_body_sensed : ndarray (N, 4)
        True attitude at ``t - tau``: the attitude each sample actually saw.
    B_enu_t_nT : ndarray (N, 3)
        Field in ENU at each stamp, drift and disturbance included.
    mag_clean_nT : ndarray (N, 3)
        Noise-free magnetometer values (every effect included).

    """

    R_body_mag: F64
    B_enu_nT: F64
    D: F64 | None
    offset_nT: F64 | None
    time_offset_s: float
    effects: dict[str, dict[str, Any]]
    axis_tilt: dict[str, Any] | None
    mag_t_ns: NDArray[np.int64]
    q_enu_body_true: F64
    q_enu_body_sensed: F64
    B_enu_t_nT: F64
    mag_clean_nT: F64

    def to_dict(self) -> dict[str, Any]:
        """Return the scalar truth as JSON-able data (no per-sample arrays)."""
        return {
            "R_body_mag": self.R_body_mag.tolist(),
            "B_enu_nT": self.B_enu_nT.tolist(),
            "D": None if self.D is None else self.D.tolist(),
            "offset_nT": None if self.offset_nT is None else self.offset_nT.tolist(),
            "time_offset_s": self.time_offset_s,
            "effects": self.effects,
            "axis_tilt": self.axis_tilt,
        }


@dataclass(frozen=True)
class Simulated:
    """A simulated recording with its truth and the scenario that made it."""

    recording: Recording
    truth: Truth
    scenario: Scenario


def _stamps_ns(start_ns: int, phase_s: float, rate_hz: float, duration_s: float) -> NDArray:
    n = max(0, int(math.ceil((duration_s - phase_s) * rate_hz - 1e-9)))
    k = np.arange(n, dtype=np.float64)
    return start_ns + np.round((phase_s + k / rate_hz) * 1e9).astype(np.int64)


def _bells(t_s: F64, windows: Windows) -> F64:
    """Sum of ``sin^2`` bells, 1 at each window's centre, 0 outside (half-open windows)."""
    out = np.zeros_like(t_s)
    for s, e in windows:
        inside = (t_s >= s) & (t_s < e)
        out += np.where(inside, np.sin(math.pi * (t_s - s) / (e - s)) ** 2, 0.0)
    return out


def _gates(t_s: F64, windows: Windows, edge_s: float) -> F64:
    """1 inside each window, raised-cosine edges of ``edge_s`` (abrupt when 0)."""
    out = np.zeros_like(t_s)
    for s, e in windows:
        inside = (t_s >= s) & (t_s < e)
        if edge_s > 0:
            g = _smoothstep((t_s - s) / edge_s) * _smoothstep((e - t_s) / edge_s)
        else:
            g = np.ones_like(t_s)
        out += np.where(inside, g, 0.0)
    return out


class _Model:
    """The noise-free measurement model as a function of time (s from the scenario start)."""

    def __init__(self, sc: Scenario, t0_mag_s: float, t_last_s: float,
                 rng: np.random.Generator):
        self.sc = sc
        eff = sc.effects
        self.R = np.array(sc.sensor.R_body_mag, dtype=float)
        self.D = None if eff.soft_iron is None else np.array(eff.soft_iron.D, dtype=float)
        self.o = None if eff.hard_iron is None else np.array(eff.hard_iron.offset_nT, float)
        self.tau = 0.0 if eff.time_offset is None else eff.time_offset.time_offset_s
        self.B0 = sc.field.B_enu_nT()
        self.t0 = t0_mag_s
        self.tilt = (None if eff.axis_tilt is None
                     else _tilt_matrix(eff.axis_tilt.tilt_deg, eff.axis_tilt.azimuth_deg))
        self.drift = None
        fd = eff.field_drift
        if fd is not None:
            ptp = np.array(fd.peak_to_peak_nT, dtype=float)
            if fd.kind is DriftKind.SINUSOID:
                period = fd.period_s or max(t_last_s - t0_mag_s, 1e-3)
                self.drift = lambda t: 0.5 * ptp * np.sin(
                    2 * math.pi * (t - t0_mag_s) / period)[:, None]
            else:

                lo, hi = t0_mag_s - 1.0, t_last_s + 1.0
                n = max(20, int((hi - lo) / max((hi - lo) / 200.0, 0.1)))
                grid = np.linspace(lo, hi, n)
                walk = np.cumsum(rng.standard_normal((n, 3)), axis=0)
                # Scale each axis to exactly the requested range over the recording; PCHIP
                # interpolation never overshoots the grid values.
                inner = (grid >= t0_mag_s) & (grid <= t_last_s)
                inner = inner if inner.sum() >= 2 else np.ones(n, bool)
                wmin, wmax = walk[inner].min(0), walk[inner].max(0)
                span = np.where(wmax > wmin, wmax - wmin, 1.0)
                walk = (walk - wmin) / span * ptp - 0.5 * ptp
                from scipy.interpolate import PchipInterpolator  # pipeline.core.warm.LATE_IMPORTS

                self.drift = PchipInterpolator(grid, walk, axis=0)

    def C_enu_body(self, t_s: F64) -> F64:
        return self.sc.motion.C_enu_body(t_s, self.tilt)

    def B_enu(self, t_s: F64) -> F64:
        B = np.broadcast_to(self.B0, (t_s.shape[0], 3)).copy()
        if self.drift is not None:
            B += self.drift(t_s)
        fg = self.sc.effects.field_gradient
        if fg is not None and self.sc.trajectory is not None:
            tr = self.sc.trajectory
            ref = np.array(tr.center_m if fg.reference_position_m is None
                           else fg.reference_position_m)
            B += (tr.p_enu_m(t_s) - ref) @ np.array(fg.G_nT_per_m).T  # B(p) = B + G (p - p_ref)
        dist = self.sc.effects.disturbance
        if dist is not None:
            B += dist.peak_nT * _bells(t_s - self.t0, dist.windows_s)[:, None] * np.array(
                dist.direction_enu)
        return B

    def y(self, t_s: F64) -> F64:
        """``D R.T C(t - tau).T B(t) + o + step(t)``: (M2)-(M5) without the eddy term.

        Computed by THE forward model (:func:`pipeline.model.forward.reading`) from the
        scenario's own pieces: the analytic motion at ``t - tau`` (not interpolated), the
        field with its drift, gradient and disturbance bells, and the hard-iron steps with
        their raised-cosine edges. The independent implementation of the same model is the
        test oracle ``tests/indep_gen.py``.
        """
        Ct = np.swapaxes(self.C_enu_body(t_s - self.tau), -1, -2)
        offsets = [] if self.o is None else [self.o]
        step = self.sc.effects.hard_iron_step
        if step is not None:
            offsets.append(_gates(t_s - self.t0, step.windows_s, step.edge_s)[:, None]
                           * np.array(step.offset_nT))
        return reading(Ct, self.B_enu(t_s), self.R, self.D, offsets).y_nT

    def y_full(self, t_s: F64) -> F64:
        """Model with the eddy-current term ``E_s @ d/dt(y)`` of (M5).

        The rate is the central difference of the whole noise-free reading (step
        :data:`_EDDY_STEP_S`, on the analytic motion); the forward model's regressor ``ydot0``
        (rotation alone, on the interpolated attitude) approximates it.
        """
        y = self.y(t_s)
        ed = self.sc.effects.eddy_current
        if ed is not None:
            h = _EDDY_STEP_S
            dy = (self.y(t_s + h) - self.y(t_s - h)) / (2 * h)
            y = y + dy @ np.array(ed.E_s).T
        return y


def _attitude_noise(C: F64, heading_sigma_deg: float, pr_sigma_deg: float,
                    rng: np.random.Generator) -> F64:
    """Measured attitude: heading error about ENU up, pitch/roll errors about body x and y."""
    n = C.shape[0]
    if heading_sigma_deg > 0:
        dh = rng.standard_normal(n) * math.radians(heading_sigma_deg)
        C = so3_exp(np.stack([np.zeros(n), np.zeros(n), dh], -1)) @ C
    if pr_sigma_deg > 0:
        # Li 2020: pitch is about body x, roll about body y.
        d = rng.standard_normal((n, 2)) * math.radians(pr_sigma_deg)
        C = C @ so3_exp(np.concatenate([d, np.zeros((n, 1))], -1))
    return C


def _as_read(q: F64, attitude_type: str) -> F64:
    """Return the quaternion ingest gives for ``q`` written as ``attitude_type``."""
    if attitude_type == "novatel_oem7_msgs/msg/INSPVA":
        return quat_normalize(novatel_to_quat(*quat_to_novatel(q)))
    if attitude_type == "magalign.AttitudeEuler":
        h, p, r = (np.radians(np.degrees(a)) for a in quat_to_li2020_euler(q))
        return quat_normalize(li2020_euler_to_quat(h, p, r))
    return quat_normalize(q)


def _written_position(sc: Scenario, t_att: F64, att_t_ns: NDArray) -> PositionSeries | None:
    """Positions as ingest reads them back, or None when the messages carry none.

    ``PoseStamped``: the trajectory in the frame rotated by ``frame_yaw_deg`` about Up
    (``attitude_source_local``); INSPVA: ENU on the tangent plane at the first fix.
    """
    tr = sc.trajectory
    if tr is None:
        return None
    p_enu = tr.p_enu_m(t_att)
    if sc.output.attitude_type == "geometry_msgs/msg/PoseStamped":
        return PositionSeries(att_t_ns, p_enu @ tr.Q_enu_local(),
                              PositionFrame.ATTITUDE_SOURCE_LOCAL)
    if sc.output.attitude_type == "novatel_oem7_msgs/msg/INSPVA":

        lat, lon, h = _geodetic(tr, p_enu)
        return PositionSeries(att_t_ns, geodetic_to_local_enu(lat, lon, h), PositionFrame.ENU)
    return None


def _geodetic(tr: Trajectory, p_enu: F64) -> tuple[F64, F64, F64]:
    """Latitude, longitude (deg) and height (m) of ENU points about the trajectory origin.

    The inverse of the flat-earth tangent plane of :func:`pipeline.io.mcap_read.
    geodetic_to_local_enu` (exact for it), origin at the trajectory's origin latitude and
    longitude and height 0 m at ENU ``z = 0``.
    """
    lat0, lon0 = (math.radians(x) for x in tr.origin_lat_lon_deg)
    w = math.sqrt(1.0 - WGS84_E2 * math.sin(lat0) ** 2)
    r_n, r_m = WGS84_A_M / w, WGS84_A_M * (1.0 - WGS84_E2) / w**3
    # the reader's origin is the first fix: make the first fix the stated origin
    h0 = float(p_enu[0, 2])
    d = p_enu - p_enu[0]
    lat = np.degrees(lat0 + d[:, 1] / (r_m + h0))
    lon = np.degrees(lon0 + d[:, 0] / ((r_n + h0) * math.cos(lat0)))
    return lat, lon, p_enu[:, 2]


def _rate(t_ns: NDArray) -> float | None:
    """Return the nominal rate as ingest reports it: 1 / median stamp interval, Hz."""
    dt = np.diff(t_ns)
    dt = dt[dt > 0]
    if not dt.shape[0]:
        return None
    return float(1e9 / np.median(dt))


def _encoding_name(msg_type: str) -> str:
    return "json" if msg_type.startswith("magalign.") else "cdr"


def simulate(scenario: Scenario, *, seed: int | None = None) -> Simulated:
    """Simulate a recording.

    Parameters
    ----------
    scenario : Scenario
        What to simulate.
    seed : int, optional
        Overrides ``scenario.seed``; the same seed gives the same recording.

    Returns
    -------
    Simulated
        ``recording`` (magnetometer frame ``mag``, nT; attitude ``q_enu_body`` or a turntable
        angle channel), ``truth`` and the scenario.

    """
    sc = scenario
    ss = np.random.SeedSequence(sc.seed if seed is None else seed)
    rng_mag, rng_att, rng_drift, rng_tt = (np.random.default_rng(s) for s in ss.spawn(4))
    tm = sc.timing
    mag_t_ns = _stamps_ns(tm.start_ns, tm.mag_phase_s, tm.mag_rate_hz, tm.duration_s)
    att_t_ns = _stamps_ns(tm.start_ns, tm.attitude_phase_s, tm.attitude_rate_hz, tm.duration_s)
    if mag_t_ns.shape[0] < 1:
        raise ConfigError("the scenario produces no magnetometer sample", path=sc.path,
                          key="timing.duration_s")
    t_mag = (mag_t_ns - tm.start_ns).astype(float) * 1e-9
    t_att = (att_t_ns - tm.start_ns).astype(float) * 1e-9

    model = _Model(sc, float(t_mag[0]), float(t_mag[-1]), rng_drift)
    sh = sc.effects.sample_hold
    if sh is not None and t_mag.shape[0]:
        # conversions on the native grid; each message repeats the latest one at its stamp
        t_conv = t_mag[0] + np.arange(int((t_mag[-1] - t_mag[0]) * sh.native_rate_hz) + 1
                                      ) / sh.native_rate_hz
        k = np.clip(np.searchsorted(t_conv, t_mag + 1e-12, side="right") - 1, 0, None)
        clean_conv = model.y_full(t_conv)
        conv = clean_conv + rng_mag.standard_normal(clean_conv.shape) * sc.noise.mag_sigma_nT
        clean, mag = clean_conv[k], conv[k]
    else:
        clean = model.y_full(t_mag)
        mag = clean + rng_mag.standard_normal(clean.shape) * sc.noise.mag_sigma_nT
    if sc.output.mag_type == "sensor_msgs/msg/MagneticField":
        # REP-145 puts tesla on the wire; keep exactly what reading the file back gives.
        mag = (mag * 1e-9) * 1e9

    out = sc.output
    channels = [ChannelInfo(out.mag_topic, out.mag_type, _encoding_name(out.mag_type),
                            Role.MAGNETOMETER, int(mag_t_ns.shape[0]), _rate(mag_t_ns))]
    attitude = None
    turntable = None
    position = None
    attitude_topic: str | None = out.attitude_topic
    use_angle = (isinstance(sc.motion, Turntable)
                 and sc.motion.attitude_source is AttitudeSource.TURNTABLE)
    if use_angle:
        ang = sc.motion.angle_rad(t_att)  # type: ignore[union-attr]
        ang = ang + rng_tt.standard_normal(ang.shape) * math.radians(sc.noise.heading_sigma_deg)
        # Written in degrees; keep what reading it back gives.
        turntable = AngleSeries(att_t_ns, np.radians(np.degrees(ang)))
        attitude_topic = None
        channels.append(ChannelInfo(out.turntable_topic, out.turntable_type,
                                    _encoding_name(out.turntable_type), Role.TURNTABLE,
                                    int(att_t_ns.shape[0]), _rate(att_t_ns)))
    else:
        C_meas = _attitude_noise(model.C_enu_body(t_att), sc.noise.heading_sigma_deg,
                                 sc.noise.pitch_roll_sigma_deg, rng_att)
        q_meas = _as_read(matrix_to_quat(C_meas), out.attitude_type)
        attitude = AttitudeSeries(att_t_ns, q_meas)
        position = _written_position(sc, t_att, att_t_ns)
        channels.append(ChannelInfo(out.attitude_topic, out.attitude_type,
                                    _encoding_name(out.attitude_type), Role.ATTITUDE,
                                    int(att_t_ns.shape[0]), _rate(att_t_ns)))

    recording = Recording(
        path=f"<simulated {sc.name}>",
        channels=tuple(channels),
        mag=VectorSeries(mag_t_ns, mag, Frame.MAG, "nT"),
        mag_topic=out.mag_topic,
        attitude=attitude,
        attitude_topic=attitude_topic,
        encoding=out.family,
        turntable=turntable,
        mag_frame_id=out.frame_id,
        problems=(),
        position=position,
    )
    axis_tilt = None
    if sc.effects.axis_tilt is not None and isinstance(sc.motion, Turntable):
        assert model.tilt is not None  # the model of a scenario with an axis tilt has one
        axis_tilt = {
            "tilt_deg": sc.effects.axis_tilt.tilt_deg,
            "azimuth_deg": sc.effects.axis_tilt.azimuth_deg,
            "axis_enu": (model.tilt @ _unit(sc.motion.axis_enu)).tolist(),
        }
    truth = Truth(
        R_body_mag=model.R,
        B_enu_nT=model.B0,
        D=model.D,
        offset_nT=model.o,
        time_offset_s=float(model.tau),
        effects=sc.effects.params(),
        axis_tilt=axis_tilt,
        mag_t_ns=mag_t_ns,
        q_enu_body_true=matrix_to_quat(model.C_enu_body(t_mag)),
        q_enu_body_sensed=matrix_to_quat(model.C_enu_body(t_mag - model.tau)),
        B_enu_t_nT=model.B_enu(t_mag),
        mag_clean_nT=clean,
    )
    for a in (truth.R_body_mag, truth.B_enu_nT, truth.D, truth.offset_nT,
              truth.q_enu_body_true, truth.q_enu_body_sensed, truth.B_enu_t_nT,
              truth.mag_clean_nT, truth.mag_t_ns):
        if a is not None:
            a.flags.writeable = False
    return Simulated(recording, truth, sc)


def write_simulated(sim: Simulated, path: str | Path) -> Path:
    """Write a simulated recording as an MCAP file, as a real logger would.

    Messages are interleaved by log time (stamp + the scenario's log delays). Returns the path.
    """
    rec = sim.recording
    out = sim.scenario.output
    kw: dict[str, Any] = {}
    if rec.attitude is not None:
        kw.update(attitude_t_ns=rec.attitude.t_ns, q_enu_body=rec.attitude.q_enu_body,
                  attitude_type=out.attitude_type, attitude_topic=out.attitude_topic,
                  attitude_variant=out.attitude_variant)
        tr = sim.scenario.trajectory
        if rec.position is not None and tr is not None:
            t_att = (rec.attitude.t_ns - sim.scenario.timing.start_ns).astype(float) * 1e-9
            if out.attitude_type == "novatel_oem7_msgs/msg/INSPVA":
                lat, lon, h = _geodetic(tr, tr.p_enu_m(t_att))
                kw["attitude_extra"] = {"latitude_deg": lat, "longitude_deg": lon,
                                        "height_m": h}
            else:
                kw["attitude_extra"] = {"position_m": np.asarray(rec.position.p_m)}
    if rec.turntable is not None:
        kw.update(turntable_t_ns=rec.turntable.t_ns,
                  turntable_deg=np.degrees(rec.turntable.angle_rad),
                  turntable_type=out.turntable_type, turntable_topic=out.turntable_topic)
    write_recording(
        path,
        mag_t_ns=rec.mag.t_ns,
        mag_nT=rec.mag.values,
        mag_type=out.mag_type,
        mag_topic=out.mag_topic,
        mag_frame_id=out.frame_id,
        mag_log_delay_ns=int(round(out.mag_log_delay_s * 1e9)),
        attitude_log_delay_ns=int(round(out.attitude_log_delay_s * 1e9)),
        compression=out.compression,
        **kw,
    )
    return Path(path)


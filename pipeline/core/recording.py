"""The recording model: typed, immutable containers for what flows between stages.

Every array is numpy, one per quantity, never a Python object per sample. Containers are
frozen dataclasses; stages build new ones with :func:`dataclasses.replace` instead of
mutating. Windows are half-open ``[start_ns, end_ns)`` like mcap's ``iter_messages``.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

I64 = NDArray[np.int64]
F64 = NDArray[np.float64]


class Frame(str, enum.Enum):
    """Coordinate frames of CONVENTIONS.md."""

    MAG = "mag"
    BODY = "body"
    ENU = "enu"


class Role(str, enum.Enum):
    """What a channel is used for."""

    MAGNETOMETER = "magnetometer"
    ATTITUDE = "attitude"
    TURNTABLE = "turntable"
    POSITION = "position"
    OTHER = "other"


class EncodingFamily(str, enum.Enum):
    """Message encoding family of a recording; outputs are written in the input's family."""

    ROS2 = "ros2"
    JSON = "json"


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    if a.flags.writeable:
        a = a.view()
        a.flags.writeable = False
    return a


@dataclass(frozen=True)
class VectorSeries:
    """A time series of 3-vectors.

    Attributes
    ----------
    t_ns : ndarray of int64, shape (N,)
        Sample stamps, ns since the Unix epoch, sorted non-decreasing.
    values : ndarray of float64, shape (N, 3)
        The vectors, in ``unit`` and ``frame``.
    frame : Frame
    unit : str
        ``"nT"`` for magnetic field.

    """

    t_ns: I64
    values: F64
    frame: Frame = Frame.MAG
    unit: str = "nT"

    def __post_init__(self) -> None:
        t = np.asarray(self.t_ns, dtype=np.int64)
        v = np.asarray(self.values, dtype=np.float64).reshape(-1, 3)
        if t.shape[0] != v.shape[0]:
            raise ValueError(f"t_ns has {t.shape[0]} stamps but values has {v.shape[0]} rows")
        object.__setattr__(self, "t_ns", _readonly(t))
        object.__setattr__(self, "values", _readonly(v))
        object.__setattr__(self, "frame", Frame(self.frame))

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def window(self, start_ns: int, end_ns: int) -> VectorSeries:
        """Return the samples with ``start_ns <= t < end_ns``."""
        i0, i1 = np.searchsorted(self.t_ns, [start_ns, end_ns], side="left")
        return dataclasses.replace(self, t_ns=self.t_ns[i0:i1], values=self.values[i0:i1])


@dataclass(frozen=True)
class AttitudeSeries:
    """A time series of attitudes ``q_enu_body`` (Hamilton, scalar-last ``[x, y, z, w]``).

    Attributes
    ----------
    t_ns : ndarray of int64, shape (N,)
    q_enu_body : ndarray of float64, shape (N, 4)
        Unit quaternions rotating body vectors into ENU.

    """

    t_ns: I64
    q_enu_body: F64

    def __post_init__(self) -> None:
        t = np.asarray(self.t_ns, dtype=np.int64)
        q = np.asarray(self.q_enu_body, dtype=np.float64).reshape(-1, 4)
        if t.shape[0] != q.shape[0]:
            raise ValueError(f"t_ns has {t.shape[0]} stamps but q_enu_body has {q.shape[0]} rows")
        object.__setattr__(self, "t_ns", _readonly(t))
        object.__setattr__(self, "q_enu_body", _readonly(q))

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def window(self, start_ns: int, end_ns: int) -> AttitudeSeries:
        """Return the samples with ``start_ns <= t < end_ns``."""
        i0, i1 = np.searchsorted(self.t_ns, [start_ns, end_ns], side="left")
        return dataclasses.replace(self, t_ns=self.t_ns[i0:i1], q_enu_body=self.q_enu_body[i0:i1])


class PositionFrame(str, enum.Enum):
    """Frame of a position series.

    ``enu``: east, north, up in metres from a local origin (a NED source converted; for
    geodetic fixes the WGS-84 local ENU frame at the first valid fix, the series'
    ``origin``). ``attitude_source_local``: the attitude source's own local frame (a
    motion-capture room): its third axis is up (it shares the vertical with ENU) but its
    horizontal axes are rotated about Up by an angle that is not known.
    """

    ENU = "enu"
    ATTITUDE_SOURCE_LOCAL = "attitude_source_local"


@dataclass(frozen=True)
class GeodeticOrigin:
    """The geodetic point a local ENU position frame starts from (CONVENTIONS ``position_origin``).

    Attributes
    ----------
    lat_deg, lon_deg : float
        WGS-84 geodetic latitude and longitude, degrees (north and east positive).
    height_m : float
        Height above the WGS-84 ellipsoid, metres (not above the geoid: GNSS fixes are
        ellipsoidal).

    """

    lat_deg: float
    lon_deg: float
    height_m: float

    def to_dict(self) -> dict[str, float]:
        """``{"lat_deg", "lon_deg", "height_m"}``, the JSON form of ``position_origin``."""
        return {"lat_deg": float(self.lat_deg), "lon_deg": float(self.lon_deg),
                "height_m": float(self.height_m)}


@dataclass(frozen=True)
class PositionSeries:
    """Positions of the platform: from a position channel or carried by the attitude channel.

    Attributes
    ----------
    t_ns : ndarray of int64, shape (N,)
        Stamps, ns since the Unix epoch, sorted: the stamps of the channel the positions
        were read from (a ``NavSatFix`` channel's, or the attitude channel's).
    p_m : ndarray of float64, shape (N, 3)
        Positions, metres, in ``frame``; a row is NaN where the position was lost (a
        motion-capture marker occluded, a GNSS receiver without a fix). NaN rows are kept so
        that ``t_ns`` stays the channel's; users of the series decide what a lost position
        means.
    frame : PositionFrame
    origin : GeodeticOrigin or None
        The geodetic point ``p_m = 0`` stands for, when the positions come from geodetic
        fixes (``NavSatFix``, INSPVA): frame ``enu`` about the first valid fix. None for
        local frames (a motion-capture room), whose origin is not tied to the Earth.
    max_gap_s : float or None
        The gap rule of :meth:`at` when it is given none; None: the series' own (see
        :meth:`at`). A piece of a long recording's positions carries the whole series' rule,
        so that each piece is interpolated as the whole would be.

    """

    t_ns: I64
    p_m: F64
    frame: PositionFrame = PositionFrame.ENU
    origin: GeodeticOrigin | None = None
    max_gap_s: float | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t_ns, dtype=np.int64)
        p = np.asarray(self.p_m, dtype=np.float64).reshape(-1, 3)
        if t.shape[0] != p.shape[0]:
            raise ValueError(f"t_ns has {t.shape[0]} stamps but p_m has {p.shape[0]} rows")
        object.__setattr__(self, "t_ns", _readonly(t))
        object.__setattr__(self, "p_m", _readonly(p))
        object.__setattr__(self, "frame", PositionFrame(self.frame))
        if self.origin is not None and self.frame is not PositionFrame.ENU:
            # a geodetic origin places ENU axes on the Earth; a local frame has none
            raise ValueError(f"a geodetic origin needs frame 'enu', not {self.frame.value!r}")

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def valid(self) -> np.ndarray:
        """Rows with a finite position, (N,) bool."""
        return np.all(np.isfinite(self.p_m), axis=1)

    def at(self, t_ns: np.ndarray, max_gap_s: float | None = None) -> F64:
        """Positions at ``t_ns`` by linear interpolation between valid rows, (M, 3), m.

        NaN outside the span of the valid rows and where the two valid neighbours are more
        than ``max_gap_s`` apart (a lost stretch is not bridged). ``None``: the series'
        ``max_gap_s`` if it has one, else 0.1 s, or 2.5 times the series' median interval
        when that is longer (a 10 Hz GNSS fix is bridged between fixes, a lost
        motion-capture marker is not).
        """
        t = np.asarray(t_ns, dtype=np.int64)
        if max_gap_s is None:
            max_gap_s = self.gap_rule_s()
        ok = self.valid
        tv, pv = self.t_ns[ok], self.p_m[ok]
        out = np.full((t.shape[0], 3), np.nan)
        if tv.shape[0] < 2:
            return out
        i = np.clip(np.searchsorted(tv, t, side="right") - 1, 0, tv.shape[0] - 2)
        t0, t1 = tv[i], tv[i + 1]
        span = (t1 - t0).astype(float)
        s = np.where(span > 0, (t - t0) / np.where(span > 0, span, 1.0), 0.0)
        inside = (t >= tv[0]) & (t <= tv[-1]) & ((span <= max_gap_s * 1e9) | (t == t0) | (t == t1))
        p = pv[i] + s[:, None] * (pv[i + 1] - pv[i])
        out[inside] = p[inside]
        return out

    def gap_rule_s(self) -> float:
        """Return the longest gap between valid rows that :meth:`at` bridges by default, s."""
        if self.max_gap_s is not None:
            return float(self.max_gap_s)
        step = float(np.median(np.diff(self.t_ns))) * 1e-9 if len(self.t_ns) > 1 else 0.0
        return max(0.1, 2.5 * step)

    def window(self, start_ns: int, end_ns: int) -> PositionSeries:
        """Return the samples with ``start_ns <= t < end_ns``."""
        i0, i1 = np.searchsorted(self.t_ns, [start_ns, end_ns], side="left")
        return dataclasses.replace(self, t_ns=self.t_ns[i0:i1], p_m=self.p_m[i0:i1])


@dataclass(frozen=True)
class AngleSeries:
    """A turntable angle channel: rotation about a nominal axis.

    Attributes
    ----------
    t_ns : ndarray of int64, shape (N,)
    angle_rad : ndarray of float64, shape (N,)
        Turntable angle, unwrapped, rad.

    """

    t_ns: I64
    angle_rad: F64

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_ns", _readonly(np.asarray(self.t_ns, dtype=np.int64)))
        object.__setattr__(self, "angle_rad", _readonly(np.asarray(self.angle_rad, dtype=float)))

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass(frozen=True)
class ChannelInfo:
    """One channel of a recording as ``magalign info`` reports it."""

    topic: str
    type: str
    encoding: str
    role: Role
    count: int
    rate_hz: float | None


@dataclass(frozen=True)
class Problem:
    """Something wrong in a recording that was handled (and what was lost).

    ``count`` is the number of samples or messages lost or repaired, 0 when it is not known
    (a damaged chunk without an index: the message says so).
    """

    code: str
    message: str
    count: int = 0


class SegmentKind(str, enum.Enum):
    """What a stretch of a recording is."""

    ROTATION = "rotation"
    STATIC = "static"
    MANOEUVRE = "manoeuvre"
    LINE = "line"
    TURN = "turn"


@dataclass(frozen=True)
class Segment:
    """A half-open window ``[start_ns, end_ns)`` with its motion descriptors.

    Attributes
    ----------
    start_ns, end_ns : int
    kind : SegmentKind
    axis_body, axis_enu : ndarray shape (3,) or None
        Fitted rotation axis (unit vector) in the body and ENU frames.
    twist_deg : float or None
        Total rotation about the axis over the window.
    rate_cv : float or None
        Coefficient of variation of the rotation rate (0 for a constant rate: a time offset
        is then unobservable).
    swing_rms_deg : float or None
        RMS of the swing about the fitted axis (wobble out of the rotation plane).
    coverage : float or None
        Fraction of the sphere of field directions in the body frame the window visits (0..1).

    """

    start_ns: int
    end_ns: int
    kind: SegmentKind
    axis_body: F64 | None = None
    axis_enu: F64 | None = None
    twist_deg: float | None = None
    rate_cv: float | None = None
    swing_rms_deg: float | None = None
    coverage: float | None = None

    def contains(self, t_ns: np.ndarray) -> np.ndarray:
        """Boolean mask of stamps inside the half-open window."""
        return (t_ns >= self.start_ns) & (t_ns < self.end_ns)


@dataclass(frozen=True)
class Recording:
    """What ingest makes of one MCAP file.

    Attributes
    ----------
    path : str
        The file read (never modified).
    channels : tuple of ChannelInfo
    mag : VectorSeries
        Magnetometer, frame ``mag``, nT.
    mag_topic : str
    attitude : AttitudeSeries or None
        ``None`` when the attitude comes from a turntable angle channel.
    attitude_topic : str or None
    turntable : AngleSeries or None
    encoding : EncodingFamily
    mag_frame_id : str
        ``header.frame_id`` of the magnetometer messages.
    attitude_frame_id : str
        Name of the attitude source's body frame: the ``header.frame_id`` of
        ``sensor_msgs/Imu`` messages; empty for the other types, whose frame_id names the
        reference frame (a pose, an INS solution), and when the messages carry none.
    problems : tuple of Problem
        Damage found and handled while reading (recovered bytes, duplicates, ...).
    position : PositionSeries or None
        Positions: from a ``NavSatFix`` channel when the recording has one (WGS-84 fixes as
        local ENU from the first valid fix), else those carried by the attitude channel
        (``PoseStamped`` ``pose.position``, ``Odometry`` ``pose.pose.position``, INSPVA
        latitude/longitude/height as local ENU); None when there are none.
    first_ns : int or None
        The recording's first magnetometer stamp when ``mag`` holds only parts of it (a long
        recording's analysed windows); None: ``mag``'s own first stamp. Times in seconds
        (``windows_s``, a closest approach) count from it (:meth:`origin_ns`).

    """

    path: str
    channels: tuple[ChannelInfo, ...]
    mag: VectorSeries
    mag_topic: str
    attitude: AttitudeSeries | None
    attitude_topic: str | None
    encoding: EncodingFamily = EncodingFamily.ROS2
    turntable: AngleSeries | None = None
    mag_frame_id: str = ""
    attitude_frame_id: str = ""
    problems: tuple[Problem, ...] = ()
    position: PositionSeries | None = None
    first_ns: int | None = None

    def origin_ns(self) -> int:
        """Return the stamp that times in seconds count from: the first magnetometer sample."""
        if self.first_ns is not None:
            return int(self.first_ns)
        return int(self.mag.t_ns[0]) if len(self.mag.t_ns) else 0

    @property
    def duration_s(self) -> float:
        """Span of the magnetometer stamps in seconds."""
        if len(self.mag) < 2:
            return 0.0
        return float(self.mag.t_ns[-1] - self.mag.t_ns[0]) * 1e-9


@dataclass(frozen=True)
class AlignedSeries:
    """Magnetometer samples with the attitude interpolated onto their stamps.

    Attributes
    ----------
    t_ns : ndarray of int64, shape (N,)
        Magnetometer stamps (only those with a usable attitude).
    mag_nT : ndarray, shape (N, 3)
        Magnetometer, frame ``mag``.
    q_enu_body : ndarray, shape (N, 4)
        Attitude at ``t - time_offset_s`` by SLERP.
    time_offset_s : float
        The ``tau`` used for the interpolation (CONVENTIONS).
    index : ndarray of int64, shape (N,)
        Index of each kept sample in the recording's magnetometer series.

    """

    t_ns: I64
    mag_nT: F64
    q_enu_body: F64
    time_offset_s: float = 0.0
    index: I64 | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_ns", _readonly(np.asarray(self.t_ns, dtype=np.int64)))
        object.__setattr__(self, "mag_nT", _readonly(np.asarray(self.mag_nT, dtype=float)))
        object.__setattr__(self, "q_enu_body", _readonly(np.asarray(self.q_enu_body, dtype=float)))
        if self.index is not None:
            object.__setattr__(self, "index", _readonly(np.asarray(self.index, dtype=np.int64)))

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def select(self, mask: np.ndarray) -> AlignedSeries:
        """Return the samples where ``mask`` is true."""
        return AlignedSeries(
            self.t_ns[mask],
            self.mag_nT[mask],
            self.q_enu_body[mask],
            self.time_offset_s,
            None if self.index is None else self.index[mask],
        )

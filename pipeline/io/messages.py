"""Vectorised message encoders: ROS 2 CDR and magalign's JSON channels, whole columns at once.

More in docs/modules.md, ``pipeline.io.messages``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipeline.core.errors import SchemaError
from schemas import JSON_TYPES, ROS2_TYPES
from schemas import MESSAGE_TYPES as _TABLE
from schemas import schema_for as _schema_for

U8 = NDArray[np.uint8]
I64 = NDArray[np.int64]

__all__ = ["encode", "schema_for", "flatten_rows", "WRITTEN_TYPES", "CDR_HEADER"]

#: Encapsulation header of little-endian plain CDR (CDR_LE), as ROS 2 writes it.
CDR_HEADER = b"\x00\x01\x00\x00"

#: the input types magalign writes (schemas.MESSAGE_TYPES is the table of every type)
WRITTEN_TYPES: tuple[str, ...] = ROS2_TYPES + JSON_TYPES

_NS = 1_000_000_000
# GPS time = TAI - 19 s; UTC - GPS offset is 18 s since 2017 (fixed here: the week fields of a
# simulated NovAtel header are informative only, the ROS header stamp carries the time).
_GPS_EPOCH_UNIX_NS = 315_964_800 * _NS
_GPS_LEAP_NS = 18 * _NS
_WEEK_NS = 604_800 * _NS


def schema_for(msg_type: str, variant: str | None = None) -> tuple[str, str, bytes, str]:
    """Return ``(schema_name, schema_encoding, schema_data, message_encoding)`` of a type.

    See :func:`schemas.schema_for`; ``variant`` selects an alternative layout (INSPVA).
    """
    return _schema_for(msg_type, variant)


# --------------------------------------------------------------------------------------------
# CDR layouts


@dataclass
class _Layout:
    """Byte layout of one fixed-length CDR message, built field by field.

    ``pos`` counts from the end of the encapsulation header (CDR alignment origin).
    """

    template: bytearray = field(default_factory=lambda: bytearray(CDR_HEADER))
    pos: int = 0
    slots: dict[str, tuple[str, int, int]] = field(default_factory=dict)  # name -> dtype, off, n

    def _align(self, size: int) -> None:
        pad = (-self.pos) % size
        self.template += b"\x00" * pad
        self.pos += pad

    def prim(self, dtype: str, slot: str | None = None, count: int = 1, const: float = 0) -> None:
        """Append ``count`` primitives of ``dtype``; ``slot`` names the column filled later."""
        dt = np.dtype(dtype)
        self._align(dt.itemsize)
        if slot is not None:
            self.slots[slot] = (dt.str, 4 + self.pos, count)
        self.template += np.full(count, const, dtype=dt).tobytes()
        self.pos += dt.itemsize * count

    def string(self, s: str) -> None:
        """Append a constant CDR string (uint32 length with NUL, bytes, NUL)."""
        b = s.encode("utf-8") + b"\x00"
        self.prim("<u4", const=len(b))
        self.template += b
        self.pos += len(b)

    def header(self, frame_id: str) -> None:
        """``std_msgs/Header``: ``builtin_interfaces/Time stamp`` and ``string frame_id``."""
        self.prim("<i4", "sec")
        self.prim("<u4", "nanosec")
        self.string(frame_id)

    def dtype(self) -> np.dtype:
        """Structured dtype viewing one message row, fields at their byte offsets."""
        names = list(self.slots)
        formats = [(d, (n,)) if n > 1 else d for d, _, n in self.slots.values()]
        offsets = [o for _, o, _ in self.slots.values()]
        return np.dtype(
            {"names": names, "formats": formats, "offsets": offsets, "itemsize": len(self.template)}
        )


def _layout_magnetic_field(frame_id: str, variant: str | None) -> _Layout:
    lay = _Layout()
    lay.header(frame_id)
    lay.prim("<f8", "mag_T", 3)  # geometry_msgs/Vector3 magnetic_field
    lay.prim("<f8", None, 9)  # magnetic_field_covariance: 0 = unknown (REP-145)
    return lay


def _layout_imu(frame_id: str, variant: str | None) -> _Layout:
    lay = _Layout()
    lay.header(frame_id)
    lay.prim("<f8", "q_xyzw", 4)
    lay.prim("<f8", None, 9)  # orientation_covariance
    lay.prim("<f8", "angular_velocity_radps", 3)
    # sensor_msgs/Imu: covariance[0] = -1 means "this quantity is not provided".
    lay.prim("<f8", "angular_velocity_covariance", 9)
    lay.prim("<f8", "linear_acceleration_mps2", 3)
    lay.prim("<f8", "linear_acceleration_covariance", 9)
    return lay


def _layout_pose_stamped(frame_id: str, variant: str | None) -> _Layout:
    lay = _Layout()
    lay.header(frame_id)
    lay.prim("<f8", "position_m", 3)
    lay.prim("<f8", "q_xyzw", 4)
    return lay


def _layout_quaternion_stamped(frame_id: str, variant: str | None) -> _Layout:
    lay = _Layout()
    lay.header(frame_id)
    lay.prim("<f8", "q_xyzw", 4)
    return lay


def _layout_float64(frame_id: str, variant: str | None) -> _Layout:
    lay = _Layout()
    lay.prim("<f8", "value")
    return lay


def _layout_inspva(frame_id: str, variant: str | None) -> _Layout:
    lay = _Layout()
    lay.header(frame_id)
    if variant is None:  # novatel_oem7_msgs/Oem7Header
        lay.string("INSPVA")
        lay.prim("<u2", None, const=507)  # message_id of INSPVA
        lay.prim("u1", None, const=0)  # message_type: OEM7MSGTYPE_LOG
        lay.prim("<u4", "nov_sequence")
        lay.prim("u1", None, const=180)  # time_status: FINESTEERING
        lay.prim("<u2", "gps_week")
        lay.prim("<u4", "gps_week_ms")
    elif variant == "novatel_header":  # NovatelMessageHeader
        lay.string("INSPVA")
        lay.string("COM1")
        lay.prim("<u4", "nov_sequence")
        lay.prim("<f4", None, const=50.0)  # percent_idle_time
        lay.string("FINESTEERING")
        lay.prim("<u4", "gps_week")
        lay.prim("<f8", "gps_seconds")
        lay.prim("<u4", None)  # receiver_status
        lay.prim("<u4", None, const=16809)  # receiver_software_version
    elif variant != "no_nov_header":
        raise SchemaError(f"novatel_oem7_msgs/msg/INSPVA has no layout variant {variant!r}")
    for name in ("latitude_deg", "longitude_deg", "height_m"):
        lay.prim("<f8", name)
    for name in ("north_velocity_mps", "east_velocity_mps", "up_velocity_mps"):
        lay.prim("<f8", name)
    for name in ("roll_deg", "pitch_deg", "azimuth_deg"):
        lay.prim("<f8", name)
    lay.prim("<u4", "status", const=3)  # InertialSolutionStatus INS_SOLUTION_GOOD
    return lay


def _layout_nav_sat_fix(frame_id: str, variant: str | None) -> _Layout:
    lay = _Layout()
    lay.header(frame_id)
    # sensor_msgs/NavSatStatus: status 0 = STATUS_FIX (-1 no fix), service 1 = SERVICE_GPS
    lay.prim("i1", "status", const=0)
    lay.prim("<u2", "service", const=1)
    for name in ("latitude_deg", "longitude_deg", "height_m"):
        lay.prim("<f8", name)
    lay.prim("<f8", "position_covariance", 9)  # m^2, ENU, row-major
    lay.prim("u1", "position_covariance_type", const=0)  # COVARIANCE_TYPE_UNKNOWN
    return lay


_CDR_LAYOUTS: dict[str, Callable[[str, str | None], _Layout]] = {
    "sensor_msgs/msg/MagneticField": _layout_magnetic_field,
    "sensor_msgs/msg/Imu": _layout_imu,
    "geometry_msgs/msg/PoseStamped": _layout_pose_stamped,
    "geometry_msgs/msg/QuaternionStamped": _layout_quaternion_stamped,
    "std_msgs/msg/Float64": _layout_float64,
    "novatel_oem7_msgs/msg/INSPVA": _layout_inspva,
    "sensor_msgs/msg/NavSatFix": _layout_nav_sat_fix,
}

# Columns each type needs from the caller (everything else has a default): schemas' table.
_REQUIRED: dict[str, tuple[str, ...]] = {
    t.name: t.columns for t in _TABLE.values() if t.written and t.columns}


def _stamp_columns(t_ns: I64) -> tuple[NDArray[np.int32], NDArray[np.uint32]]:
    """``builtin_interfaces/Time`` (sec, nanosec) of int64 ns stamps (floor, nanosec >= 0)."""
    sec, nsec = np.divmod(t_ns, _NS)
    if sec.size and (sec.min() < np.iinfo(np.int32).min or sec.max() > np.iinfo(np.int32).max):
        raise SchemaError("stamps outside the int32 seconds range of builtin_interfaces/Time")
    return sec.astype(np.int32), nsec.astype(np.uint32)


def _encode_cdr(
    msg_type: str, t_ns: I64, fields: Mapping[str, ArrayLike], frame_id: str,
    variant: str | None,
) -> tuple[U8, I64]:
    lay = _CDR_LAYOUTS[msg_type](frame_id, variant)
    n = t_ns.shape[0]
    width = len(lay.template)
    buf = np.empty((n, width), dtype=np.uint8)
    buf[:] = np.frombuffer(bytes(lay.template), dtype=np.uint8)
    rec = buf.view(lay.dtype()).reshape(n)
    cols = dict(fields)
    if "sec" in lay.slots:
        cols["sec"], cols["nanosec"] = _stamp_columns(t_ns)
    if msg_type == "sensor_msgs/msg/Imu":
        # REP-145 / sensor_msgs/Imu: covariance element 0 = -1 marks a quantity not provided.
        for q, cov in (("angular_velocity_radps", "angular_velocity_covariance"),
                       ("linear_acceleration_mps2", "linear_acceleration_covariance")):
            if q not in cols and cov not in cols:
                c = np.zeros(9)
                c[0] = -1.0
                cols[cov] = c
    if "gps_week" in lay.slots:
        gps_ns = t_ns - _GPS_EPOCH_UNIX_NS + _GPS_LEAP_NS
        week, in_week_ns = np.divmod(gps_ns, _WEEK_NS)
        cols.setdefault("gps_week", week)
        cols.setdefault("gps_week_ms", in_week_ns // 1_000_000)
        cols.setdefault("gps_seconds", in_week_ns / 1e9)
        cols.setdefault("nov_sequence", np.arange(n))
    for name, (_, _, count) in lay.slots.items():
        if name not in cols:
            continue  # template default
        a = np.asarray(cols[name])
        if count > 1 and a.ndim >= 1 and a.shape[-1] != count:
            raise SchemaError(f"{msg_type}: field {name} needs {count} columns, got {a.shape}")
        if a.ndim >= 1 and a.shape[0] != n and not (a.ndim == 1 and count > 1):
            raise SchemaError(f"{msg_type}: field {name} has {a.shape[0]} rows for {n} stamps")
        rec[name] = a
    offsets = np.arange(n + 1, dtype=np.int64) * width
    return buf.reshape(-1), offsets


# --------------------------------------------------------------------------------------------
# JSON


def _num(a: ArrayLike) -> NDArray[np.bytes_]:
    """Shortest round-trip decimal strings of float64 values, JSON spelling of non-finite."""
    a = np.asarray(a, dtype=np.float64)
    s = a.astype("S")
    bad = ~np.isfinite(a)
    if bad.any():
        s = s.astype("S32")
        s[np.isnan(a)] = b"NaN"
        s[a == np.inf] = b"Infinity"
        s[a == -np.inf] = b"-Infinity"
    return s


def _json_string(s: str) -> bytes:

    return json.dumps(s).encode("utf-8")


def flatten_rows(rows: NDArray[np.bytes_]) -> tuple[U8, I64]:
    """Concatenate a 1-D array of byte strings into ``(data, offsets)`` without a Python loop.

    The strings must contain no NUL bytes (numpy's ``S`` dtype pads with NULs).
    """
    rows = np.ascontiguousarray(rows)
    n = rows.shape[0]
    width = rows.dtype.itemsize
    lengths = np.char.str_len(rows).astype(np.int64)
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(lengths, out=offsets[1:])
    if n == 0 or width == 0:
        return np.zeros(0, dtype=np.uint8), offsets
    u8 = rows.view(np.uint8).reshape(n, width)
    data = u8[np.arange(width) < lengths[:, None]]
    return data, offsets


def _cat(*parts: bytes | NDArray[np.bytes_]) -> NDArray[np.bytes_]:
    out = parts[0]
    for p in parts[1:]:
        out = np.char.add(out, p)
    return np.asarray(out)


def _vec_json(a: ArrayLike, n: int, k: int, name: str, msg_type: str) -> NDArray[np.bytes_]:
    a = np.asarray(a, dtype=np.float64)
    if a.shape != (n, k):
        raise SchemaError(f"{msg_type}: field {name} must have shape ({n}, {k}), got {a.shape}")
    s = _num(a)
    parts: list[bytes | NDArray[np.bytes_]] = [b"["]
    for j in range(k):
        if j:
            parts.append(b", ")
        parts.append(s[:, j])
    parts.append(b"]")
    return _cat(*parts)


def _scalar_json(a: ArrayLike, n: int, name: str, msg_type: str) -> NDArray[np.bytes_]:
    a = np.asarray(a, dtype=np.float64)
    if a.shape != (n,):
        raise SchemaError(f"{msg_type}: field {name} must have shape ({n},), got {a.shape}")
    return _num(a)


def _encode_json(
    msg_type: str, t_ns: I64, fields: Mapping[str, ArrayLike], frame_id: str
) -> tuple[U8, I64]:
    n = t_ns.shape[0]
    head: list[bytes | NDArray[np.bytes_]] = [b'{"t_ns": ', t_ns.astype("S")]
    fid = b', "frame_id": ' + _json_string(frame_id)
    if msg_type == "magalign.Magnetometer":
        parts = [*head, fid, b', "mag_nT": ',
                 _vec_json(fields["mag_nT"], n, 3, "mag_nT", msg_type), b"}"]
    elif msg_type == "magalign.AttitudeQuaternion":
        parts = [*head, fid, b', "q_enu_body": ',
                 _vec_json(fields["q_xyzw"], n, 4, "q_xyzw", msg_type), b"}"]
    elif msg_type == "magalign.AttitudeEuler":
        parts = [*head, fid]
        for name in ("heading_deg", "pitch_deg", "roll_deg"):
            parts += [f', "{name}": '.encode(), _scalar_json(fields[name], n, name, msg_type)]
        parts.append(b"}")
    else:  # magalign.Turntable
        parts = [*head, b', "angle_deg": ',
                 _scalar_json(fields["angle_deg"], n, "angle_deg", msg_type), b"}"]
    if n == 0:
        return np.zeros(0, dtype=np.uint8), np.zeros(1, dtype=np.int64)
    return flatten_rows(_cat(*parts))


# --------------------------------------------------------------------------------------------


def encode(
    msg_type: str,
    t_ns: ArrayLike,
    fields: Mapping[str, ArrayLike],
    frame_id: str = "",
    *,
    variant: str | None = None,
) -> tuple[U8, I64]:
    """Encode N messages of one type at once.

    Parameters
    ----------
    msg_type : str
        One of :data:`WRITTEN_TYPES`.
    t_ns : array_like of int64, shape (N,)
        Header stamps, ns since the Unix epoch (``std_msgs/msg/Float64`` has no header: the
        stamps only fix N there; the MCAP log time carries the time).
    fields : mapping of str to ndarray
        Columns, by type:

        - ``sensor_msgs/msg/MagneticField``: ``mag_T`` (N, 3), tesla, sensor frame.
        - ``sensor_msgs/msg/Imu``: ``q_xyzw`` (N, 4) orientation ``q_enu_body``; optional
          ``angular_velocity_radps`` (N, 3), ``linear_acceleration_mps2`` (N, 3) (without
          them their covariance[0] is -1, "not provided").
        - ``geometry_msgs/msg/PoseStamped``: ``q_xyzw`` (N, 4); optional ``position_m`` (N, 3).
        - ``geometry_msgs/msg/QuaternionStamped``: ``q_xyzw`` (N, 4).
        - ``novatel_oem7_msgs/msg/INSPVA``: ``roll_deg``, ``pitch_deg``, ``azimuth_deg`` (N,)
          (azimuth clockwise from north); optional ``latitude_deg``, ``longitude_deg``,
          ``height_m``, ``north_velocity_mps``, ``east_velocity_mps``, ``up_velocity_mps``,
          ``status`` (default 3, INS_SOLUTION_GOOD).
        - ``std_msgs/msg/Float64``: ``value`` (N,).
        - ``sensor_msgs/msg/NavSatFix``: ``latitude_deg``, ``longitude_deg`` (N,), WGS-84,
          ``height_m`` (N,), above the WGS-84 ellipsoid (the message's ``altitude``);
          optional ``status`` (N,) int (default 0, STATUS_FIX; -1 is no fix), ``service``
          (default 1, SERVICE_GPS), ``position_covariance`` (N, 9) or (9,), m^2, ENU
          row-major (default zeros), ``position_covariance_type`` (default 0, unknown).
        - ``magalign.Magnetometer``: ``mag_nT`` (N, 3).
        - ``magalign.AttitudeQuaternion``: ``q_xyzw`` (N, 4), written as ``q_enu_body``.
        - ``magalign.AttitudeEuler``: ``heading_deg``, ``pitch_deg``, ``roll_deg`` (N,),
          Li 2020 convention.
        - ``magalign.Turntable``: ``angle_deg`` (N,).
    frame_id : str
        ``header.frame_id`` (ROS 2) or ``frame_id`` (JSON), the same for every message.
    variant : str, optional
        Layout variant of the type (INSPVA: ``"no_nov_header"``, ``"novatel_header"``).

    Returns
    -------
    data : ndarray of uint8, shape (sum of lengths,)
        All payloads, concatenated.
    offsets : ndarray of int64, shape (N + 1,)
        Message ``i`` is ``data[offsets[i]:offsets[i + 1]]``.

    Raises
    ------
    SchemaError
        Unknown type or variant, missing or mis-shaped field.

    """
    if msg_type not in WRITTEN_TYPES:
        raise SchemaError(
            f"cannot encode message type {msg_type!r}",
            hint=f"supported: {', '.join(WRITTEN_TYPES)}",
        )
    t = np.asarray(t_ns)
    if t.ndim != 1 or not (np.issubdtype(t.dtype, np.integer) or t.size == 0):
        raise SchemaError(f"{msg_type}: t_ns must be a 1-D integer array (ns), got {t.dtype}")
    t = t.astype(np.int64, copy=False)
    missing = [k for k in _REQUIRED[msg_type] if k not in fields]
    if missing:
        raise SchemaError(f"{msg_type}: missing field(s) {', '.join(missing)}")
    if msg_type in JSON_TYPES:
        if variant is not None:
            raise SchemaError(f"JSON type {msg_type} has no variant {variant!r}")
        return _encode_json(msg_type, t, fields, frame_id)
    return _encode_cdr(msg_type, t, fields, frame_id, variant)


# --------------------------------------------------------------------------------------------
# output-only messages of the corrected MCAP (schemas.OUTPUT_ROS2_TYPES / OUTPUT_JSON_TYPES)


def encode_tf_static(
    t_ns: int, parent_frame_id: str, child_frame_id: str, q_xyzw: ArrayLike,
    translation_m: ArrayLike = (0.0, 0.0, 0.0),
) -> tuple[U8, I64]:
    """Encode one ``tf2_msgs/msg/TFMessage`` holding one ``geometry_msgs/TransformStamped``.

    Parameters
    ----------
    t_ns : int
        Header stamp, ns since the Unix epoch.
    parent_frame_id, child_frame_id : str
        ``header.frame_id`` and ``child_frame_id``: the transform gives the child frame's
        pose in the parent frame, ``p_parent = R @ p_child + translation`` (REP-105/tf2).
    q_xyzw : array_like, shape (4,)
        Rotation ``R`` as a unit quaternion, scalar last.
    translation_m : array_like, shape (3,)
        Translation in metres.

    Returns
    -------
    data, offsets
        One message, in the layout of :func:`encode`.

    """
    lay = _Layout()
    lay.prim("<u4", const=1)  # sequence<TransformStamped> of length 1
    lay.header(parent_frame_id)
    lay.string(child_frame_id)
    lay.prim("<f8", "translation_m", 3)
    lay.prim("<f8", "q_xyzw", 4)
    buf = np.frombuffer(bytes(lay.template), dtype=np.uint8).copy()
    rec = buf.view(lay.dtype())
    sec, nsec = _stamp_columns(np.array([t_ns], dtype=np.int64))
    rec["sec"], rec["nanosec"] = sec[0], nsec[0]
    rec["translation_m"] = np.asarray(translation_m, dtype=float).reshape(3)
    rec["q_xyzw"] = np.asarray(q_xyzw, dtype=float).reshape(4)
    return buf, np.array([0, buf.shape[0]], dtype=np.int64)


def encode_field_magnitude_json(t_ns: ArrayLike, magnitude_nT: ArrayLike,
                                frame_id: str = "") -> tuple[U8, I64]:
    """Encode N ``magalign.FieldMagnitude`` JSON messages ``{t_ns, frame_id, magnitude_nT}``.

    NaN is written as ``NaN``, as on every JSON channel of magalign.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    n = t.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.uint8), np.zeros(1, dtype=np.int64)
    v = _scalar_json(magnitude_nT, n, "magnitude_nT", "magalign.FieldMagnitude")
    return flatten_rows(_cat(b'{"t_ns": ', t.astype("S"), b', "frame_id": ',
                             _json_string(frame_id), b', "magnitude_nT": ', v, b"}"))

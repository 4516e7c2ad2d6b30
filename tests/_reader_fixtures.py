"""Recordings for the READER's tests, written with the mcap packages' own writers.

The ROS 2 message definitions are embedded here (standard ROS 2 Humble texts, in the
concatenated form mcap_ros2/rosbag2 store), so the reader is tested against files it did
not write itself.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_ros2._dynamic import serialize_dynamic
from mcap_ros2.writer import Writer as Ros2Writer

SEP = "=" * 80 + "\n"
HEADER = (SEP + "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
          + SEP + "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n")
VECTOR3 = SEP + "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
QUAT = SEP + "MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"

DEFS = {
    "sensor_msgs/msg/MagneticField": (
        "std_msgs/Header header\ngeometry_msgs/Vector3 magnetic_field\n"
        "float64[9] magnetic_field_covariance\n" + HEADER + VECTOR3),
    "sensor_msgs/msg/Imu": (
        "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\n"
        "float64[9] orientation_covariance # Row major about x, y, z axes\n"
        "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n"
        + HEADER + QUAT + VECTOR3),
    "geometry_msgs/msg/PoseStamped": (
        "std_msgs/Header header\nPose pose\n" + HEADER
        + SEP + "MSG: geometry_msgs/Pose\nPoint position\nQuaternion orientation\n"
        + SEP + "MSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n" + QUAT),
    "geometry_msgs/msg/QuaternionStamped": (
        "std_msgs/Header header\ngeometry_msgs/Quaternion quaternion\n" + HEADER + QUAT),
    "std_msgs/msg/Float64": "float64 data\n",
    "nav_msgs/msg/Odometry": (
        "std_msgs/Header header\nstring child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n"
        + HEADER
        + SEP + "MSG: geometry_msgs/PoseWithCovariance\nPose pose\nfloat64[36] covariance\n"
        + SEP + "MSG: geometry_msgs/Pose\nPoint position\nQuaternion orientation\n"
        + SEP + "MSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n" + QUAT
        + SEP + "MSG: geometry_msgs/TwistWithCovariance\nTwist twist\nfloat64[36] covariance\n"
        + SEP + "MSG: geometry_msgs/Twist\nVector3 linear\nVector3 angular\n" + VECTOR3),
}

_INS_STATUS = (SEP + "MSG: novatel_oem7_msgs/InertialSolutionStatus\n"
               "uint32 INS_INACTIVE = 0\nuint32 INS_SOLUTION_GOOD = 3\nuint32 status\n")
_INSPVA_BODY = ("std_msgs/Header header\nOem7Header nov_header\nfloat64 latitude\n"
                "float64 longitude\nfloat64 height\nfloat64 north_velocity\n"
                "float64 east_velocity\nfloat64 up_velocity\nfloat64 roll\nfloat64 pitch\n"
                "float64 azimuth\nInertialSolutionStatus status\n")
#: two driver versions of the Oem7Header: the newer one has receiver status fields
INSPVA_DEFS = {
    "old": _INSPVA_BODY + HEADER + SEP + (
        "MSG: novatel_oem7_msgs/Oem7Header\nstring message_name\nuint16 message_id\n"
        "uint8 message_type\nuint32 sequence_number\nuint8 time_status\n"
        "uint16 gps_week_number\nuint32 gps_week_milliseconds\n") + _INS_STATUS,
    "new": _INSPVA_BODY + HEADER + SEP + (
        "MSG: novatel_oem7_msgs/Oem7Header\nuint16 OEM7MSGTYPE_LOG = 0\n"
        "string message_name\nuint16 message_id\nuint8 message_type\n"
        "uint32 sequence_number\nuint8 time_status\nuint16 gps_week_number\n"
        "uint32 gps_week_milliseconds\nuint32 receiver_status\nuint16 reserved\n"
        "uint16 receiver_sw_version\n") + _INS_STATUS,
}

T0 = 1_700_000_000 * 1_000_000_000


def stamp(t: int) -> dict:
    return {"sec": int(t // 1_000_000_000), "nanosec": int(t % 1_000_000_000)}


def header(t: int, frame: str) -> dict:
    return {"stamp": stamp(t), "frame_id": frame}


def ros_msg(msg_type: str, t: int, value: np.ndarray, frame: str = "f") -> dict:
    """A ROS 2 message dict of ``msg_type`` holding ``value`` (tesla, quaternion, rpy...)."""
    v = [float(x) for x in np.atleast_1d(value)]
    if msg_type == "sensor_msgs/msg/MagneticField":
        return {"header": header(t, frame),
                "magnetic_field": {"x": v[0], "y": v[1], "z": v[2]},
                "magnetic_field_covariance": [0.0] * 9}
    q = dict(zip("xyzw", v, strict=False))
    if msg_type == "sensor_msgs/msg/Imu":
        z3 = {"x": 0.0, "y": 0.0, "z": 0.0}
        return {"header": header(t, frame), "orientation": q,
                "orientation_covariance": [0.0] * 9, "angular_velocity": z3,
                "angular_velocity_covariance": [-1.0] + [0.0] * 8, "linear_acceleration": z3,
                "linear_acceleration_covariance": [-1.0] + [0.0] * 8}
    if msg_type == "geometry_msgs/msg/PoseStamped":
        return {"header": header(t, frame),
                "pose": {"position": {"x": 1.0, "y": 2.0, "z": 3.0}, "orientation": q}}
    if msg_type == "nav_msgs/msg/Odometry":
        z3 = {"x": 0.0, "y": 0.0, "z": 0.0}
        # position: x = seconds since T0, so that the test can check the order of rows
        pos = {"x": (t - T0) * 1e-9, "y": 2.0, "z": 3.0}
        return {"header": header(t, frame), "child_frame_id": "base_link",
                "pose": {"pose": {"position": pos, "orientation": q}, "covariance": [0.0] * 36},
                "twist": {"twist": {"linear": z3, "angular": z3}, "covariance": [0.0] * 36}}
    if msg_type == "geometry_msgs/msg/QuaternionStamped":
        return {"header": header(t, frame), "quaternion": q}
    if msg_type == "std_msgs/msg/Float64":
        return {"data": v[0]}
    if msg_type.startswith("novatel_oem7_msgs/msg/INSPVA"):
        nov = {"message_name": "INSPVA" if len(frame) % 2 else "INSPVAX_LONGER_NAME",
               "message_id": 507, "message_type": 0, "sequence_number": 7, "time_status": 180,
               "gps_week_number": 2280, "gps_week_milliseconds": 123456,
               "receiver_status": 1, "reserved": 0, "receiver_sw_version": 17000}
        return {"header": header(t, frame), "nov_header": nov, "latitude": 52.5,
                "longitude": 13.4, "height": 40.0, "north_velocity": 0.0,
                "east_velocity": 0.0, "up_velocity": 0.0, "roll": v[0], "pitch": v[1],
                "azimuth": v[2], "status": {"status": 3}}
    raise ValueError(msg_type)


def _as_type(name: str) -> str:
    if name.startswith("novatel"):
        return "novatel_oem7_msgs/msg/INSPVA"
    return name if name in DEFS else "geometry_msgs/msg/QuaternionStamped"


def write_ros2(path: Path, streams: list[tuple[str, str, str, np.ndarray, np.ndarray, list]],
               *, compression: CompressionType = CompressionType.ZSTD,
               chunk_size: int = 1 << 20, log_delay_ns: int = 500_000,
               log_times: dict[int, np.ndarray] | None = None) -> Path:
    """Write streams ``(topic, schema_name, definition, t_ns, values, frames)`` with
    mcap_ros2's Writer, interleaved by log time (= stamp + a delay) as a logger would."""
    events = []
    for k, (_topic, _name, _d, t_ns, _v, _f) in enumerate(streams):
        if log_times is not None and k in log_times:
            events += [(int(t), k, i) for i, t in enumerate(log_times[k])]
        else:
            events += [(int(t) + log_delay_ns * (k + 1), k, i) for i, t in enumerate(t_ns)]
    events.sort()
    with open(path, "wb") as fh:
        w = Ros2Writer(fh, chunk_size=chunk_size, compression=compression)
        schemas = [w.register_msgdef(name, d) for _t, name, d, *_ in streams]
        for log, k, i in events:
            topic, name, _d, t_ns, vals, frames = streams[k]
            msg_type = _as_type(name)
            w.write_message(topic, schemas[k], ros_msg(msg_type, int(t_ns[i]), vals[i],
                                                      frames[i % len(frames)]),
                            log_time=log, publish_time=log, sequence=i)
        w.finish()
    return path


def write_ros2_raw(path: Path, streams, *, use_chunking: bool = True,
                   compression: CompressionType = CompressionType.ZSTD,
                   chunk_size: int = 1 << 20, enable_crcs: bool = True) -> Path:
    """Like :func:`write_ros2` but through mcap's plain Writer (non-chunked files possible),
    encoding with mcap_ros2's dynamic serializer."""
    events = []
    for k, (_topic, _name, _d, t_ns, _v, _f) in enumerate(streams):
        events += [(int(t) + 500_000 * (k + 1), k, i) for i, t in enumerate(t_ns)]
    events.sort()
    with open(path, "wb") as fh:
        w = McapWriter(fh, chunk_size=chunk_size, compression=compression,
                       use_chunking=use_chunking, enable_crcs=enable_crcs)
        w.start("ros2", "test")
        ids, enc = [], []
        for topic, name, d, *_ in streams:
            sid = w.register_schema(name, "ros2msg", d.encode())
            ids.append(w.register_channel(topic, "cdr", sid))
            enc.append(serialize_dynamic(name, d)[name])
        for log, k, i in events:
            _topic, name, _d, t_ns, vals, frames = streams[k]
            msg_type = _as_type(name)
            data = enc[k](ros_msg(msg_type, int(t_ns[i]), vals[i], frames[i % len(frames)]))
            w.add_message(ids[k], log, data, log, sequence=i)
        w.finish()
    return path


def json_schema(name: str) -> bytes:
    return (Path(__file__).resolve().parents[1] / "schemas" / f"{name}.json").read_bytes()


def write_json(path: Path, streams: list[tuple[str, str, np.ndarray, list[dict]]]) -> Path:
    """Write JSON channels ``(topic, schema_name, t_ns, message dicts)`` with mcap's Writer."""
    events = []
    for k, (_topic, _name, t_ns, _m) in enumerate(streams):
        events += [(int(t) + 300_000 * (k + 1), k, i) for i, t in enumerate(t_ns)]
    events.sort()
    with open(path, "wb") as fh:
        w = McapWriter(fh, compression=CompressionType.ZSTD)
        w.start("", "test")
        ids = []
        for topic, name, *_ in streams:
            sid = w.register_schema(name, "jsonschema", json_schema(name))
            ids.append(w.register_channel(topic, "json", sid))
        for log, k, i in events:
            w.add_message(ids[k], log, json.dumps(streams[k][3][i]).encode(), log)
        w.finish()
    return path


def motion(n: int = 400, rate_hz: float = 100.0, seed: int = 0):
    """Stamps, a field in the mag frame (T) and a rotating attitude: a small, valid data set."""
    rng = np.random.default_rng(seed)
    t = T0 + np.round(np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    yaw = np.linspace(0, 2 * np.pi, n)
    pitch = 0.3 * np.sin(np.linspace(0, 6, n))
    from pipeline.core.geometry import quat_mul
    qz = np.stack([np.zeros(n), np.zeros(n), np.sin(yaw / 2), np.cos(yaw / 2)], -1)
    qx = np.stack([np.sin(pitch / 2), np.zeros(n), np.zeros(n), np.cos(pitch / 2)], -1)
    q = quat_mul(qz, qx)
    q = q * np.where(rng.random(n) < 0.3, -1.0, 1.0)[:, None]  # both hemispheres occur
    mag_T = (np.array([20e-6, 5e-6, -40e-6]) + 1e-7 * rng.standard_normal((n, 3)))
    return t, mag_T, q

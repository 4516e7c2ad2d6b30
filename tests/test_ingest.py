"""READER: decoding of every supported type against mcap_ros2's own decoder."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _reader_fixtures import DEFS, INSPVA_DEFS, T0, motion, write_json, write_ros2, write_ros2_raw
from mcap.reader import make_reader
from mcap.writer import CompressionType
from mcap_ros2.decoder import DecoderFactory

from pipeline.core.errors import ChannelError, SchemaError
from pipeline.core.geometry import li2020_euler_to_quat, novatel_to_quat, quat_rotate
from pipeline.core.recording import EncodingFamily, Role
from pipeline.io.mcap_read import read_raw_channels, read_recording
from stages.context import Context
from stages.ingest import Ingest

MAG = "sensor_msgs/msg/MagneticField"
FRAMES = ["imu", "magnetometer_link_long", "m"]  # per-message frame_id lengths vary


def _theirs(path):
    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _s, ch, m, ros in reader.iter_decoded_messages(log_time_order=False):
            out.setdefault(ch.topic, []).append(_Msg(ros, m.log_time))
    return out


class _Msg:
    def __init__(self, ros_msg, log_time_ns):
        self.ros_msg = ros_msg
        self.log_time_ns = log_time_ns


def _q_same(a, b, tol=1e-12):
    """Quaternions equal up to sign (same rotation)."""
    d = np.abs(np.sum(a * b, axis=1))
    return np.all(np.abs(d - 1.0) < tol)


@pytest.mark.parametrize("att_type", ["sensor_msgs/msg/Imu", "geometry_msgs/msg/PoseStamped",
                                      "geometry_msgs/msg/QuaternionStamped"])
def test_cdr_quaternion_types_match_mcap_ros2(tmp_path, att_type):
    t, mag_T, q = motion(300)
    p = write_ros2(tmp_path / "r.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, FRAMES),
        ("/att", att_type, DEFS[att_type], t + 1_234_567, q, FRAMES[::-1]),
    ], chunk_size=4096)
    rec = read_recording(p)
    theirs = _theirs(p)
    m = theirs["/mag"]
    t_ref = np.array([x.ros_msg.header.stamp.sec * 10**9 + x.ros_msg.header.stamp.nanosec
                      for x in m])
    v_ref = np.array([[x.ros_msg.magnetic_field.x, x.ros_msg.magnetic_field.y,
                       x.ros_msg.magnetic_field.z] for x in m]) * 1e9
    np.testing.assert_array_equal(rec.mag.t_ns, t_ref)
    np.testing.assert_allclose(rec.mag.values, v_ref, rtol=1e-15, atol=0)
    np.testing.assert_array_equal(rec.mag.t_ns, t)
    assert rec.mag_frame_id == "imu" and rec.encoding is EncodingFamily.ROS2
    def qof(msg):
        o = {"sensor_msgs/msg/Imu": lambda r: r.orientation,
             "geometry_msgs/msg/PoseStamped": lambda r: r.pose.orientation,
             "geometry_msgs/msg/QuaternionStamped": lambda r: r.quaternion}[att_type](msg)
        return [o.x, o.y, o.z, o.w]
    q_ref = np.array([qof(x.ros_msg) for x in theirs["/att"]])
    np.testing.assert_array_equal(rec.attitude.t_ns, t + 1_234_567)
    assert _q_same(rec.attitude.q_enu_body, q_ref)
    assert rec.problems == ()
    roles = {c.topic: c.role for c in rec.channels}
    assert roles == {"/mag": Role.MAGNETOMETER, "/att": Role.ATTITUDE}


@pytest.mark.parametrize("layout", ["old", "new"])
def test_inspva_two_header_layouts(tmp_path, layout):
    n = 120
    t, mag_T, _ = motion(n)
    rng = np.random.default_rng(3)
    rpy = np.stack([rng.uniform(-20, 20, n), rng.uniform(-10, 10, n),
                    rng.uniform(0, 360, n)], -1)
    p = write_ros2(tmp_path / "r.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, ["mag"]),
        ("/ins", "novatel_oem7_msgs/msg/INSPVA", INSPVA_DEFS[layout], t, rpy, FRAMES),
    ])
    rec = read_recording(p)
    ref = np.array([[x.ros_msg.roll, x.ros_msg.pitch, x.ros_msg.azimuth]
                    for x in _theirs(p)["/ins"]])
    np.testing.assert_array_equal(ref, rpy)
    assert _q_same(rec.attitude.q_enu_body, novatel_to_quat(rpy[:, 0], rpy[:, 1], rpy[:, 2]))


def test_inspva_azimuth_is_clockwise_from_north(tmp_path):
    t, mag_T, _ = motion(20)
    rpy = np.tile([0.0, 0.0, 90.0], (20, 1))  # level, heading east
    p = write_ros2(tmp_path / "r.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, ["mag"]),
        ("/ins", "novatel_oem7_msgs/msg/INSPVA", INSPVA_DEFS["new"], t, rpy, ["ins"]),
    ])
    q = read_recording(p).attitude.q_enu_body
    forward_enu = quat_rotate(q, [0.0, 1.0, 0.0])  # NovAtel body y is forward
    np.testing.assert_allclose(forward_enu, np.tile([1.0, 0.0, 0.0], (20, 1)), atol=1e-12)


def test_float64_turntable_uses_log_time(tmp_path):
    t, mag_T, _ = motion(100)
    ang = np.mod(np.linspace(0, 720, 100), 360.0)
    p = write_ros2(tmp_path / "r.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, ["mag"]),
        ("/table", "std_msgs/msg/Float64", DEFS["std_msgs/msg/Float64"], t, ang, [""]),
    ], log_delay_ns=1000)
    rec = read_recording(p)
    assert rec.attitude is None
    logs = np.array([x.log_time_ns for x in _theirs(p)["/table"]])
    np.testing.assert_array_equal(rec.turntable.t_ns, logs)
    np.testing.assert_allclose(rec.turntable.angle_rad, np.radians(np.linspace(0, 720, 100)),
                               atol=1e-9)


@pytest.mark.parametrize("compression", [CompressionType.NONE, CompressionType.LZ4])
@pytest.mark.parametrize("chunked", [True, False])
def test_compressions_and_unchunked(tmp_path, compression, chunked):
    t, mag_T, q = motion(200)
    p = write_ros2_raw(tmp_path / "r.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, FRAMES),
        ("/att", "sensor_msgs/msg/Imu", DEFS["sensor_msgs/msg/Imu"], t, q, ["b"]),
    ], use_chunking=chunked, compression=compression, chunk_size=2048)
    rec = read_recording(p)
    np.testing.assert_allclose(rec.mag.values, mag_T * 1e9, rtol=1e-15)
    assert _q_same(rec.attitude.q_enu_body, q)
    assert rec.problems == ()


def _json_msgs(t, key, rows, frame="mag"):
    return [{"t_ns": int(a), "frame_id": frame, key: [float(x) for x in r]}
            for a, r in zip(t, rows, strict=True)]


def test_json_magnetometer_and_quaternion(tmp_path):
    t, mag_T, q = motion(150)
    p = write_json(tmp_path / "j.mcap", [
        ("/mag", "magalign.Magnetometer", t, _json_msgs(t, "mag_nT", mag_T * 1e9)),
        ("/q", "magalign.AttitudeQuaternion", t + 5, _json_msgs(t + 5, "q_enu_body", q)),
    ])
    rec = read_recording(p)
    assert rec.encoding is EncodingFamily.JSON and rec.mag_frame_id == "mag"
    np.testing.assert_array_equal(rec.mag.values, mag_T * 1e9)
    np.testing.assert_array_equal(rec.attitude.t_ns, t + 5)
    assert _q_same(rec.attitude.q_enu_body, q)


def test_json_euler_li2020_and_turntable(tmp_path):
    t, mag_T, _ = motion(90)
    rng = np.random.default_rng(5)
    hpr = np.stack([rng.uniform(0, 359, 90), rng.uniform(-30, 30, 90),
                    rng.uniform(-30, 30, 90)], -1)
    eul = [{"t_ns": int(a), "frame_id": "b", "heading_deg": h, "pitch_deg": pp, "roll_deg": r}
           for a, (h, pp, r) in zip(t, hpr.tolist(), strict=True)]
    tt = [{"t_ns": int(a), "angle_deg": float(i)} for i, a in enumerate(t)]
    p = write_json(tmp_path / "j.mcap", [
        ("/mag", "magalign.Magnetometer", t, _json_msgs(t, "mag_nT", mag_T * 1e9)),
        ("/euler", "magalign.AttitudeEuler", t, eul),
        ("/tt", "magalign.Turntable", t, tt),
    ])
    rec = read_recording(p)
    r = np.radians(hpr)
    assert _q_same(rec.attitude.q_enu_body, li2020_euler_to_quat(r[:, 0], r[:, 1], r[:, 2]))
    np.testing.assert_allclose(rec.turntable.angle_rad, np.radians(np.arange(90.0)))


def test_json_message_not_matching_stored_schema(tmp_path):
    t, mag_T, q = motion(30)
    bad = [{"t_ns": int(a), "mag_nT": [1.0, 2.0]} for a in t]  # two components only
    p = write_json(tmp_path / "j.mcap", [
        ("/mag", "magalign.Magnetometer", t, bad),
        ("/q", "magalign.AttitudeQuaternion", t, _json_msgs(t, "q_enu_body", q)),
    ])
    with pytest.raises(SchemaError, match="JSON Schema"):
        read_recording(p)


def test_roles_two_candidates_and_topic_option(tmp_path):
    t, mag_T, q = motion(60)
    streams = [("/mag_a", MAG, DEFS[MAG], t, mag_T, ["a"]),
               ("/mag_b", MAG, DEFS[MAG], t, mag_T * 2, ["b"]),
               ("/att", "sensor_msgs/msg/Imu", DEFS["sensor_msgs/msg/Imu"], t, q, ["b"])]
    p = write_ros2(tmp_path / "r.mcap", streams)
    with pytest.raises(ChannelError) as ei:
        read_recording(p)
    msg = ei.value.one_line()
    assert "/mag_a" in msg and "/mag_b" in msg and "--mag" in msg
    assert ei.value.role == "magnetometer" and ei.value.exit_code == 2
    rec = Ingest(mag_topic="/mag_b").run(Context(source=str(p))).recording
    np.testing.assert_allclose(rec.mag.values, mag_T * 2e9, rtol=1e-15)
    assert rec.mag_topic == "/mag_b" and rec.mag_frame_id == "b"


def test_missing_attitude_and_unknown_schema(tmp_path):
    t, mag_T, q = motion(60)
    mag_def = DEFS[MAG]
    p = write_ros2(tmp_path / "r.mcap", [
        ("/mag", MAG, mag_def, t, mag_T, ["a"]),
        ("/odd", "acme_msgs/msg/Orientation", DEFS["geometry_msgs/msg/QuaternionStamped"],
         t, q, ["b"])])
    with pytest.raises(ChannelError, match="no attitude") as ei:
        read_recording(p)
    assert "acme_msgs/msg/Orientation" in str(ei.value)
    with pytest.raises(SchemaError, match="not a supported attitude type"):
        read_recording(p, attitude_topic="/odd")
    with pytest.raises(ChannelError, match="no channel with topic /nope"):
        read_recording(p, attitude_topic="/nope")


def test_definition_without_needed_field(tmp_path):
    t, mag_T, q = motion(40)
    broken = "std_msgs/Header header\ngeometry_msgs/Vector3 field\n" + DEFS[MAG].split(
        "float64[9] magnetic_field_covariance\n", 1)[1]
    p = write_ros2_raw(tmp_path / "r.mcap", [
        ("/mag", MAG, broken, t, mag_T, ["a"]),
        ("/att", "sensor_msgs/msg/Imu", DEFS["sensor_msgs/msg/Imu"], t, q, ["b"])])
    with pytest.raises(SchemaError, match="magnetic_field"):
        read_recording(p)


def test_raw_channels_equal_mcap_reader(tmp_path):
    t, mag_T, q = motion(250)
    p = write_ros2(tmp_path / "r.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, FRAMES),
        ("/att", "sensor_msgs/msg/Imu", DEFS["sensor_msgs/msg/Imu"], t, q, ["b"])],
        chunk_size=3000)
    raw = {c.topic: c for c in read_raw_channels(p)}
    with open(p, "rb") as fh:
        ref: dict[str, list] = {}
        for sch, ch, m in make_reader(fh).iter_messages(log_time_order=False):
            ref.setdefault(ch.topic, []).append((sch, ch, m))
    for topic, msgs in ref.items():
        rc = raw[topic]
        assert rc.schema_name == msgs[0][0].name and rc.schema_data == msgs[0][0].data
        assert rc.message_encoding == "cdr" and rc.schema_encoding == "ros2msg"
        np.testing.assert_array_equal(rc.log_time_ns, [m.log_time for _s, _c, m in msgs])
        np.testing.assert_array_equal(rc.sequence, [m.sequence for _s, _c, m in msgs])
        for i in (0, 7, len(msgs) - 1):
            assert rc.data[rc.offsets[i]:rc.offsets[i + 1]].tobytes() == msgs[i][2].data
        assert rc.offsets[-1] == sum(len(m.data) for _s, _c, m in msgs)


def test_ingest_stage_contract():
    assert Ingest.requires == frozenset({"source"})
    assert Ingest.provides == frozenset({"recording"})
    with pytest.raises(Exception):  # noqa: B017  frozen dataclass
        Ingest().mag_topic = "/x"  # type: ignore[misc]
    assert json.dumps(T0)  # fixture epoch is an int


def _mag_att(tmp_path, mag_T, name="sat.mcap"):
    t, _, q = motion(len(mag_T))
    return t, write_ros2(tmp_path / name, [("/mag", MAG, DEFS[MAG], t, mag_T, ["imu"]),
                                           ("/att", "sensor_msgs/msg/Imu",
                                            DEFS["sensor_msgs/msg/Imu"], t, q, ["b"])])


def test_samples_pinned_at_a_rail_are_dropped(tmp_path):
    """An axis clipped at its range limit: those samples go, like NaN samples (issue 9)."""
    _, mag_T, _ = motion(300)
    rail = float(np.quantile(mag_T[:, 1], 0.25))
    pinned = mag_T[:, 1] <= rail
    mag_T[:, 1] = np.maximum(mag_T[:, 1], rail)
    t, p = _mag_att(tmp_path, mag_T)
    rec = read_recording(p)
    sat = [pr for pr in rec.problems if pr.code == "saturated"]
    assert len(sat) == 1 and sat[0].count == int(pinned.sum()) > 60
    assert "dropped" in sat[0].message and "axis y" in sat[0].message
    np.testing.assert_array_equal(rec.mag.t_ns, t[~pinned])
    np.testing.assert_allclose(rec.mag.values, mag_T[~pinned] * 1e9, rtol=1e-15)


def test_rails_on_two_axes_pinning_most_samples_are_refused(tmp_path):
    """Each rail holds fewer than half of the samples, both together more: refused."""
    from pipeline.core.errors import DataQualityError

    _, mag_T, _ = motion(300)
    lo = float(np.quantile(mag_T[:, 0], 0.4))
    hi = float(np.quantile(mag_T[:, 2], 0.6))
    n_pinned = int(np.count_nonzero((mag_T[:, 0] <= lo) | (mag_T[:, 2] >= hi)))
    assert n_pinned > 150  # the noise of the axes is independent: about 64 %
    mag_T[:, 0] = np.maximum(mag_T[:, 0], lo)
    mag_T[:, 2] = np.minimum(mag_T[:, 2], hi)
    _, p = _mag_att(tmp_path, mag_T)
    with pytest.raises(DataQualityError, match=r"saturated") as ei:
        read_recording(p)
    assert f"{n_pinned / 300:.0%}" in ei.value.message

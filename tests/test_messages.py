"""Message encoders (pipeline.io.messages) and schemas, checked against mcap_ros2 and jsonschema."""

from __future__ import annotations

import io
import json
import math
import re

import jsonschema
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer

from pipeline.core.errors import SchemaError
from pipeline.io.messages import WRITTEN_TYPES, encode, schema_for
from schemas import JSON_TYPES, ROS2_TYPES, VARIANTS, json_schema

T0 = 1_700_000_000_123_456_789


def _decoder(msg_type: str, variant: str | None = None):
    name, enc, data, _ = schema_for(msg_type, variant)
    # A fresh factory per schema: mcap_ros2 caches decoders by schema id.
    return DecoderFactory().decoder_for("cdr", Schema(id=1, name=name, encoding=enc, data=data))


def _split(data: np.ndarray, offsets: np.ndarray) -> list[bytes]:
    return [bytes(data[offsets[i] : offsets[i + 1]]) for i in range(len(offsets) - 1)]


def _columns(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return {
        "mag_T": rng.normal(size=(n, 3)) * 3e-5,
        "mag_nT": rng.normal(size=(n, 3)) * 3e4,
        "q_xyzw": q / np.linalg.norm(q, axis=1, keepdims=True),
        "roll_deg": rng.uniform(-180, 180, n),
        "pitch_deg": rng.uniform(-90, 90, n),
        "azimuth_deg": rng.uniform(0, 360, n),
        "heading_deg": rng.uniform(-180, 180, n),
        "latitude_deg": rng.uniform(-90, 90, n),
        "longitude_deg": rng.uniform(-180, 180, n),
        "height_m": rng.uniform(-100, 3000, n),
        "value": rng.normal(size=n),
        "angle_deg": rng.uniform(0, 360, n),
    }


def _stamp_ns(m) -> int:
    return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec


def _check_ros2(msg_type: str, variant, t_ns, cols, frame_id, data, offsets) -> None:
    dec = _decoder(msg_type, variant)
    for i, raw in enumerate(_split(data, offsets)):
        m = dec(raw)
        if msg_type == "std_msgs/msg/Float64":
            assert m.data == cols["value"][i]
            continue
        assert _stamp_ns(m) == t_ns[i]
        assert m.header.frame_id == frame_id
        if msg_type == "sensor_msgs/msg/MagneticField":
            f = m.magnetic_field
            assert [f.x, f.y, f.z] == list(cols["mag_T"][i])
            assert m.magnetic_field_covariance == [0.0] * 9
        elif msg_type in ("sensor_msgs/msg/Imu", "geometry_msgs/msg/PoseStamped",
                          "geometry_msgs/msg/QuaternionStamped"):
            o = {"sensor_msgs/msg/Imu": lambda m: m.orientation,
                 "geometry_msgs/msg/PoseStamped": lambda m: m.pose.orientation,
                 "geometry_msgs/msg/QuaternionStamped": lambda m: m.quaternion}[msg_type](m)
            assert [o.x, o.y, o.z, o.w] == list(cols["q_xyzw"][i])
            if msg_type == "sensor_msgs/msg/Imu":
                # "not provided" marker of sensor_msgs/Imu for the absent quantities
                assert m.angular_velocity_covariance[0] == -1.0
                assert m.linear_acceleration_covariance[0] == -1.0
        elif msg_type == "sensor_msgs/msg/NavSatFix":
            assert (m.latitude, m.longitude, m.altitude) == (
                cols["latitude_deg"][i], cols["longitude_deg"][i], cols["height_m"][i])
            assert (m.status.status, m.status.service) == (0, 1)  # STATUS_FIX, SERVICE_GPS
            assert m.position_covariance == [0.0] * 9 and m.position_covariance_type == 0
        else:  # INSPVA
            assert (m.roll, m.pitch, m.azimuth) == (
                cols["roll_deg"][i], cols["pitch_deg"][i], cols["azimuth_deg"][i])
            assert (m.latitude, m.longitude, m.height) == (
                cols["latitude_deg"][i], cols["longitude_deg"][i], cols["height_m"][i])
            assert m.status.status == 3
            if variant is None:
                assert m.nov_header.message_name == "INSPVA"
                assert m.nov_header.message_id == 507
                assert m.nov_header.sequence_number == i
            elif variant == "novatel_header":
                assert m.nov_header.gps_time_status == "FINESTEERING"
            else:
                assert not hasattr(m, "nov_header")


ROS2_CASES = [(t, v) for t in ROS2_TYPES for v in VARIANTS.get(t, (None,))]


@pytest.mark.parametrize(("msg_type", "variant"), ROS2_CASES)
@pytest.mark.parametrize("frame_id", ["", "mag", "imu_link_7"])
def test_cdr_decodes_with_mcap_ros2(msg_type, variant, frame_id):
    n = 40
    t_ns = T0 + np.arange(n, dtype=np.int64) * 3_500_001
    cols = _columns(n)
    data, offsets = encode(msg_type, t_ns, cols, frame_id, variant=variant)
    assert data.dtype == np.uint8 and offsets.dtype == np.int64 and offsets.shape == (n + 1,)
    assert bytes(data[:4]) == b"\x00\x01\x00\x00"
    _check_ros2(msg_type, variant, t_ns, cols, frame_id, data, offsets)


def _ros2_dict(msg_type: str, t: int, cols: dict, i: int, frame_id: str) -> dict:
    sec, nsec = divmod(t, 1_000_000_000)
    hdr = {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": frame_id}
    q = dict(zip("xyzw", cols["q_xyzw"][i].tolist(), strict=True))
    if msg_type == "sensor_msgs/msg/MagneticField":
        return {"header": hdr, "magnetic_field": dict(zip("xyz", cols["mag_T"][i].tolist(),
                                                          strict=True)),
                "magnetic_field_covariance": [0.0] * 9}
    if msg_type == "sensor_msgs/msg/Imu":
        cov = [-1.0] + [0.0] * 8
        return {"header": hdr, "orientation": q, "orientation_covariance": [0.0] * 9,
                "angular_velocity": {"x": 0.0, "y": 0.0, "z": 0.0},
                "angular_velocity_covariance": cov,
                "linear_acceleration": {"x": 0.0, "y": 0.0, "z": 0.0},
                "linear_acceleration_covariance": cov}
    if msg_type == "geometry_msgs/msg/PoseStamped":
        return {"header": hdr, "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                                        "orientation": q}}
    if msg_type == "geometry_msgs/msg/QuaternionStamped":
        return {"header": hdr, "quaternion": q}
    if msg_type == "std_msgs/msg/Float64":
        return {"data": float(cols["value"][i])}
    if msg_type == "sensor_msgs/msg/NavSatFix":
        return {"header": hdr, "status": {"status": 0, "service": 1},
                "latitude": float(cols["latitude_deg"][i]),
                "longitude": float(cols["longitude_deg"][i]),
                "altitude": float(cols["height_m"][i]), "position_covariance": [0.0] * 9,
                "position_covariance_type": 0}
    raise AssertionError(msg_type)


@pytest.mark.parametrize("msg_type", [t for t in ROS2_TYPES if "INSPVA" not in t])
def test_cdr_bytes_identical_to_mcap_ros2_writer(msg_type):
    n = 25
    t_ns = T0 + np.arange(n, dtype=np.int64) * 1_000_003
    cols = _columns(n, seed=3)
    data, offsets = encode(msg_type, t_ns, cols, "sensor")
    name, _, s_data, _ = schema_for(msg_type)
    buf = io.BytesIO()
    w = Ros2Writer(buf)
    schema = w.register_msgdef(name, s_data.decode())
    for i, t in enumerate(t_ns.tolist()):
        w.write_message("/x", schema, _ros2_dict(msg_type, t, cols, i, "sensor"), log_time=t)
    w.finish()
    buf.seek(0)
    theirs = [m.data for _, _, m in make_reader(buf).iter_messages()]
    assert theirs == _split(data, offsets)


def test_inspva_bytes_identical_to_mcap_ros2_writer():
    n = 10
    t_ns = T0 + np.arange(n, dtype=np.int64) * 50_000_000
    cols = _columns(n, seed=4)
    data, offsets = encode("novatel_oem7_msgs/msg/INSPVA", t_ns, cols, "ins")
    name, _, s_data, _ = schema_for("novatel_oem7_msgs/msg/INSPVA")
    dec = _decoder("novatel_oem7_msgs/msg/INSPVA")
    buf = io.BytesIO()
    w = Ros2Writer(buf)
    schema = w.register_msgdef(name, s_data.decode())
    for i, raw in enumerate(_split(data, offsets)):
        m = dec(raw)  # re-encode what mcap_ros2 decoded from our bytes
        nh = m.nov_header
        msg = {
            "header": {"stamp": {"sec": m.header.stamp.sec, "nanosec": m.header.stamp.nanosec},
                       "frame_id": m.header.frame_id},
            "nov_header": {k: getattr(nh, k) for k in (
                "message_name", "message_id", "message_type", "sequence_number", "time_status",
                "gps_week_number", "gps_week_milliseconds")},
            **{k: getattr(m, k) for k in ("latitude", "longitude", "height", "north_velocity",
                                           "east_velocity", "up_velocity", "roll", "pitch",
                                           "azimuth")},
            "status": {"status": m.status.status},
        }
        w.write_message("/ins", schema, msg, log_time=int(t_ns[i]))
    w.finish()
    buf.seek(0)
    assert [m.data for _, _, m in make_reader(buf).iter_messages()] == _split(data, offsets)
    # GPS week of the stamp: 2023-11-14 is in GPS week 2288.
    assert dec(_split(data, offsets)[0]).nov_header.gps_week_number == 2288


def test_inspva_variants_differ_in_layout():
    n = 3
    t_ns = T0 + np.arange(n, dtype=np.int64)
    cols = _columns(n)
    lengths = {v: encode("novatel_oem7_msgs/msg/INSPVA", t_ns, cols, "ins", variant=v)[1][1]
               for v in VARIANTS["novatel_oem7_msgs/msg/INSPVA"]}
    assert len(set(lengths.values())) == 3
    texts = {v: schema_for("novatel_oem7_msgs/msg/INSPVA", v)[2]
             for v in VARIANTS["novatel_oem7_msgs/msg/INSPVA"]}
    assert re.search(rb"^Oem7Header\s+nov_header$", texts[None], re.M)
    assert re.search(rb"^NovatelMessageHeader\s+nov_header$", texts["novatel_header"], re.M)
    assert b"nov_header" not in texts["no_nov_header"]


@pytest.mark.parametrize("msg_type", JSON_TYPES)
def test_json_messages_parse_validate_and_round_trip(msg_type):
    n = 30
    t_ns = T0 + np.arange(n, dtype=np.int64) * 7
    cols = _columns(n, seed=5)
    data, offsets = encode(msg_type, t_ns, cols, "mag")
    name, s_enc, s_data, m_enc = schema_for(msg_type)
    assert (name, s_enc, m_enc) == (msg_type, "jsonschema", "json")
    schema = json.loads(s_data)
    jsonschema.Draft202012Validator.check_schema(schema)
    validator = jsonschema.Draft202012Validator(schema)
    for i, raw in enumerate(_split(data, offsets)):
        d = json.loads(raw)
        validator.validate(d)
        assert d["t_ns"] == t_ns[i]
        if msg_type == "magalign.Magnetometer":
            assert d["mag_nT"] == cols["mag_nT"][i].tolist() and d["frame_id"] == "mag"
        elif msg_type == "magalign.AttitudeQuaternion":
            assert d["q_enu_body"] == cols["q_xyzw"][i].tolist()
        elif msg_type == "magalign.AttitudeEuler":
            assert [d["heading_deg"], d["pitch_deg"], d["roll_deg"]] == [
                cols["heading_deg"][i], cols["pitch_deg"][i], cols["roll_deg"][i]]
        else:
            assert d["angle_deg"] == cols["angle_deg"][i]


def test_json_non_finite_and_frame_id_escaping():
    mag = np.array([[np.nan, np.inf, -np.inf], [-0.0, 5e-324, 1.7976931348623157e308]])
    data, offsets = encode("magalign.Magnetometer", np.array([0, 1]), {"mag_nT": mag},
                           'we"ird\\frame')
    a, b = (json.loads(x) for x in _split(data, offsets))
    assert math.isnan(a["mag_nT"][0]) and a["mag_nT"][1:] == [math.inf, -math.inf]
    assert b["mag_nT"] == mag[1].tolist() and math.copysign(1, b["mag_nT"][0]) == -1
    assert a["frame_id"] == 'we"ird\\frame'


def test_schema_for_every_type_and_errors():
    for t in WRITTEN_TYPES:
        name, s_enc, s_data, m_enc = schema_for(t)
        assert name == t and s_data
        assert (s_enc, m_enc) == (("jsonschema", "json") if t in JSON_TYPES
                                  else ("ros2msg", "cdr"))
        if t in JSON_TYPES:
            assert json_schema(t)["$schema"].endswith("2020-12/schema")
    with pytest.raises(SchemaError):
        schema_for("sensor_msgs/msg/Temperature")
    with pytest.raises(SchemaError):
        schema_for("novatel_oem7_msgs/msg/INSPVA", "nonexistent")
    with pytest.raises(SchemaError):
        encode("sensor_msgs/msg/MagneticField", np.arange(3), {"q_xyzw": np.zeros((3, 4))})
    with pytest.raises(SchemaError):
        encode("sensor_msgs/msg/MagneticField", np.arange(3), {"mag_T": np.zeros((2, 3))})
    with pytest.raises(SchemaError):
        encode("magalign.Magnetometer", np.arange(3), {"mag_nT": np.zeros((3, 2))})


def test_empty_and_negative_stamps():
    data, offsets = encode("sensor_msgs/msg/MagneticField", np.zeros(0, np.int64),
                           {"mag_T": np.zeros((0, 3))})
    assert data.size == 0 and offsets.tolist() == [0]
    data, offsets = encode("magalign.Turntable", np.zeros(0, np.int64),
                           {"angle_deg": np.zeros(0)})
    assert data.size == 0 and offsets.tolist() == [0]
    t = np.array([-1, -1_000_000_000, -1_500_000_000])
    data, offsets = encode("geometry_msgs/msg/QuaternionStamped", t,
                           {"q_xyzw": np.tile([0.0, 0, 0, 1], (3, 1))})
    dec = _decoder("geometry_msgs/msg/QuaternionStamped")
    got = [dec(r).header.stamp for r in _split(data, offsets)]
    assert [(s.sec, s.nanosec) for s in got] == [(-1, 999_999_999), (-1, 0), (-2, 500_000_000)]


# ------------------------------------------------------------------ property tests

finite = st.floats(allow_nan=False, allow_infinity=True, width=64)
stamps = hnp.arrays(np.int64, st.integers(1, 12),
                    elements=st.integers(-(2**31) * 10**9, (2**31 - 1) * 10**9))
frame_ids = st.text(st.characters(min_codepoint=32, max_codepoint=0x2FFF,
                                  blacklist_categories=("Cs",)), max_size=12)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(t_ns=stamps, data=st.data(), frame_id=frame_ids)
def test_property_magnetic_field_round_trip(t_ns, data, frame_id):
    n = t_ns.shape[0]
    mag = data.draw(hnp.arrays(np.float64, (n, 3), elements=finite))
    raw, offsets = encode("sensor_msgs/msg/MagneticField", t_ns, {"mag_T": mag}, frame_id)
    dec = _decoder("sensor_msgs/msg/MagneticField")
    for i, r in enumerate(_split(raw, offsets)):
        m = dec(r)
        assert _stamp_ns(m) == t_ns[i] and m.header.frame_id == frame_id
        f = m.magnetic_field
        np.testing.assert_array_equal([f.x, f.y, f.z], mag[i])


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(t_ns=stamps, data=st.data(), variant=st.sampled_from(VARIANTS[
    "novatel_oem7_msgs/msg/INSPVA"]), frame_id=frame_ids)
def test_property_inspva_round_trip(t_ns, data, variant, frame_id):
    n = t_ns.shape[0]
    t_ns = np.abs(t_ns)  # GPS weeks are unsigned: stamps after 1980
    t_ns = t_ns + 315_964_800 * 10**9
    t_ns = np.minimum(t_ns, (2**31 - 1) * 10**9)
    ang = data.draw(hnp.arrays(np.float64, (n, 3), elements=finite))
    cols = {"roll_deg": ang[:, 0], "pitch_deg": ang[:, 1], "azimuth_deg": ang[:, 2]}
    raw, offsets = encode("novatel_oem7_msgs/msg/INSPVA", t_ns, cols, frame_id,
                          variant=variant)
    dec = _decoder("novatel_oem7_msgs/msg/INSPVA", variant)
    for i, r in enumerate(_split(raw, offsets)):
        m = dec(r)
        assert _stamp_ns(m) == t_ns[i]
        np.testing.assert_array_equal([m.roll, m.pitch, m.azimuth], ang[i])


@settings(max_examples=40, deadline=None)
@given(t_ns=stamps, data=st.data(), frame_id=frame_ids)
def test_property_json_round_trip_exact(t_ns, data, frame_id):
    n = t_ns.shape[0]
    q = data.draw(hnp.arrays(np.float64, (n, 4), elements=st.floats(allow_nan=False,
                                                                  allow_infinity=False)))
    raw, offsets = encode("magalign.AttitudeQuaternion", t_ns, {"q_xyzw": q}, frame_id)
    for i, r in enumerate(_split(raw, offsets)):
        d = json.loads(r)
        assert d["t_ns"] == t_ns[i] and d["frame_id"] == frame_id
        np.testing.assert_array_equal(d["q_enu_body"], q[i])


def test_one_table_of_message_types():
    """schemas.MESSAGE_TYPES is the only list: reader, writer, simulator and schemas follow it."""
    import pipeline.app.simulate as simulate
    import pipeline.io.mcap_decode as reader
    from pipeline.io import messages
    from schemas import MESSAGE_TYPES, MessageRole, schema_text

    by_role = {MessageRole.MAGNETOMETER: (reader.MAG_TYPES, simulate.MAG_TYPES),
               MessageRole.ATTITUDE: (reader.ATTITUDE_TYPES, simulate.ATTITUDE_TYPES),
               MessageRole.TURNTABLE: (reader.TURNTABLE_TYPES, simulate.TURNTABLE_TYPES),
               MessageRole.POSITION: (reader.POSITION_TYPES, simulate.POSITION_TYPES)}
    for t in MESSAGE_TYPES.values():
        if t.role is MessageRole.OUTPUT:
            assert all(t.short_name not in r for r, _ in by_role.values())
            assert schema_text(t.name)
            continue
        read, simulated = by_role[t.role]
        assert t.short_name in read, t.name
        assert (t.name in simulated) == t.written, t.name
        if t.written:  # a stored schema, an encoder and its columns for every layout variant
            for v in t.variants:
                assert schema_text(t.name, v)
            assert t.name in messages.WRITTEN_TYPES and t.columns
            assert (t.name in messages._CDR_LAYOUTS) == (t.encoding == "ros2")
        if t.quaternion:
            assert reader._CDR_QUAT[t.short_name] == t.quaternion
    n_input = sum(t.role is not MessageRole.OUTPUT for t in MESSAGE_TYPES.values())
    assert sum(len(r) for r, _ in by_role.values()) == n_input

"""Positions from a ``sensor_msgs/msg/NavSatFix`` channel: WGS-84 fixes as local ENU metres.

The recordings are written by ``mcap_ros2``'s own writer with a hand-written ROS 2 NavSatFix
definition (the reader never saw it), beside a magnetometer and an attitude channel; the
expected ENU positions are computed here, independently of magalign, through ECEF. Tolerances
are physical (1 mm of position).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _reader_fixtures import DEFS, SEP, T0, motion, ros_msg
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer

from pipeline.app.cli import main
from pipeline.core.errors import ChannelError, InputError, SchemaError
from pipeline.core.recording import GeodeticOrigin, PositionFrame, PositionSeries, Role
from pipeline.io.mcap_decode import geodetic_to_local_enu, local_enu_to_geodetic
from pipeline.io.mcap_header import read_recording_header
from pipeline.io.mcap_read import iter_recording_chunks, read_recording
from pipeline.io.mcap_write import write_recording

MAG = "sensor_msgs/msg/MagneticField"
IMU = "sensor_msgs/msg/Imu"
FIX = "sensor_msgs/msg/NavSatFix"

#: sensor_msgs/msg/NavSatFix as ROS 2 Humble ships it (comments, constants and all), in the
#: concatenated form rosbag2 and mcap_ros2 store
FIX_DEF = (
    "# Navigation Satellite fix for any Global Navigation Satellite System\n"
    "#\n# Specified using the WGS 84 reference ellipsoid\n\n"
    "# header.stamp specifies the ROS time for this measurement\n"
    "std_msgs/Header header\n\n"
    "# Satellite fix status information.\n"
    "NavSatStatus status\n\n"
    "# Latitude [degrees]. Positive is north of equator; negative is south.\n"
    "float64 latitude\n\n"
    "# Longitude [degrees]. Positive is east of prime meridian; negative is west.\n"
    "float64 longitude\n\n"
    "# Altitude [m]. Positive is above the WGS 84 ellipsoid\n"
    "# (quiet NaN if no altitude is available).\n"
    "float64 altitude\n\n"
    "# Position covariance [m^2] defined relative to a tangential plane\n"
    "float64[9] position_covariance\n\n"
    "uint8 COVARIANCE_TYPE_UNKNOWN = 0\n"
    "uint8 COVARIANCE_TYPE_APPROXIMATED = 1\n"
    "uint8 COVARIANCE_TYPE_DIAGONAL_KNOWN = 2\n"
    "uint8 COVARIANCE_TYPE_KNOWN = 3\n\n"
    "uint8 position_covariance_type\n"
    + SEP + "MSG: std_msgs/Header\n"
    "# Standard metadata for higher-level stamped data types.\n"
    "builtin_interfaces/Time stamp\n"
    "string frame_id\n"
    + SEP + "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
    + SEP + "MSG: sensor_msgs/NavSatStatus\n"
    "# Navigation Satellite fix status for any Global Navigation Satellite System.\n"
    "int8 STATUS_NO_FIX =  -1        # unable to fix position\n"
    "int8 STATUS_FIX =      0        # unaugmented fix\n"
    "int8 STATUS_SBAS_FIX = 1        # with satellite-based augmentation\n"
    "int8 STATUS_GBAS_FIX = 2        # with ground-based augmentation\n\n"
    "int8 status\n\n"
    "uint16 SERVICE_GPS =     1\n"
    "uint16 SERVICE_GLONASS = 2\n"
    "uint16 SERVICE_COMPASS = 4      # includes BeiDou.\n"
    "uint16 SERVICE_GALILEO = 8\n\n"
    "uint16 service\n"
)

# ------------------------------------------------------------------ independent geodesy
_A = 6378137.0  # WGS-84 semi-major axis, m
_F = 1.0 / 298.257223563  # WGS-84 flattening
_E2 = _F * (2.0 - _F)


def _ecef(lat_deg, lon_deg, h_m):
    """WGS-84 geodetic -> ECEF, m (textbook form)."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = _A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    return np.stack([(n + h_m) * np.cos(lat) * np.cos(lon),
                     (n + h_m) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - _E2) + h_m) * np.sin(lat)], axis=-1)


def _enu(lat_deg, lon_deg, h_m, origin):
    """ECEF difference from ``origin`` (lat, lon, h) rotated into its east, north, up axes."""
    lat0, lon0 = np.radians(origin[0]), np.radians(origin[1])
    d = _ecef(lat_deg, lon_deg, h_m) - _ecef(*origin)
    rot = np.array([
        [-np.sin(lon0), np.cos(lon0), 0.0],
        [-np.sin(lat0) * np.cos(lon0), -np.sin(lat0) * np.sin(lon0), np.cos(lat0)],
        [np.cos(lat0) * np.cos(lon0), np.cos(lat0) * np.sin(lon0), np.sin(lat0)]])
    return d @ rot.T


# ------------------------------------------------------------------ recordings
#: a GNSS track near Zurich: about 2.6 km east-west, 1.9 km north-south, 30 m up and down;
#: large enough that the Earth's curvature (d^2 / 2R: ~0.1 m at 1.3 km) shows in ENU
ORIGIN = (47.3769, 8.5417, 447.0)
N_MAG, MAG_HZ = 2000, 100.0
N_FIX, FIX_HZ = 100, 5.0


def _track(n: int = N_FIX, origin=ORIGIN):
    """Stamps and fixes (lat deg, lon deg, ellipsoidal height m) of the GNSS track."""
    t = T0 + np.round(np.arange(n) * 1e9 / FIX_HZ).astype(np.int64)
    s = np.linspace(0.0, 2.0 * np.pi, n)
    lat = origin[0] + 0.0085 * np.sin(s)
    lon = origin[1] + 0.017 * (1.0 - np.cos(s))
    h = origin[2] + 15.0 * np.sin(3.0 * s)
    return t, np.stack([lat, lon, h], axis=-1)


def _fix_msg(t: int, fix, status: int = 0, frame: str = "gnss_antenna") -> dict:
    return {"header": {"stamp": {"sec": int(t // 1_000_000_000),
                                 "nanosec": int(t % 1_000_000_000)}, "frame_id": frame},
            "status": {"status": status, "service": 1},
            "latitude": float(fix[0]), "longitude": float(fix[1]), "altitude": float(fix[2]),
            "position_covariance": [0.02, 0, 0, 0, 0.02, 0, 0, 0, 0.09],
            "position_covariance_type": 2}


def _write(path: Path, fix_channels: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
           attitude: str = IMU, fix_frames: tuple[str, ...] = ("gnss_antenna",)) -> Path:
    """Magnetometer, attitude and NavSatFix channels through mcap_ros2's writer.

    ``fix_channels``: topic -> (stamps, fixes (N, 3), status (N,)). Messages are logged in
    receive order (stamp plus a delay per channel), the way a logger writes them.
    ``fix_frames`` are the NavSatFix frame ids in turn (lengths that differ shift every
    later field: the reader's general path instead of its one-layout fast path).
    """
    t, mag_T, q = motion(N_MAG, rate_hz=MAG_HZ)
    events: list[tuple[int, int, str, dict]] = []
    for i in range(N_MAG):
        events.append((int(t[i]) + 400_000, 0, "/mag", ros_msg(MAG, int(t[i]), mag_T[i], "m")))
        events.append((int(t[i]) + 700_000, 1, "/att", ros_msg(attitude, int(t[i]), q[i], "b")))
    for k, (topic, (tf, fixes, status)) in enumerate(fix_channels.items()):
        for i in range(len(tf)):
            events.append((int(tf[i]) + 30_000_000, 2 + k, topic,
                           _fix_msg(int(tf[i]), fixes[i], int(status[i]),
                                    fix_frames[i % len(fix_frames)])))
    events.sort(key=lambda e: (e[0], e[1]))
    with open(path, "wb") as fh:
        w = Ros2Writer(fh, chunk_size=16_384)
        schemas = {"/mag": w.register_msgdef(MAG, DEFS[MAG]),
                   "/att": w.register_msgdef(attitude, DEFS[attitude])}
        fix_schema = w.register_msgdef(FIX, FIX_DEF)
        for log, _k, topic, msg in events:
            w.write_message(topic, schemas.get(topic, fix_schema), msg, log_time=log,
                            publish_time=log)
        w.finish()
    return path


def _status(n: int, no_fix=()) -> np.ndarray:
    s = np.zeros(n, dtype=np.int64)
    s[list(no_fix)] = -1
    return s


# ------------------------------------------------------------------ tests
def test_fixes_become_enu_metres_about_the_first_valid_fix(tmp_path):
    t, fixes = _track()
    fixes[40, 0] = np.nan  # a receiver reporting a fix with no latitude: lost
    status = _status(N_FIX, no_fix=(0, 1, 2, 70))  # no fix at start (acquiring) and once
    rec = read_recording(_write(tmp_path / "r.mcap", {"/gnss/fix": (t, fixes, status)}))

    roles = {c.topic: c.role for c in rec.channels}
    assert roles == {"/mag": Role.MAGNETOMETER, "/att": Role.ATTITUDE,
                     "/gnss/fix": Role.POSITION}
    p = rec.position
    assert isinstance(p, PositionSeries) and p.frame is PositionFrame.ENU
    # the NavSatFix stamps (header.stamp, not the log time 30 ms later)
    assert np.array_equal(p.t_ns, t)
    lost = np.zeros(N_FIX, dtype=bool)
    lost[[0, 1, 2, 40, 70]] = True
    assert np.array_equal(~p.valid, lost)
    # origin: the first valid fix (row 3), not the first message
    o = p.origin
    assert o is not None
    assert o.lat_deg == pytest.approx(fixes[3, 0], abs=1e-12)
    assert o.lon_deg == pytest.approx(fixes[3, 1], abs=1e-12)
    assert o.height_m == pytest.approx(fixes[3, 2], abs=1e-9)
    assert o.to_dict() == pytest.approx({"lat_deg": fixes[3, 0], "lon_deg": fixes[3, 1],
                                         "height_m": fixes[3, 2]})
    want = _enu(fixes[:, 0], fixes[:, 1], fixes[:, 2], tuple(fixes[3]))
    assert np.max(np.abs(p.p_m[~lost] - want[~lost])) < 1e-3  # m
    # the track is large enough to need the ellipsoid: a flat plane (up = height difference)
    # is off by decimetres, so the 1 mm above checks the curvature, not just the scale
    assert np.max(np.abs(want[~lost, 2] - (fixes[~lost, 2] - fixes[3, 2]))) > 0.1
    assert np.max(np.hypot(want[~lost, 0], want[~lost, 1])) > 2000.0
    lost_pr = [pr for pr in rec.problems if pr.code == "position_lost"]
    assert len(lost_pr) == 1 and lost_pr[0].count == 5
    # the attitude and magnetometer are read as without the position channel
    assert len(rec.mag) == N_MAG and rec.attitude is not None and len(rec.attitude) == N_MAG


def test_out_of_order_fixes_are_sorted_before_the_origin_is_chosen(tmp_path):
    t, fixes = _track()
    order = np.r_[5:N_FIX, 0:5]  # the first five fixes logged last
    path = tmp_path / "r.mcap"
    _write(path, {"/fix": (t[order], fixes[order], _status(N_FIX))},
           fix_frames=("gps", "gnss_antenna_link", "a"))
    p = read_recording(path).position
    assert p is not None and p.origin is not None
    assert np.array_equal(p.t_ns, t)
    assert p.origin.lat_deg == pytest.approx(fixes[0, 0], abs=1e-12)
    want = _enu(fixes[:, 0], fixes[:, 1], fixes[:, 2], tuple(fixes[0]))
    assert np.max(np.abs(p.p_m - want)) < 1e-3


def test_navsatfix_wins_over_attitude_positions(tmp_path):
    t, fixes = _track()
    both = read_recording(_write(tmp_path / "both.mcap", {"/fix": (t, fixes, _status(N_FIX))},
                                 attitude="geometry_msgs/msg/PoseStamped"))
    assert both.position is not None and both.position.frame is PositionFrame.ENU
    assert both.position.origin is not None
    assert np.array_equal(both.position.t_ns, t)
    # without the NavSatFix channel the pose's own positions are used (local frame)
    pose = read_recording(_write(tmp_path / "pose.mcap", {},
                                 attitude="geometry_msgs/msg/PoseStamped"))
    assert pose.position is not None
    assert pose.position.frame is PositionFrame.ATTITUDE_SOURCE_LOCAL
    assert pose.position.origin is None


def test_two_navsatfix_channels_need_position_topic(tmp_path):
    t, fixes = _track()
    t2, fixes2 = _track(origin=(47.38, 8.55, 500.0))
    path = _write(tmp_path / "two.mcap", {"/gnss1/fix": (t, fixes, _status(N_FIX)),
                                          "/gnss2/fix": (t2, fixes2, _status(N_FIX))})
    rec = read_recording(path)
    # positions are optional: no choice means none used, and a problem that says why
    assert rec.position is None
    amb = [pr for pr in rec.problems if pr.code == "position_ambiguous"]
    assert len(amb) == 1 and "/gnss1/fix" in amb[0].message and "/gnss2/fix" in amb[0].message
    assert "position_topic" in amb[0].message
    chosen = read_recording(path, position_topic="/gnss2/fix")
    assert chosen.position is not None and chosen.position.origin is not None
    assert chosen.position.origin.height_m == pytest.approx(fixes2[0, 2], abs=1e-9)
    want = _enu(fixes2[:, 0], fixes2[:, 1], fixes2[:, 2], tuple(fixes2[0]))
    assert np.max(np.abs(chosen.position.p_m - want)) < 1e-3
    assert not any(pr.code == "position_ambiguous" for pr in chosen.problems)
    # a topic that is absent, or not a NavSatFix: an input error naming the file
    with pytest.raises(ChannelError) as absent:
        read_recording(path, position_topic="/gnss3/fix")
    with pytest.raises(SchemaError) as wrong:
        read_recording(path, position_topic="/mag")
    for exc in (absent.value, wrong.value):
        assert isinstance(exc, InputError) and exc.path == str(path)
        assert str(path) in exc.one_line()
    # the header of the two-pass path chooses the same way
    head = read_recording_header(path, position_topic="/gnss1/fix")
    assert head.position is not None and head.position.origin is not None
    assert head.position.origin.height_m == pytest.approx(fixes[0, 2], abs=1e-9)


def test_no_valid_fix_at_all(tmp_path, capsys):
    t, fixes = _track()
    path = _write(tmp_path / "nofix.mcap", {"/fix": (t, fixes, _status(N_FIX, range(N_FIX)))})
    rec = read_recording(path)
    assert rec.position is None  # the Imu carries no positions either
    nofix = [pr for pr in rec.problems if pr.code == "no_position_fix"]
    assert len(nofix) == 1 and nofix[0].count == N_FIX and "/fix" in nofix[0].message
    assert main(["info", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert any(pr["code"] == "no_position_fix" for pr in out["problems"])
    # the two-pass header still says that the recording has positions (a receiver acquiring)
    head = read_recording_header(path)
    assert head.position is not None and head.position.origin is None
    assert not head.position.valid.any()


def test_without_a_valid_fix_the_attitude_positions_are_used(tmp_path):
    """An INS's own fixes (INSPVA) stand in when the NavSatFix channel never has a fix."""
    t, mag_T, q = motion(N_MAG, rate_hz=MAG_HZ)
    tf, fixes = _track()
    ins = np.stack([np.interp(t, tf, fixes[:, k]) for k in range(3)], axis=-1)
    path = write_recording(
        tmp_path / "ins.mcap", mag_t_ns=t, mag_nT=mag_T * 1e9, attitude_t_ns=t, q_enu_body=q,
        attitude_type="novatel_oem7_msgs/msg/INSPVA",
        attitude_extra={"latitude_deg": ins[:, 0], "longitude_deg": ins[:, 1],
                        "height_m": ins[:, 2]},
        position_t_ns=tf, position_fix=fixes, position_extra={"status": np.full(N_FIX, -1)})
    rec = read_recording(path)
    p = rec.position
    assert p is not None and p.frame is PositionFrame.ENU and np.array_equal(p.t_ns, t)
    assert p.origin is not None
    assert p.origin.to_dict() == pytest.approx(
        {"lat_deg": ins[0, 0], "lon_deg": ins[0, 1], "height_m": ins[0, 2]}, abs=1e-9)
    want = _enu(ins[:, 0], ins[:, 1], ins[:, 2], tuple(ins[0]))
    assert np.max(np.abs(p.p_m - want)) < 1e-3
    assert any(pr.code == "no_position_fix" for pr in rec.problems)


def test_info_lists_the_position_channel(tmp_path, capsys):
    t, fixes = _track()
    path = _write(tmp_path / "r.mcap", {"/gnss/fix": (t, fixes, _status(N_FIX, (7,)))})
    assert main(["info", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    ch = {c["topic"]: c for c in out["channels"]}
    assert ch["/gnss/fix"]["role"] == "position"
    assert ch["/gnss/fix"]["type"] == FIX and ch["/gnss/fix"]["count"] == N_FIX
    assert ch["/gnss/fix"]["rate_hz"] == pytest.approx(FIX_HZ, rel=1e-6)
    assert ch["/mag"]["role"] == "magnetometer" and ch["/att"]["role"] == "attitude"
    lost = [pr for pr in out["problems"] if pr["code"] == "position_lost"]
    assert len(lost) == 1 and lost[0]["count"] == 1
    assert main(["info", str(path)]) == 0
    table = capsys.readouterr().out
    row = next(line for line in table.splitlines() if line.startswith("/gnss/fix"))
    assert "position" in row.split()


def test_long_recording_paths_ignore_positions_without_breaking(tmp_path):
    t, fixes = _track()
    path = _write(tmp_path / "r.mcap", {"/fix": (t, fixes, _status(N_FIX))})
    chunks = list(iter_recording_chunks(path, max_messages=500))
    assert len(chunks) > 1
    assert sum(len(c.mag) for c in chunks) == N_MAG
    assert sum(len(c.attitude) for c in chunks if c.attitude is not None) == N_MAG
    assert all(c.turntable is None for c in chunks)
    head = read_recording_header(path)
    assert head.mag_topic == "/mag" and head.attitude_topic == "/att"
    assert {c.topic: c.role for c in head.channels}["/fix"] is Role.POSITION
    # positions present: the two-pass plan (which ignores positions) must not be taken
    assert head.position is not None and head.position.origin is not None


def test_round_trip_through_magalign_writer(tmp_path):
    t, mag_T, q = motion(N_MAG, rate_hz=MAG_HZ)
    tf, fixes = _track()
    status = _status(N_FIX, no_fix=(0, 55))
    cov = np.tile([0.04, 0, 0, 0, 0.04, 0, 0, 0, 0.25], (N_FIX, 1))
    path = write_recording(
        tmp_path / "ours.mcap", mag_t_ns=t, mag_nT=mag_T * 1e9, attitude_t_ns=t, q_enu_body=q,
        position_t_ns=tf, position_fix=fixes, position_topic="/gps/fix",
        position_log_delay_ns=20_000_000,
        position_extra={"status": status, "position_covariance": cov,
                        "position_covariance_type": np.full(N_FIX, 2)})
    # mcap_ros2 decodes magalign's messages with the definition magalign stored
    got = []
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _s, _ch, m, ros in reader.iter_decoded_messages(topics=["/gps/fix"]):
            got.append((m.log_time, ros))
    assert len(got) == N_FIX
    for i, (log, m) in enumerate(got):
        stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        assert stamp == tf[i] and log == tf[i] + 20_000_000
        assert m.header.frame_id == "gnss" and m.status.status == status[i]
        assert m.status.service == 1
        assert abs(m.latitude - fixes[i, 0]) < 1e-12 and abs(m.longitude - fixes[i, 1]) < 1e-12
        assert abs(m.altitude - fixes[i, 2]) < 1e-9
        assert np.allclose(m.position_covariance, cov[i], atol=1e-15)
        assert m.position_covariance_type == 2
    rec = read_recording(path)
    assert {c.topic: c.role for c in rec.channels}["/gps/fix"] is Role.POSITION
    p = rec.position
    assert p is not None and p.origin is not None and np.array_equal(p.t_ns, tf)
    assert np.array_equal(~p.valid, status < 0)
    assert p.origin.lat_deg == pytest.approx(fixes[1, 0], abs=1e-12)
    want = _enu(fixes[:, 0], fixes[:, 1], fixes[:, 2], tuple(fixes[1]))
    ok = status >= 0
    assert np.max(np.abs(p.p_m[ok] - want[ok])) < 1e-3


@pytest.mark.parametrize("origin", [(47.3769, 8.5417, 447.0), (-33.87, 151.21, 25.0),
                                    (0.0, 179.99, 0.0), (89.5, -120.0, 3000.0)])
def test_geodetic_conversion_against_ecef(origin):
    """Exact WGS-84 ENU, also across the antimeridian and near a pole; and its inverse."""
    rng = np.random.default_rng(7)
    n = 500
    lat = np.clip(origin[0] + rng.uniform(-0.05, 0.05, n), -90.0, 90.0)
    lon = (origin[1] + rng.uniform(-0.05, 0.05, n) + 180.0) % 360.0 - 180.0
    h = origin[2] + rng.uniform(-100.0, 100.0, n)
    o = GeodeticOrigin(*origin)
    got = geodetic_to_local_enu(lat, lon, h, origin=o)
    want = _enu(lat, lon, h, origin)
    assert np.max(np.abs(got - want)) < 1e-6  # m (over up to 8 km)
    la, lo, hh = local_enu_to_geodetic(want, o)
    assert np.max(np.abs(_enu(la, lo, hh, origin) - want)) < 1e-6
    assert np.max(np.abs(hh - h)) < 1e-6


def test_geodetic_origin_only_for_enu():
    t = np.arange(3, dtype=np.int64)
    o = GeodeticOrigin(47.0, 8.0, 400.0)
    assert PositionSeries(t, np.zeros((3, 3)), origin=o).origin == o
    assert PositionSeries(t, np.zeros((3, 3))).origin is None  # constructors without it
    with pytest.raises(ValueError, match="enu"):
        PositionSeries(t, np.zeros((3, 3)), PositionFrame.ATTITUDE_SOURCE_LOCAL, o)
    assert o.to_dict() == {"lat_deg": 47.0, "lon_deg": 8.0, "height_m": 400.0}

"""The independent generator's new sources (tests/indep_gen.py) against hand computations.

A magnetised object fixed in the surroundings (``local_source``, a point dipole), the
magnetometer's lever arm from the tracked point, the ``survey`` and ``translate`` paths,
geodetic positions (INSPVA, NavSatFix) and a rotated PoseStamped frame. Noise is off where
the physics is checked; every file is read back with the real ``mcap`` / ``mcap_ros2``
readers, and the hand computations (dipole, WGS-84 through ECEF, the measurement model) are
written out here, not taken from the generator. Without the new options the generator must
give what it gave before them (known answers computed with the unmodified module).
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import indep_gen as g
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

POSE = "geometry_msgs/msg/PoseStamped"
IMU = "sensor_msgs/msg/Imu"
INSPVA = "novatel_oem7_msgs/msg/INSPVA"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"

# ----------------------------------------------------------------------------- hand helpers


def _dipole_hand(m: np.ndarray, r: np.ndarray) -> np.ndarray:
    """mu0/4pi (3 (m.r) r / r^5 - m / r^3), nT, row by row (not the generator's code)."""
    out = np.empty_like(r)
    for i, rv in enumerate(r):
        n = float(np.sqrt(rv @ rv))
        out[i] = 100.0 * (3.0 * float(m @ rv) * rv / n**5 - m / n**3)
    return out


def _ecef(lat_deg: np.ndarray, lon_deg: np.ndarray, h_m: np.ndarray) -> np.ndarray:
    """Exact WGS-84 geodetic to ECEF, m."""
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    la, lo = np.radians(lat_deg), np.radians(lon_deg)
    n = a / np.sqrt(1 - e2 * np.sin(la) ** 2)
    return np.stack([(n + h_m) * np.cos(la) * np.cos(lo), (n + h_m) * np.cos(la) * np.sin(lo),
                     (n * (1 - e2) + h_m) * np.sin(la)], axis=-1)


def _geodetic_to_enu_exact(llh: np.ndarray, origin: tuple) -> np.ndarray:
    """ENU of geodetic points on the exact tangent plane at ``origin`` (through ECEF), m."""
    lat0, lon0, h0 = origin
    d = _ecef(llh[:, 0], llh[:, 1], llh[:, 2]) - _ecef(np.array(lat0), np.array(lon0),
                                                       np.array(h0))
    la, lo = np.radians(lat0), np.radians(lon0)
    rot = np.array([[-np.sin(lo), np.cos(lo), 0.0],
                    [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
                    [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)]])
    return d @ rot.T


def _read(path: Path) -> tuple[dict[str, list[tuple[int, Any]]], dict[str, str], dict[str, int]]:
    """Messages per topic as (header stamp ns, ROS message), schema names, summary counts."""
    msgs: dict[str, list[tuple[int, Any]]] = defaultdict(list)
    schemas: dict[str, str] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        counts = {summary.channels[c].topic: n
                  for c, n in summary.statistics.channel_message_counts.items()}
        for schema, channel, _message, ros in reader.iter_decoded_messages():
            assert schema is not None
            schemas[channel.topic] = schema.name
            st = ros.header.stamp
            msgs[channel.topic].append((st.sec * 1_000_000_000 + st.nanosec, ros))
    return dict(msgs), schemas, counts


def _mag(msgs: list[tuple[int, Any]]) -> tuple[np.ndarray, np.ndarray]:
    t = np.array([s for s, _ in msgs], dtype=np.int64)
    y = np.array([[m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z]
                  for _, m in msgs]) * 1e9
    return t, y


def _pose(msgs: list[tuple[int, Any]]) -> tuple[np.ndarray, np.ndarray, Rotation]:
    t = np.array([s for s, _ in msgs], dtype=np.int64)
    p = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for _, m in msgs])
    q = np.array([[m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
                   m.pose.orientation.w] for _, m in msgs])
    return t, p, Rotation.from_quat(q)


def _model(C: Rotation, B_enu: np.ndarray, rotvec_deg: tuple) -> np.ndarray:
    """y = R_body_mag.T C.T B (CONVENTIONS measurement model, no D, o, tau)."""
    return Rotation.from_rotvec(np.radians(rotvec_deg)).inv().apply(C.inv().apply(B_enu))


# ----------------------------------------------------------------------------- dipole


def test_dipole_field_hand_values():
    """On the axis 2 m / r^3 * 100 nT, on the equator -m / r^3 * 100 nT, at 45 deg by hand."""
    z = np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(g.dipole_field_nT(z, [0.0, 0.0, 1.0]), [0, 0, 200.0], atol=1e-12)
    np.testing.assert_allclose(g.dipole_field_nT(z, [1.0, 0.0, 0.0]), [0, 0, -100.0],
                               atol=1e-12)
    np.testing.assert_allclose(g.dipole_field_nT(z, [0.0, 0.0, 2.0]), [0, 0, 25.0], atol=1e-12)
    np.testing.assert_allclose(g.dipole_field_nT(z, [0.0, -2.0, 0.0]), [0, 0, -12.5],
                               atol=1e-12)
    # 45 deg: u = (1, 0, 1)/sqrt2, m.u = 1/sqrt2, r^3 = 2 sqrt2: 100 (1.5, 0, 0.5) / 2.828
    np.testing.assert_allclose(g.dipole_field_nT(z, [1.0, 0.0, 1.0]),
                               [150 / (2 * np.sqrt(2)), 0.0, 50 / (2 * np.sqrt(2))], atol=1e-12)
    # vectorised (N, 3) x (N, 3) and (3,) x (N, 3), against the row-by-row formula
    rng = np.random.default_rng(0)
    r = rng.normal(size=(50, 3)) * 3
    m = rng.normal(size=(50, 3))
    out = g.dipole_field_nT(m, r)
    assert out.shape == (50, 3)
    np.testing.assert_allclose(out, np.array([_dipole_hand(mi, ri[None])[0]
                                              for mi, ri in zip(m, r, strict=True)]),
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g.dipole_field_nT(m[0], r), _dipole_hand(m[0], r), rtol=1e-12,
                               atol=1e-12)


def test_source_presence_windows_and_ramp():
    p = {"windows_s": [[10.0, 20.0], [30.0, 31.0]]}
    t = np.array([9.999, 10.0, 15.0, 19.999, 20.0, 25.0, 30.5, 31.0])
    np.testing.assert_array_equal(g.source_presence(p, t), [0, 1, 1, 1, 0, 0, 1, 0])
    np.testing.assert_array_equal(g.source_presence({}, t), np.ones(len(t)))
    pr = {"windows_s": [[10.0, 20.0]], "ramp_s": 2.0}
    np.testing.assert_allclose(
        g.source_presence(pr, np.array([9.0, 10.0, 11.0, 12.0, 15.0, 19.0, 20.0])),
        [0.0, 0.0, 0.5, 1.0, 1.0, 0.5, 0.0], atol=1e-12)


def _lab_spec(**kw: Any) -> g.Spec:
    """Noise-free translate recording, attitude on the magnetometer's stamps."""
    base: dict[str, Any] = dict(name="lab", seed=21, duration_s=20.0, mag_rate_hz=50.0,
                                att_rate_hz=50.0, att_type=POSE, path="translate",
                                att_noise_deg=0.0, mag_noise_nT=0.0,
                                rotvec_body_mag_deg=(1.0, -2.0, 3.0))
    base.update(kw)
    return g.Spec(**base)


def test_local_source_readings_match_hand_dipole_through_the_file(tmp_path):
    """Read back: y = R.T C.T (B + dipole(p - s)) in the window, y = R.T C.T B outside."""
    src = np.array([1.0, 2.0, 0.4])  # 0.8 m below the path's centre, +-0.5 m motion
    mom = np.array([0.05, -0.1, 0.2])
    spec = _lab_spec(effects={"local_source": {"position_m": src.tolist(),
                                               "moment_Am2": mom.tolist(),
                                               "windows_s": [[5.005, 15.005]]}})
    path = g.write(spec, tmp_path / "lab.mcap")
    msgs, _, _ = _read(path)
    tm, y = _mag(msgs["/imu/mag"])
    ta, p, C = _pose(msgs["/attitude"])
    idx = np.searchsorted(ta, tm)
    assert np.array_equal(ta[idx], tm)  # the attitude was sampled at every mag stamp
    p, C = p[idx], C[idx]
    ts = (tm - g.T0_NS) * 1e-9
    inside = (ts >= 5.005) & (ts < 15.005)
    B = np.tile(np.asarray(spec.B_enu_nT), (len(ts), 1))
    B[inside] += _dipole_hand(mom, p[inside] - src)
    expect = _model(C, B, spec.rotvec_body_mag_deg)
    np.testing.assert_allclose(y, expect, atol=1e-6, rtol=0)
    # the source is seen: tens to thousands of nT at 0.3-1.3 m
    add = np.linalg.norm(_dipole_hand(mom, p[inside] - src), axis=1)
    assert 5.0 < add.min() and add.max() < 5000.0


def test_lever_arm_moves_the_evaluation_point_by_C_l(tmp_path):
    """sensor = p + C l; the gradient and the dipole are seen there (hand model via the file)."""
    lever = np.array([0.1, 0.8, -0.3])  # on a pole ahead of the walker, 0.3 m lower
    src = np.array([1.0, 15.0, 0.0])  # between the first two lines, on the ground
    mom = np.array([0.0, 3.0, -5.0])
    G = np.array([[20.0, 5.0, 0.0], [5.0, -30.0, 8.0], [0.0, 8.0, 10.0]])
    eff = {"local_source": {"position_m": src.tolist(), "moment_Am2": mom.tolist()},
           "lever_arm": {"lever_arm_body_m": lever.tolist()}}
    spec = g.Spec("walk", 5, duration_s=40.0, mag_rate_hz=50.0, att_rate_hz=50.0,
                  path="survey", att_noise_deg=0.0, mag_noise_nT=0.0, effects=eff,
                  rotvec_body_mag_deg=(0.5, 1.0, -1.5))
    t = np.linspace(0.0, 40.0, 777)
    C = g.true_attitude(spec, t)
    np.testing.assert_allclose(g.sensor_position_m(spec, t) - g.position_m(spec, t),
                               C.apply(lever), atol=1e-12)
    # the gradient term is linear: the lever arm adds G C l exactly
    with_g = g.Spec("walk", 5, duration_s=40.0, path="survey",
                    effects={"field_gradient": {"G_nT_per_m": G.tolist()},
                             "lever_arm": {"lever_arm_body_m": lever.tolist()}})
    no_la = g.Spec("walk", 5, duration_s=40.0, path="survey",
                   effects={"field_gradient": {"G_nT_per_m": G.tolist()}})
    np.testing.assert_allclose(g.field_enu(with_g, t) - g.field_enu(no_la, t),
                               C.apply(lever) @ G.T, atol=1e-9)
    # end to end through the file: positions and attitude read back carry the lever arm
    path = g.write(spec, tmp_path / "walk.mcap")
    msgs, _, _ = _read(path)
    tm, y = _mag(msgs["/imu/mag"])
    ta, p, Cr = _pose(msgs["/attitude"])
    idx = np.searchsorted(ta, tm)
    assert np.array_equal(ta[idx], tm)
    p_s = p[idx] + Cr[idx].apply(lever)
    B = np.asarray(spec.B_enu_nT) + _dipole_hand(mom, p_s - src)
    np.testing.assert_allclose(y, _model(Cr[idx], B, spec.rotvec_body_mag_deg), atol=1e-6,
                               rtol=0)
    # without the lever arm the same readings would be off by far more than the noise
    B0 = np.asarray(spec.B_enu_nT) + _dipole_hand(mom, p[idx] - src)
    assert np.abs(y - _model(Cr[idx], B0, spec.rotvec_body_mag_deg)).max() > 50.0
    # the truth: closest approach of the SENSOR (not the tracked point), from the samples
    tr = g.truth(spec)
    ls = tr["effects"]["local_source"]
    d = np.linalg.norm(p_s - src, axis=1)
    i = int(np.argmin(d))
    assert ls["closest_approach_m"] <= d[i] + 1e-9
    assert d[i] - ls["closest_approach_m"] < 0.01  # 1.5 m/s x 20 ms between samples
    assert abs(ls["closest_approach_s"] - (tm[i] - g.T0_NS) * 1e-9) < 0.03
    d_tracked = np.linalg.norm(p[idx] - src, axis=1).min()
    assert abs(d_tracked - ls["closest_approach_m"]) > 0.05
    assert tr["effects"]["lever_arm"] == {"lever_arm_body_m": lever.tolist()}
    assert ls["moment_Am2"] == mom.tolist() and ls["windows_s"] is None
    assert ls["position_frame"] == "attitude_source_local" and ls["position_origin"] is None
    np.testing.assert_allclose(ls["position_m"], src, atol=1e-12)


# ----------------------------------------------------------------------------- geodetic


def test_navsatfix_channel_reproduces_the_path_within_1_mm(tmp_path):
    spec = g.Spec("fix", 8, duration_s=30.0, mag_rate_hz=50.0, att_rate_hz=25.0,
                  att_type=IMU, path="survey", position_type="navsatfix",
                  geo_origin=(48.1, 11.6, 520.0), att_noise_deg=0.0, mag_noise_nT=0.0)
    path = g.write(spec, tmp_path / "fix.mcap")
    msgs, schemas, counts = _read(path)
    assert schemas == {"/imu/mag": "sensor_msgs/msg/MagneticField", "/attitude": IMU,
                       "/gps/fix": NAVSATFIX}
    n_att = len(g.att_stamps_s(spec))
    assert counts == {"/imu/mag": 1500, "/attitude": n_att, "/gps/fix": 300}
    assert {k: len(v) for k, v in msgs.items()} == counts
    fixes = msgs["/gps/fix"]
    assert all(m.status.status == 0 and m.status.service == 1
               and m.position_covariance_type == 2 and m.header.frame_id == "gps"
               for _, m in fixes)
    tf = np.array([s for s, _ in fixes], dtype=np.int64)
    np.testing.assert_array_equal(tf, g.T0_NS + np.arange(300) * 100_000_000)
    llh = np.array([[m.latitude, m.longitude, m.altitude] for _, m in fixes])
    enu = _geodetic_to_enu_exact(llh, spec.geo_origin)
    path_enu = g.position_m(spec, (tf - g.T0_NS) * 1e-9)
    assert np.abs(enu - path_enu).max() < 1e-3
    assert np.ptp(path_enu[:, 1]) > 25.0  # it did walk a line
    # the attitude rides on its own channel (Imu), the same as the generator's
    q = np.array([[m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w]
                  for _, m in msgs["/attitude"]])
    ta = (np.array([s for s, _ in msgs["/attitude"]]) - g.T0_NS) * 1e-9
    ang = (Rotation.from_quat(q) * g.true_attitude(spec, ta).inv()).magnitude()
    assert ang.max() < 1e-6
    # the truth: the origin a reader takes (the first fix) and the generator's origin
    tr = g.truth(spec)
    assert tr["position_frame"] == "enu"
    assert tr["geo_origin"] == {"lat_deg": 48.1, "lon_deg": 11.6, "height_m": 520.0}
    o = tr["position_origin"]
    assert [o["lat_deg"], o["lon_deg"], o["height_m"]] == llh[0].tolist()


def test_inspva_positions_and_velocities_reproduce_the_path(tmp_path):
    src = [3.0, 10.0, 0.0]
    spec = g.Spec("ins", 9, duration_s=30.0, mag_rate_hz=50.0, att_rate_hz=50.0,
                  att_type=INSPVA, path="survey", position_type="inspva",
                  att_noise_deg=0.0, mag_noise_nT=0.0,
                  effects={"local_source": {"position_m": src, "moment_Am2": [0, 0, 10.0]}})
    path = g.write(spec, tmp_path / "ins.mcap")
    msgs, schemas, counts = _read(path)
    assert schemas == {"/imu/mag": "sensor_msgs/msg/MagneticField", "/attitude": INSPVA}
    assert counts == {"/imu/mag": 1500, "/attitude": len(g.att_stamps_s(spec))}
    att = msgs["/attitude"]
    ta = (np.array([s for s, _ in att]) - g.T0_NS) * 1e-9
    llh = np.array([[m.latitude, m.longitude, m.height] for _, m in att])
    enu = _geodetic_to_enu_exact(llh, spec.geo_origin)
    assert np.abs(enu - g.position_m(spec, ta)).max() < 1e-3
    # velocities: differences of the positions read back (the path is smooth)
    ven = np.array([[m.east_velocity, m.north_velocity, m.up_velocity] for _, m in att])
    vd = np.gradient(enu, ta, axis=0)
    assert np.abs(ven - vd)[2:-2].max() < 0.01
    assert np.abs(np.linalg.norm(ven, axis=1)[ta > 3.0] - 1.5).max() < 0.3
    # NovAtel: azimuth clockwise from north; walking north then south (plus 1 deg of swing)
    az = np.array([m.azimuth for _, m in att])
    north = (ta > 4.0) & (ta < 15.0)
    assert np.abs((az[north] + 180.0) % 360.0 - 180.0).max() < 1.5
    # the truth: the source relative to the first INSPVA position (the origin a reader takes)
    tr = g.truth(spec)
    ls = tr["effects"]["local_source"]
    o = tr["position_origin"]
    assert [o["lat_deg"], o["lon_deg"], o["height_m"]] == llh[0].tolist()
    np.testing.assert_allclose(ls["position_m"],
                               np.array(src) - _geodetic_to_enu_exact(llh[:1],
                                                                      spec.geo_origin)[0],
                               atol=1e-3)
    assert ls["position_frame"] == "enu" and ls["position_origin"] == o


def test_flat_earth_conversion_round_trip_and_radii():
    N, M = g.wgs84_radii_m(52.5)
    # N: the radius of the parallel over cos(lat); M: the meridian arc per radian, both from
    # the exact ECEF of the ellipsoid (finite difference over +-1e-5 deg)
    e = _ecef(np.array([52.5 - 1e-5, 52.5, 52.5 + 1e-5]), np.zeros(3), np.zeros(3))
    assert N == pytest.approx(np.hypot(e[1, 0], e[1, 1]) / np.cos(np.radians(52.5)), abs=0.01)
    assert M == pytest.approx(np.linalg.norm(e[2] - e[0]) / np.radians(2e-5), abs=1.0)
    assert N == pytest.approx(6391616.8, abs=0.1) and M == pytest.approx(6375692.9, abs=0.1)
    rng = np.random.default_rng(3)
    p = rng.uniform(-70, 70, (200, 3)) * np.array([1, 1, 0.1])
    llh = g.enu_to_geodetic(p, (52.5, 13.3, 40.0))
    np.testing.assert_allclose(g.geodetic_to_enu(llh, (52.5, 13.3, 40.0)), p, atol=1e-9)
    # within 100 m of the origin the flat earth departs from the exact plane by < 1 mm (the
    # curvature d^2 / 2R: 0.8 mm at 100 m)
    assert np.abs(_geodetic_to_enu_exact(llh, (52.5, 13.3, 40.0)) - p).max() < 1e-3


def test_rotated_pose_frame(tmp_path):
    spec = _lab_spec(position_frame_yaw_deg=30.0,
                     effects={"local_source": {"position_m": [1.0, 2.0, 0.4],
                                               "moment_Am2": [0.0, 0.0, 0.1]}})
    msgs, _, _ = _read(g.write(spec, tmp_path / "room.mcap"))
    ta, p, _ = _pose(msgs["/attitude"])
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    Q = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # room axes -> ENU
    np.testing.assert_allclose(p @ Q.T, g.position_m(spec, (ta - g.T0_NS) * 1e-9), atol=1e-12)
    ls = g.truth(spec)["effects"]["local_source"]
    np.testing.assert_allclose(Q @ np.array(ls["position_m"]), [1.0, 2.0, 0.4], atol=1e-12)
    assert ls["position_enu_m"] == [1.0, 2.0, 0.4]
    with pytest.raises(ValueError, match="pose only"):
        g.readings(g.Spec("x", 1, att_type=INSPVA, position_type="inspva",
                          position_frame_yaw_deg=10.0))


def test_bad_combinations_are_refused():
    with pytest.raises(ValueError, match="INSPVA"):
        g.readings(g.Spec("x", 1, position_type="inspva"))
    with pytest.raises(ValueError, match="navsatfix"):
        g.readings(g.Spec("x", 1, position_type="navsatfix"))  # PoseStamped: no
    with pytest.raises(ValueError, match="path"):
        g.readings(g.Spec("x", 1, path="spiral"))


# ----------------------------------------------------------------------------- paths


def _heading_of_forward(C: Rotation) -> np.ndarray:
    """Unwrapped track angle (rad, from east) of the forward (body y) axis, horizontal."""
    f = C.apply([0.0, 1.0, 0.0])
    return np.unwrap(np.arctan2(f[:, 1], f[:, 0]))


@pytest.mark.parametrize("cal_s", [0.0, 40.0])
def test_survey_is_smooth_in_position_velocity_and_heading(cal_s):
    """No steps or kinks: first differences within the speed, second within the acceleration.

    A kink of 1.5 m/s would give a second difference of 15 mm at 10 ms, the bound is 0.3 mm;
    a step in turn rate of 1 rad/s would give 10 mrad, the bound 0.5 mrad.
    """
    v, dt = 1.5, 0.01
    spec = g.Spec("sv", 4, duration_s=130.0, path="survey", survey_calibration_s=cal_s)
    t = np.arange(-1.0, 130.0, dt)
    p = g.position_m(spec, t)
    d1 = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert d1.max() <= v * dt * (1 + 1e-6)
    assert np.linalg.norm(np.diff(p, 2, axis=0), axis=1).max() < 3.0 * dt**2
    C = g.true_attitude(spec, t)
    h = _heading_of_forward(C)
    assert np.abs(np.diff(h)).max() < 2.0 * dt  # turn rate below 2 rad/s
    assert np.abs(np.diff(h, 2)).max() < 5.0 * dt**2  # angular acceleration below 5 rad/s^2
    w = (C[1:] * C[:-1].inv()).as_rotvec() / dt  # angular velocity, ENU, rad/s
    assert np.linalg.norm(np.diff(w, axis=0), axis=1).max() < 5.0 * dt
    # geometry: lines along north at x = 0, 2, 4, ..., 30 m long, at 1 m height
    walk = t > cal_s + 3.0
    assert np.all(p[:, 2] == 1.0)
    on_line = walk & (p[:, 1] > 0.0) & (p[:, 1] < 30.0)
    np.testing.assert_allclose(p[on_line, 0] / 2.0, np.round(p[on_line, 0] / 2.0), atol=1e-12)
    assert p[:, 0].max() >= 4.0 and np.ptp(p[walk, 1]) > 30.0
    # the heading follows the travel within the 1 deg yaw swing (+ pitch/roll coupling)
    vel = np.gradient(p, t, axis=0)
    trk = np.arctan2(vel[walk, 1], vel[walk, 0])
    dh = (h[walk] - trk + np.pi) % (2 * np.pi) - np.pi
    assert np.degrees(np.abs(dh)).max() < 1.5
    # standing still before the walk
    still = t < cal_s
    assert np.all(p[still] == p[0])


def test_survey_calibration_manoeuvre_visits_four_headings_and_tilts():
    spec = g.Spec("cal", 4, duration_s=60.0, path="survey", survey_calibration_s=40.0,
                  swing_deg=(0.0, 0.0, 0.0))
    t = np.arange(0.0, 40.0, 0.01)
    ang = g._angles(spec, t)
    C = g.true_attitude(spec, t)
    # yaw, pitch, roll back from the rotation (ZXY, CONVENTIONS) agree with the angles
    np.testing.assert_allclose(np.unwrap(C.as_euler("ZXY")[:, 0]), np.unwrap(ang[:, 0]),
                               atol=1e-9)
    hd = np.degrees(_heading_of_forward(C))  # 90 = north
    for k, head in enumerate([90.0, 0.0, -90.0, -180.0]):
        seg = (t >= k * 10.0) & (t < k * 10.0 + 6.0)  # the tilts of each heading
        np.testing.assert_allclose(hd[seg], head, atol=1e-9)
        assert np.degrees(ang[seg, 2]).max() == pytest.approx(10.0, abs=0.01)
        assert np.degrees(ang[seg, 2]).min() == pytest.approx(-10.0, abs=0.01)
        assert np.degrees(ang[seg, 1]).max() == pytest.approx(5.0, abs=0.01)
        assert np.degrees(ang[seg, 1]).min() == pytest.approx(-5.0, abs=0.01)
    assert hd[-1] == pytest.approx(-270.0, abs=0.5)  # north again, a full turn clockwise
    np.testing.assert_allclose(g.position_m(spec, t), np.tile([0.0, 0.0, 1.0], (len(t), 1)))


def test_translate_moves_but_barely_turns():
    spec = g.Spec("tr", 6, duration_s=60.0, path="translate")
    t = np.arange(0.0, 60.0, 0.01)
    p = g.position_m(spec, t)
    assert np.all(np.ptp(p, axis=0) > 0.8) and np.all(np.abs(p - [1.0, 2.0, 1.2]) <= 0.5)
    C = g.true_attitude(spec, t)
    mean = C.mean()
    assert np.degrees((C * mean.inv()).magnitude()).max() < 5.0
    # smooth: 0.1-0.3 Hz at 0.5 m per axis -> speeds below sqrt(3) 0.94 m/s, accelerations
    # below sqrt(3) 1.78 m/s^2
    assert np.linalg.norm(np.diff(p, axis=0), axis=1).max() < 1.7 * 0.01
    assert np.linalg.norm(np.diff(p, 2, axis=0), axis=1).max() < 3.1 * 0.01**2


def test_handheld_wanders_through_its_box_and_turns():
    box = ((0.0, 2.0), (0.0, 2.0), (0.3, 1.0))
    spec = g.Spec("hh", 8, duration_s=100.0, path="handheld", handheld_box_m=box)
    t = np.arange(0.0, 100.0, 0.01)
    p = g.position_m(spec, t)
    lo, hi = np.array(box).T
    assert np.all(p >= lo) and np.all(p <= hi)
    assert np.all(np.ptp(p, axis=0) > 0.7 * (hi - lo))  # it reaches across the box
    # smooth: per axis at most 2 pi (0.6 * 0.07 + 0.4 * 0.2) h m/s
    v = np.diff(p, axis=0) / 0.01
    assert np.abs(v).max(axis=0) @ [1, 1, 0] < 2 * 2 * np.pi * 0.122 * 1.0
    # it turns as the Lissajous motion does (the same attitude)
    np.testing.assert_allclose(
        g.true_attitude(spec, t).as_quat(),
        g.true_attitude(g.Spec("hh", 8, duration_s=100.0), t).as_quat(), atol=0)
    # and it comes back: most places are passed again more than 10 s later within 0.3 m
    k = np.arange(0, len(t), 50)
    back = [np.min(np.linalg.norm(p[k][np.abs(t[k] - t[i]) > 10.0] - p[i], axis=1)) < 0.3
            for i in k]
    assert np.mean(back) > 0.5


# ----------------------------------------------------------------------------- unchanged


def test_defaults_give_the_answers_of_before():
    """Known answers computed with the unmodified generator (1e-6 nT, 1e-9 m / quaternion)."""
    r = g.readings(g.Spec("x", 7))
    assert len(r["t_mag_s"]) == 6000 and len(r["t_att_s"]) == 6003
    assert set(r) == {"t_mag_s", "mag_nT", "t_att_s", "att", "pos_m"}
    np.testing.assert_allclose(r["mag_nT"][[0, 1234, 5999]], [
        [25323.4630495278, 17522.6165810002, -37260.5835723691],
        [-4058.3848025704, 3502.0467016246, -48039.4201056845],
        [6365.3627599266, -8525.9039080527, -47153.6789239856]], atol=1e-6, rtol=0)
    np.testing.assert_allclose(r["att"].as_quat()[[0, 50, 6000]], [
        [-0.0639720167, 0.1877173278, 0.2212127428, 0.9548480028],
        [0.0419267002, 0.1698053022, 0.2411682251, 0.9545921634],
        [-0.0803948586, 0.0741825334, -0.8394189634, -0.5323621158]], atol=1e-9, rtol=0)
    np.testing.assert_allclose(r["pos_m"][[0, 100, 6000]], [
        [0.7110456126, 1.8722140035, 1.2517014759],
        [0.8813472093, 2.0169900299, 1.3995660545],
        [1.3604593756, 1.9841055588, 1.0030134932]], atol=1e-9, rtol=0)
    s2 = g.Spec("y", 11, effects={
        "field_gradient": {"G_nT_per_m": [[100, 20, 0], [20, -50, 10], [0, 10, -50]]},
        "time_offset": {"time_offset_s": 0.01}})
    t = np.array([0.0, 12.5, 33.3])
    np.testing.assert_allclose(g.clean_readings(s2, t), [
        [25805.2100757679, 21710.2900229628, -34614.7762673653],
        [7878.6002887238, 5586.1710292448, -47344.9676672432],
        [-34162.837151837, 2153.4336627715, -34132.5934601542]], atol=1e-6, rtol=0)
    np.testing.assert_allclose(g.field_enu(s2, t), [
        [776.6732875419, 19993.3372859535, -43989.5972026661],
        [834.4820377428, 19985.2793453406, -43985.4413171554],
        [832.5795240873, 20013.9481113433, -43994.311118806]], atol=1e-6, rtol=0)
    np.testing.assert_allclose(g.true_attitude(s2, t).as_rotvec(), [
        [-0.2435636453, 0.3575255587, 0.4864903451],
        [-0.0540201784, -0.5174969104, 2.1129825554],
        [-0.4323263814, -0.0911645225, -1.8379395009]], atol=1e-9, rtol=0)


def test_default_files_and_key_carry_nothing_new(tmp_path):
    """A default INSPVA keeps its fixed position; the key has no new spec fields or truth."""
    s = g.Spec("old", 2, duration_s=4.0, att_type=INSPVA)
    kp = g.write_corpus(tmp_path / "c", [s, g.Spec("old_pose", 3, duration_s=4.0)], [])
    msgs, schemas, counts = _read(tmp_path / "c" / "old.mcap")
    assert set(counts) == {"/imu/mag", "/attitude"} and counts["/imu/mag"] == 400
    assert {(m.latitude, m.longitude, m.height, m.north_velocity)
            for _, m in msgs["/attitude"]} == {(52.5, 13.3, 40.0, 0.0)}
    key = json.loads(kp.read_text())["recordings"]
    for name in ("old", "old_pose"):
        assert set(key[name]) == {"effects", "strength_x_threshold", "spec"}
        assert not set(key[name]["spec"]) & set(g._NEW_FIELDS)
    # old_pose: PoseStamped positions on the Lissajous path, as before
    msgs, schemas, _ = _read(tmp_path / "c" / "old_pose.mcap")
    assert schemas["/attitude"] == POSE
    ta, p, _ = _pose(msgs["/attitude"])
    np.testing.assert_allclose(p, g.position_m(g.Spec("old_pose", 3), (ta - g.T0_NS) * 1e-9),
                               atol=1e-12)


def test_truth_in_the_key_and_beside_a_recording(tmp_path):
    eff = {"local_source": {"position_m": [2.0, 10.0, 0.0], "moment_Am2": [0.0, 0.0, 20.0],
                            "windows_s": [[5.0, 42.0]], "ramp_s": 1.0},
           "lever_arm": {"lever_arm_body_m": [0.0, 0.5, 0.0]}}
    s = g.Spec("new", 12, duration_s=45.0, path="survey", att_type=IMU,
               position_type="navsatfix", effects=eff)
    kp = g.write_corpus(tmp_path / "c", [s], [])
    entry = json.loads(kp.read_text())["recordings"]["new"]
    tr = entry["truth"]
    assert entry["spec"]["path"] == "survey" and entry["spec"]["position_type"] == "navsatfix"
    assert tr["format"] == "indep_gen.truth/1" and tr["path"] == "survey"
    assert tr["position_type"] == "navsatfix" and tr["position_frame"] == "enu"
    assert tr["geo_origin"] == {"lat_deg": 52.5, "lon_deg": 13.3, "height_m": 40.0}
    ls = tr["effects"]["local_source"]
    assert set(ls) >= {"position_m", "position_frame", "position_origin", "moment_Am2",
                       "windows_s", "closest_approach_m", "closest_approach_s"}
    assert ls["windows_s"] == [[5.0, 42.0]] and ls["ramp_s"] == 1.0
    # the second line (x = 2 m, southwards from t = 25 s) passes right over the source: the
    # sensor, 0.5 m ahead and 1 m up, is above it when the tracked point is at y = 10.5 m
    t_over = 3.0 + (30.0 - 2.25) / 1.5 + 8 * 2.0 / (3 * 1.5) + 19.5 / 1.5
    assert ls["closest_approach_s"] == pytest.approx(t_over, abs=0.3)
    assert ls["closest_approach_m"] == pytest.approx(1.0, abs=0.05)
    assert tr["effects"]["lever_arm"]["lever_arm_body_m"] == [0.0, 0.5, 0.0]
    # write(truth_path=...) writes the same truth beside a single recording
    tp = tmp_path / "new_truth.json"
    g.write(s, tmp_path / "new.mcap", truth_path=tp)
    assert json.loads(tp.read_text()) == tr

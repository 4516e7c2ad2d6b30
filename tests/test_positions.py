"""Positions in the recording model: read from the attitude channel, NaN rows, diagnosis data."""

import numpy as np
import pytest
from _reader_fixtures import DEFS, T0, motion, write_ros2

from pipeline.core.recording import PositionFrame, PositionSeries
from pipeline.io.mcap_decode import geodetic_to_local_enu
from pipeline.io.mcap_read import read_recording


def test_odometry_positions_and_orientation_are_read(tmp_path):
    t, mag_T, q = motion(300)[:3]
    order = np.r_[1:300, 0]  # written out of order: positions must follow the sort
    path = write_ros2(tmp_path / "odom.mcap", [
        ("/mag", "sensor_msgs/msg/MagneticField", DEFS["sensor_msgs/msg/MagneticField"], t,
         mag_T, ["m"]),
        ("/odom", "nav_msgs/msg/Odometry", DEFS["nav_msgs/msg/Odometry"], t[order], q[order],
         ["odom"]),
    ])
    rec = read_recording(path)
    assert rec.attitude is not None and len(rec.attitude) == 300
    p = rec.position
    assert p is not None and p.frame is PositionFrame.ATTITUDE_SOURCE_LOCAL
    # x was written as seconds since T0: rows follow the sorted stamps, metres
    assert np.max(np.abs(p.p_m[:, 0] - (p.t_ns - T0) * 1e-9)) < 1e-9
    assert np.allclose(p.p_m[:, 1:], [2.0, 3.0], atol=1e-12)


@pytest.mark.parametrize("att_type, frame", [
    ("geometry_msgs/msg/PoseStamped", PositionFrame.ATTITUDE_SOURCE_LOCAL),
    ("novatel_oem7_msgs/msg/INSPVA", PositionFrame.ENU),
])
def test_simulated_trajectory_round_trips(tmp_path, att_type, frame):
    from pipeline.app.simulate import scenario_from_dict, simulate, write_simulated

    sc = {"name": "p", "timing": {"duration_s": 20.0, "mag_rate_hz": 50.0,
                                   "attitude_rate_hz": 50.0},
          "motion": {"profile": "multiaxis"}, "field": {"enu_nT": [0.0, 20000.0, -40000.0]},
          "trajectory": {"frame_yaw_deg": 30.0}, "output": {"attitude_type": att_type}}
    sim = simulate(scenario_from_dict(sc))
    rec = read_recording(write_simulated(sim, tmp_path / "p.mcap"))
    assert rec.position is not None and rec.position.frame is frame
    t_s = (np.asarray(rec.position.t_ns) - sim.scenario.timing.start_ns) * 1e-9
    p_enu = sim.scenario.trajectory.p_enu_m(t_s)
    if frame is PositionFrame.ENU:
        want = p_enu - p_enu[0]  # tangent plane at the first fix
    else:
        want = p_enu @ sim.scenario.trajectory.Q_enu_local()  # room frame, yawed 30 deg
    assert np.max(np.abs(rec.position.p_m - want)) < 1e-3  # m
    # without a trajectory the pose carries no position
    sc.pop("trajectory")
    sim = simulate(scenario_from_dict(sc))
    assert read_recording(write_simulated(sim, tmp_path / "q.mcap")).position is None


def test_tangent_plane_scale():
    """0.001 deg of latitude is ~111 m north; of longitude ~68 m east at 52.5 deg N.

    ENU is exact (WGS-84 through ECEF): a point 68 m east at 5 m more height is 5 m minus
    the Earth's curvature, d^2 / (2 N) = 0.36 mm, above the origin's horizontal plane.
    """
    p = geodetic_to_local_enu(np.array([52.5, 52.501, 52.5]), np.array([13.4, 13.4, 13.401]),
                              np.array([40.0, 40.0, 45.0]))
    assert abs(p[1, 1] - 111.3) < 0.2 and abs(p[1, 0]) < 1e-9
    assert abs(p[2, 0] - 67.9) < 0.2 and abs(p[2, 2] - (5.0 - 67.91**2 / (2 * 6.3914e6))) < 1e-6


def test_lost_positions_are_not_bridged_and_leave_the_diagnosis():
    from pipeline.core.recording import AlignedSeries, AttitudeSeries, Recording, VectorSeries
    from stages.diagnose.model import FitData  # noqa: F401 (the data the stage builds)
    from stages.diagnose.stage import fit_data_from

    t = np.arange(1000, dtype=np.int64) * 10_000_000  # 100 Hz, 10 s
    p = np.stack([np.sin(t * 1e-9), np.cos(t * 1e-9), 0 * t + 1.0], -1)
    p[300:400] = np.nan  # one second lost
    ps = PositionSeries(t, p, PositionFrame.ATTITUDE_SOURCE_LOCAL)
    at = ps.at(t + 5_000_000)
    lost = ~np.isfinite(at).all(axis=1)
    assert lost[299:400].all() and not lost[:299].any() and not lost[400:-1].any()
    q = np.tile([0.0, 0.0, 0.0, 1.0], (1000, 1))
    rec = Recording("x", (), VectorSeries(t, np.ones((1000, 3)) * 3e4), "/m",
                    AttitudeSeries(t, q), "/a", position=ps)
    al = AlignedSeries(t, np.ones((1000, 3)) * 3e4, q, 0.0, np.arange(1000))
    data = fit_data_from(rec, al)
    # 100 lost, and the 10 + 10 samples within MAX_LAG_S (0.1 s) of the attitude's ends
    assert len(data) == 880 and np.isfinite(data.p_m).all()
    assert data.position_frame == "attitude_source_local"
    assert np.allclose(data.p_ref_m, np.nanmean(p[10:990], axis=0), atol=1e-3)  # m

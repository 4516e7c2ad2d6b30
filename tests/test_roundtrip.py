"""Simulate -> write MCAP -> ingest gives the same arrays back, for every supported type."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from pipeline.app.cli import main
from pipeline.app.simulate import load_scenario, scenario_from_dict, simulate, write_simulated
from pipeline.core.geometry import quat_rotate
from pipeline.core.recording import EncodingFamily, Role
from pipeline.io.mcap_read import read_recording

ROOT = Path(__file__).resolve().parents[1]

ROS_ATTITUDE = [
    "sensor_msgs/msg/Imu",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/QuaternionStamped",
    "novatel_oem7_msgs/msg/INSPVA",
]
JSON_ATTITUDE = ["magalign.AttitudeQuaternion", "magalign.AttitudeEuler"]


def _scenario(output: dict, motion: dict | None = None, **over) -> dict:
    d = {
        "name": "rt",
        "timing": {"duration_s": 3.0, "mag_rate_hz": 50.0, "attitude_rate_hz": 40.0,
                   "attitude_phase_s": 0.003},
        "motion": motion or {"profile": "multiaxis", "yaw_rate_deg_s": 120.0,
                             "pitch_amplitude_deg": 40.0, "roll_amplitude_deg": 60.0,
                             "pitch_period_s": 2.0, "roll_period_s": 3.0},
        "field": {"enu_nT": [1500.0, 21000.0, -43000.0]},
        "sensor": {"misalignment_rotvec_deg": [1.0, -2.0, 0.5]},
        "noise": {"mag_sigma_nT": 1.0, "heading_sigma_deg": 0.1, "pitch_roll_sigma_deg": 0.05},
        "output": output,
    }
    d.update(over)
    return d


def _same_quat(a: np.ndarray, b: np.ndarray, atol: float = 1e-12) -> None:
    """Quaternions equal up to sign, row by row."""
    s = np.sign(np.sum(a * b, axis=1))[:, None]
    np.testing.assert_allclose(a, s * b, atol=atol)


def _roundtrip(tmp_path: Path, d: dict):
    sim = simulate(scenario_from_dict(d), seed=1)
    path = write_simulated(sim, tmp_path / "rec.mcap")
    return sim, sim.recording, read_recording(path), path


def _check_common(mem, back) -> None:
    np.testing.assert_array_equal(back.mag.t_ns, mem.mag.t_ns)
    # nT conversion exact to float precision (tesla on the wire for MagneticField).
    np.testing.assert_allclose(back.mag.values, mem.mag.values, rtol=1e-15, atol=1e-10)
    assert back.mag_topic == mem.mag_topic
    assert back.mag_frame_id == mem.mag_frame_id
    assert back.encoding == mem.encoding
    assert back.attitude_topic == mem.attitude_topic
    assert back.problems == ()
    assert len(back.channels) == len(mem.channels)
    for cb, cm in zip(sorted(back.channels, key=lambda c: c.topic),
                      sorted(mem.channels, key=lambda c: c.topic), strict=True):
        assert (cb.topic, cb.type, cb.encoding, cb.role, cb.count) == (
            cm.topic, cm.type, cm.encoding, cm.role, cm.count)
        assert cb.rate_hz == pytest.approx(cm.rate_hz, rel=1e-9)


@pytest.mark.parametrize("attitude_type", ROS_ATTITUDE)
def test_ros2_roundtrip(tmp_path, attitude_type):
    d = _scenario({"mag_type": "sensor_msgs/msg/MagneticField", "attitude_type": attitude_type,
                   "frame_id": "fluxgate", "mag_log_delay_s": 0.002,
                   "attitude_log_delay_s": 0.031})
    sim, mem, back, _ = _roundtrip(tmp_path, d)
    assert mem.encoding is EncodingFamily.ROS2
    _check_common(mem, back)
    np.testing.assert_array_equal(back.attitude.t_ns, mem.attitude.t_ns)
    _same_quat(back.attitude.q_enu_body, mem.attitude.q_enu_body)
    assert back.turntable is None


@pytest.mark.parametrize("attitude_type", JSON_ATTITUDE)
def test_json_roundtrip(tmp_path, attitude_type):
    d = _scenario({"mag_type": "magalign.Magnetometer", "attitude_type": attitude_type,
                   "mag_topic": "/fluxgate", "attitude_topic": "/ins"})
    sim, mem, back, path = _roundtrip(tmp_path, d)
    assert mem.encoding is EncodingFamily.JSON
    _check_common(mem, back)
    np.testing.assert_array_equal(back.attitude.t_ns, mem.attitude.t_ns)
    _same_quat(back.attitude.q_enu_body, mem.attitude.q_enu_body)
    # The file holds the documented JSON layout, in nT.
    with open(path, "rb") as fh:
        for _, ch, msg in make_reader(fh).iter_messages(topics=["/fluxgate"]):
            obj = json.loads(msg.data)
            assert ch.message_encoding == "json"
            assert obj["t_ns"] == int(mem.mag.t_ns[0])
            np.testing.assert_allclose(obj["mag_nT"], mem.mag.values[0], rtol=1e-15)
            break


@pytest.mark.parametrize(("mag_type", "turntable_type"), [
    ("sensor_msgs/msg/MagneticField", "std_msgs/msg/Float64"),
    ("magalign.Magnetometer", "magalign.Turntable"),
])
def test_turntable_roundtrip(tmp_path, mag_type, turntable_type):
    motion = {"profile": "turntable", "rate_deg_s": 200.0, "rate_modulation": 0.3,
              "modulation_period_s": 1.0, "attitude_source": "turntable"}
    d = _scenario({"mag_type": mag_type, "turntable_type": turntable_type,
                   "attitude_type": ("magalign.AttitudeQuaternion"
                                     if mag_type.startswith("magalign.")
                                     else "sensor_msgs/msg/Imu")},
                  motion=motion, effects={"axis_tilt": {"tilt_deg": 2.0, "azimuth_deg": 10.0}})
    sim, mem, back, _ = _roundtrip(tmp_path, d)
    _check_common(mem, back)
    assert back.attitude is None and mem.attitude is None
    np.testing.assert_array_equal(back.turntable.t_ns, mem.turntable.t_ns)
    np.testing.assert_allclose(back.turntable.angle_rad, mem.turntable.angle_rad, atol=1e-12)
    assert mem.turntable.angle_rad[-1] > 2 * math.pi  # unwrapped past one turn
    roles = {c.role for c in back.channels}
    assert roles == {Role.MAGNETOMETER, Role.TURNTABLE}


def test_inspva_azimuth_convention(tmp_path):
    # Li 2020 heading -90 deg turns body y (NovAtel's forward axis) to point east.
    motion = {"profile": "static_sweep", "heading_start_deg": -90.0, "heading_step_deg": 30.0,
              "n_headings": 12, "pitch_deg": 0.0, "roll_deg": 0.0, "dwell_s": 0.1}
    d = _scenario({"attitude_type": "novatel_oem7_msgs/msg/INSPVA",
                   "attitude_topic": "/inspva"}, motion=motion, noise={})
    del d["timing"]
    sim, mem, back, path = _roundtrip(tmp_path, d)
    fwd = quat_rotate(back.attitude.q_enu_body, np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(fwd[0], [1.0, 0.0, 0.0], atol=1e-12)
    az = []
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, _, _, msg in reader.iter_decoded_messages(topics=["/inspva"]):
            az.append(msg.azimuth)
    # Azimuth is clockwise from north: 90 = east; heading +30 deg (counter-clockwise) each step.
    want = np.mod(90.0 - 30.0 * np.arange(12), 360.0)
    np.testing.assert_allclose(np.mod(np.array(az) - want + 180.0, 360.0) - 180.0, 0.0, atol=1e-9)
    assert az[0] == pytest.approx(90.0, abs=1e-9)
    # ... and the forward axis points where the azimuth says: (sin az, cos az) in (east, north).
    fwd = quat_rotate(back.attitude.q_enu_body, np.array([0.0, 1.0, 0.0]))
    azr = np.radians(az)
    np.testing.assert_allclose(fwd[:, :2], np.stack([np.sin(azr), np.cos(azr)], -1), atol=1e-12)


@pytest.mark.parametrize("variant", ["oem7_header", "novatel_header", "no_nov_header"])
def test_inspva_header_layouts(tmp_path, variant):
    # INSPVA's header differs between driver versions; each layout must read back the same.
    d = _scenario({"attitude_type": "novatel_oem7_msgs/msg/INSPVA", "attitude_variant": variant})
    sim, mem, back, _ = _roundtrip(tmp_path, d)
    _check_common(mem, back)
    np.testing.assert_array_equal(back.attitude.t_ns, mem.attitude.t_ns)
    _same_quat(back.attitude.q_enu_body, mem.attitude.q_enu_body)


def test_ros2_magnetic_field_is_tesla_on_the_wire(tmp_path):
    d = _scenario({"mag_type": "sensor_msgs/msg/MagneticField", "attitude_type":
                   "sensor_msgs/msg/Imu"})
    sim, mem, back, path = _roundtrip(tmp_path, d)
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, _, _, msg in reader.iter_decoded_messages(topics=["/mag"]):
            f = msg.magnetic_field
            np.testing.assert_allclose([f.x, f.y, f.z], mem.mag.values[0] * 1e-9, rtol=1e-15)
            assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == (
                mem.mag.t_ns[0])
            break


def test_demo_recording_is_small_and_reads_back(tmp_path):
    sim = simulate(load_scenario(ROOT / "pipeline" / "demo" / "line_04.toml"))
    path = write_simulated(sim, tmp_path / "line_04.mcap")
    assert path.stat().st_size < 3_000_000
    back = read_recording(path)
    _check_common(sim.recording, back)
    _same_quat(back.attitude.q_enu_body, sim.recording.attitude.q_enu_body)


def test_cli_simulate(tmp_path, capsys):
    out = tmp_path / "li.mcap"
    scen = ROOT / "pipeline" / "scenarios" / "li2020_section41.toml"
    assert main(["simulate", str(scen), "--out", str(out), "--seed", "3"]) == 0
    assert "360 magnetometer" in capsys.readouterr().out
    back = read_recording(out)
    np.testing.assert_allclose(back.mag.values, simulate(load_scenario(scen)).recording.mag.values,
                               rtol=1e-15)


def test_cli_simulate_bad_scenario(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('[motion]\nprofile = "turntable"\nrate = 3\n')
    assert main(["simulate", str(bad), "--out", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and "motion.rate" in err[0] and "line 3" in err[0]
    assert not (tmp_path / "x.mcap").exists()
    assert main(["simulate", str(bad), "--challenge", "2", "--out", str(tmp_path)]) == 2


def test_cli_simulate_challenge(tmp_path):
    # --challenge hands over to pipeline.app.challenge.generate (DIAGNOSE's generator).
    out = tmp_path / "chal"
    assert main(["simulate", "--challenge", "1", "--seed", "4", "--out", str(out)]) == 0
    recs = sorted(out.glob("*.mcap"))
    assert len(recs) == 1
    assert len(read_recording(recs[0]).mag) > 0

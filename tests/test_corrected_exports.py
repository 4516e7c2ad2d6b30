"""The corrected MCAP's /tf_static (body -> mag) and |B| channel, read back with mcap readers."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from pipeline.core.geometry import quat_to_matrix
from pipeline.core.recording import AttitudeSeries
from pipeline.io.mcap_read import read_recording
from pipeline.io.mcap_write import write_recording
from pipeline.model.calibration import Calibration
from stages.write_mcap import write_corrected_mcap

B_ENU = np.array([1300.0, 15000.0, -49000.0])
T0 = 1_700_000_000_000_000_000


def _rot(rotvec_deg) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()


def _calibration() -> Calibration:
    D = np.array([[1.02, 0.01, -0.005], [0.01, 0.98, 0.003], [-0.005, 0.003, 1.01]])
    return Calibration(R_body_mag=_rot([1.5, -2.0, 30.0]), sigma_rotvec_deg=[0.01] * 3,
                       B_enu_nT=B_ENU, estimator="truth", residual_rms_nT=0.0, n_samples=0,
                       D=D, offset_nT=[250.0, -120.0, 80.0])


def _recording(tmp_path, cal: Calibration, *, json_family: bool, frame: str):
    from scipy.spatial.transform import Rotation

    n = 400
    t = T0 + np.arange(n, dtype=np.int64) * 10_000_000  # 100 Hz
    rng = np.random.default_rng(3)
    q = Rotation.from_rotvec(rng.normal(0, 1.0, (n, 3))).as_quat()  # scalar last
    y = cal.predict(t, AttitudeSeries(t, q))  # noise-free raw magnetometer, mag frame, nT
    kw = {}
    if json_family:
        kw = {"mag_type": "magalign.Magnetometer", "attitude_type": "magalign.AttitudeQuaternion"}
        mag = {"mag_nT": y}
    else:
        mag = {"mag_nT": y}
    path = write_recording(tmp_path / "rec.mcap", mag_t_ns=t, q_enu_body=q, attitude_t_ns=t,
                           mag_frame_id="mag_link", attitude_frame_id=frame, **mag, **kw)
    return read_recording(path), y


@pytest.mark.parametrize("json_family", [False, True], ids=["ros2", "json"])
def test_tf_static_and_magnitude_read_back(tmp_path, json_family):
    cal = _calibration()
    rec, y = _recording(tmp_path, cal, json_family=json_family, frame="imu_link")
    out = write_corrected_mcap(rec, cal, tmp_path / "out.corrected.mcap")
    with open(out, "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        tf = list(reader.iter_decoded_messages(topics=["/tf_static"]))
    assert len(tf) == 1
    schema, channel, message, msg = tf[0]
    assert schema.name == "tf2_msgs/msg/TFMessage" and channel.message_encoding == "cdr"
    assert message.log_time == T0
    (tr,) = msg.transforms
    # the attitude is sensor_msgs/Imu here: its frame_id names the body frame
    assert tr.header.frame_id == ("body" if json_family else "imu_link")
    assert tr.child_frame_id == "mag_link"
    assert (tr.header.stamp.sec, tr.header.stamp.nanosec) == divmod(T0, 1_000_000_000)
    assert [tr.transform.translation.x, tr.transform.translation.y,
            tr.transform.translation.z] == [0.0, 0.0, 0.0]
    r = tr.transform.rotation
    q = np.array([r.x, r.y, r.z, r.w])
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12
    assert np.abs(quat_to_matrix(q) - cal.R_body_mag).max() < 1e-12
    # a mag-frame vector rotated by the transform is the body-frame vector
    v_mag = np.array([0.3, -0.5, 0.8])
    assert np.allclose(quat_to_matrix(q) @ v_mag, cal.R_body_mag @ v_mag, atol=1e-12)

    # |B| channel: one message per magnetometer sample, the calibrated magnitude in nT:
    # noise-free data restored with the true model give |B_enu| (49 uT) to float precision
    topic = "/mag/magnitude"
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        (ch,) = [c for c in summary.channels.values() if c.topic == topic]
        if json_family:
            rows = [(m.log_time, json.loads(m.data)) for _, _, m in
                    reader.iter_messages(topics=[topic])]
            t = np.array([d["t_ns"] for _, d in rows])
            assert {d["frame_id"] for _, d in rows} == {"mag_link"}
            b = np.array([d["magnitude_nT"] for _, d in rows])
            assert summary.schemas[ch.schema_id].name == "magalign.FieldMagnitude"
        else:
            rows = [(m.log_time, d) for _, _, m, d in reader.iter_decoded_messages(
                topics=[topic])]
            t = np.array([lt for lt, _ in rows])
            b = np.array([d.data for _, d in rows])
            assert summary.schemas[ch.schema_id].name == "std_msgs/msg/Float64"
    assert ch.metadata.get("unit") == "nT"
    assert len(b) == len(rec.mag) == 400
    assert np.array_equal(t, rec.mag.t_ns)
    assert np.abs(b - np.linalg.norm(B_ENU)).max() < 1e-6
    # and it is not the raw magnitude (offset and D were removed): they differ by > 100 nT
    assert np.abs(np.linalg.norm(y, axis=1) - np.linalg.norm(B_ENU)).max() > 100.0


def test_pose_attitude_has_no_body_frame_name(tmp_path):
    cal = _calibration()
    from scipy.spatial.transform import Rotation

    n = 50
    t = T0 + np.arange(n, dtype=np.int64) * 10_000_000
    q = Rotation.from_rotvec(np.random.default_rng(0).normal(0, 1, (n, 3))).as_quat()
    y = cal.predict(t, AttitudeSeries(t, q))
    p = write_recording(tmp_path / "p.mcap", mag_t_ns=t, mag_nT=y, attitude_t_ns=t,
                        q_enu_body=q, attitude_type="geometry_msgs/msg/PoseStamped",
                        attitude_frame_id="world")
    rec = read_recording(p)
    assert rec.attitude_frame_id == ""  # a pose's frame_id is the reference frame, "world"
    out = write_corrected_mcap(rec, cal, tmp_path / "p.corrected.mcap")
    with open(out, "rb") as f:
        (tf,) = [m for *_, m in make_reader(f, decoder_factories=[DecoderFactory()])
                 .iter_decoded_messages(topics=["/tf_static"])]
    assert tf.transforms[0].header.frame_id == "body"
    assert tf.transforms[0].child_frame_id == "mag"


@pytest.mark.parametrize("json_family", [False, True], ids=["ros2", "json"])
def test_info_does_not_call_the_magnitude_a_turntable(tmp_path, capsys, json_family):
    """The |B| channel is a number in nT: neither a turntable angle nor a magnetometer."""
    from pipeline.app.cli import main

    cal = _calibration()
    rec, _ = _recording(tmp_path, cal, json_family=json_family, frame="imu_link")
    out = write_corrected_mcap(rec, cal, tmp_path / "out.corrected.mcap")
    assert main(["info", "--json", str(out)]) == 0
    roles = {c["topic"]: c["role"] for c in json.loads(capsys.readouterr().out)["channels"]}
    assert roles["/mag/magnitude"] == "other", roles
    assert roles["/mag"] == "magnetometer"
    assert "turntable" not in roles.values()

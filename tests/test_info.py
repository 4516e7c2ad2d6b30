"""READER: ``magalign info`` on simulated-by-writer files, cut files and the real lab data."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _reader_fixtures import DEFS, motion, write_ros2

from pipeline.cli import main
from pipeline.errors import RecoveredDataWarning
from pipeline.mcap_read import read_recording

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
MAG = "sensor_msgs/msg/MagneticField"


def _info(capsys, *args):
    assert main(["info", *args]) == 0
    return capsys.readouterr().out


def test_info_json_and_table(tmp_path, capsys):
    t, mag_T, q = motion(500, rate_hz=250.0)
    keep = np.arange(500) % 2 == 0
    p = write_ros2(tmp_path / "r.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, ["imu"]),
        ("/pose", "geometry_msgs/msg/PoseStamped", DEFS["geometry_msgs/msg/PoseStamped"],
         t[keep], q[keep], ["w"]),
        ("/temp", "std_msgs/msg/Float64", DEFS["std_msgs/msg/Float64"], t[:10],
         np.ones(10), [""])])
    out = json.loads(_info(capsys, str(p), "--json"))
    assert set(out) == {"channels", "duration_s", "problems"}
    ch = {c["topic"]: c for c in out["channels"]}
    assert ch["/mag"]["role"] == "magnetometer" and ch["/mag"]["count"] == 500
    assert ch["/mag"]["rate_hz"] == pytest.approx(250.0, rel=1e-9)
    assert ch["/pose"]["role"] == "attitude" and ch["/pose"]["count"] == 250
    assert ch["/pose"]["rate_hz"] == pytest.approx(125.0, rel=1e-9)
    assert ch["/temp"]["role"] == "turntable"
    assert out["duration_s"] == pytest.approx(499 / 250.0)
    assert out["problems"] == []
    table = _info(capsys, str(p))
    assert "/mag" in table and "magnetometer" in table and "250.000" in table


def test_info_reports_cut_file(tmp_path, capsys):
    t, mag_T, q = motion(300)
    p = write_ros2(tmp_path / "r.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, ["imu"]),
        ("/att", "sensor_msgs/msg/Imu", DEFS["sensor_msgs/msg/Imu"], t, q, ["b"])],
        chunk_size=4096)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.warns(RecoveredDataWarning):
        out = json.loads(_info(capsys, str(cut), "--json"))
    assert any(pr["code"] == "truncated" for pr in out["problems"])
    assert 0 < out["channels"][0]["count"] < 300


@pytest.mark.skipif(not REAL.is_dir(), reason=f"real lab recordings not present ({REAL})")
def test_real_lab_03(capsys):
    out = json.loads(_info(capsys, str(REAL / "lab_03.mcap"), "--json"))
    ch = {c["role"]: c for c in out["channels"]}
    assert ch["magnetometer"]["topic"] == "/imu/mag"
    assert ch["magnetometer"]["count"] == 53240
    assert round(ch["magnetometer"]["rate_hz"], 1) == 285.7
    assert ch["attitude"]["topic"] == "/mocap/pose" and ch["attitude"]["count"] == 51534
    rec = read_recording(REAL / "lab_03.mcap")  # the real indoor MEMS data pass every check
    assert 20_000 < np.median(np.linalg.norm(rec.mag.values, axis=1)) < 70_000
    assert rec.mag_frame_id == "imu"

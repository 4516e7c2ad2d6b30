"""READER: ``magalign info`` on simulated-by-writer files, cut files and the real lab data."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from _reader_fixtures import DEFS, motion, write_ros2

from pipeline.app.cli import main
from pipeline.io.mcap_read import read_recording

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
MAG = "sensor_msgs/msg/MagneticField"


def _info(capsys, *args):
    return _info_err(capsys, *args)[0]


def _info_err(capsys, *args) -> tuple[str, str]:
    assert main(["info", *args]) == 0
    got = capsys.readouterr()
    return got.out, got.err


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
    assert set(out) == {"channels", "duration_s", "problems"}  # CONVENTIONS, exactly
    assert "sample-and-hold: none" in _info(capsys, str(p))  # every message a new reading
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
    text, _err = _info_err(capsys, str(cut), "--json")
    out = json.loads(text)
    # the command prints what was lost, one line per warning
    assert f"magalign: warning: {cut}: file cut" in _err
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


def test_info_lists_value_problems_as_the_reader_finds_them(tmp_path, capsys):
    """NaN samples and zero quaternions: the reader's own checks, same counts (issue 9)."""
    t, mag_T, q = motion(300)
    mag_T[[3, 50]] = np.nan
    mag_T[77, 2] = np.inf
    q[[5, 6]] = 0.0
    p = write_ros2(tmp_path / "v.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, ["imu"]),
        ("/att", "sensor_msgs/msg/Imu", DEFS["sensor_msgs/msg/Imu"], t, q, ["b"])])
    out = json.loads(_info(capsys, str(p), "--json"))
    got = {(pr["code"], pr["message"].split(":")[0]): pr["count"] for pr in out["problems"]}
    assert got == {("nonfinite", "/mag"): 3, ("zero_quaternion", "/att"): 2}
    rec = read_recording(p)
    assert {(pr.code, pr.message.split(":")[0]): pr.count for pr in rec.problems} == got
    assert "NaN" in _info(capsys, str(p))


def test_info_json_lists_a_chunk_failing_its_crc_once(tmp_path, capsys):
    from mcap.reader import make_reader
    from mcap.writer import CompressionType

    t, mag_T, q = motion(300)
    p = write_ros2(tmp_path / "c.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, ["imu"]),
        ("/att", "sensor_msgs/msg/Imu", DEFS["sensor_msgs/msg/Imu"], t, q, ["b"])],
        compression=CompressionType.NONE, chunk_size=2048)
    with open(p, "rb") as fh:
        c = make_reader(fh).get_summary().chunk_indexes[2]
    data = bytearray(p.read_bytes())
    # chunk record: opcode, length, 3 x u64, u32 crc, compression string, u64 records length
    data[c.chunk_start_offset + 9 + 28 + 4 + len(c.compression) + 8 + 100] ^= 0xFF
    bad = tmp_path / "crc.mcap"
    bad.write_bytes(bytes(data))
    text, _err = _info_err(capsys, str(bad), "--json")
    out = json.loads(text)
    assert "CRC" in _err and _err.startswith("magalign: warning: ")
    crc = [pr for pr in out["problems"] if pr["code"] == "chunk_crc"]
    assert len(crc) == 1 and crc[0]["count"] > 0
    count = {ch["topic"]: ch["count"] for ch in out["channels"]}
    assert count["/mag"] + count["/att"] == 600 - crc[0]["count"]


def test_info_reports_sample_and_hold(tmp_path, capsys):
    """The repeats of a sensor that converts slower than it sends, and its native rate."""
    from pipeline.app.simulate import scenario_from_dict, simulate, write_simulated

    sc = {"name": "held", "timing": {"duration_s": 20.0, "mag_rate_hz": 100.0,
                                      "attitude_rate_hz": 100.0},
          "motion": {"profile": "multiaxis"}, "field": {"enu_nT": [0.0, 20000.0, -40000.0]},
          "effects": {"sample_hold": {"native_rate_hz": 70.0}}}
    p = write_simulated(simulate(scenario_from_dict(sc)), tmp_path / "held.mcap")
    table = _info(capsys, str(p))
    m = re.search(r"sample-and-hold: (\d+) of (\d+) /mag messages \((\d+\.\d) %\) repeat the "
                  r"previous reading; the sensor\s+converts\s+at about (\d+\.\d) Hz", table)
    assert m, table
    repeats, messages, pct, native = (float(x) for x in m.groups())
    assert native == pytest.approx(70.0, rel=0.02)
    assert pct == pytest.approx(30.0, abs=2.0) and repeats == pytest.approx(
        0.3 * messages, rel=0.05)
    assert all(len(line) <= 100 for line in table.splitlines()[1:])  # [0]: the path

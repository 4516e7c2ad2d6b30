"""``magalign info`` reports the attitude samples missing: gaps, and no attitude at the ends."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _reader_fixtures import DEFS, motion, write_ros2

from pipeline.app.cli import main
from pipeline.io.mcap_checks import attitude_gaps

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
MAG = "sensor_msgs/msg/MagneticField"
POSE = "geometry_msgs/msg/PoseStamped"


def _info(capsys, *args):
    assert main(["info", *args]) == 0
    return capsys.readouterr().out


def test_gaps_and_ends_counted_against_the_attitude_rate(tmp_path, capsys):
    n = 2000  # 200 Hz magnetometer and attitude
    t, mag_T, q = motion(n, rate_hz=200.0)
    keep = np.ones(n, bool)
    keep[:100] = False  # 0.5 s before the first attitude sample
    keep[-50:] = False  # 0.25 s after the last
    keep[700:730] = False  # a gap of 30 samples
    keep[1200:1220] = False  # and one of 20
    p = write_ros2(tmp_path / "r.mcap", [("/mag", MAG, DEFS[MAG], t, mag_T, ["imu"]),
                                         ("/pose", POSE, DEFS[POSE], t[keep], q[keep], ["w"])])
    out = json.loads(_info(capsys, str(p), "--json"))
    assert set(out) == {"channels", "duration_s", "problems"}
    gaps = [pr for pr in out["problems"] if pr["code"] == "attitude_gaps"]
    assert len(gaps) == 1 and gaps[0]["count"] == 200 == n - keep.sum()
    msg = gaps[0]["message"]
    assert msg.startswith("/pose: 200 attitude samples missing")
    assert "100 in the 0.500 s before" in msg and "50 in the 0.250 s after" in msg
    assert "50 in 2 gaps" in msg and "longest 0.155 s" in msg
    table = _info(capsys, str(p))
    assert "problems: none" not in table and "[attitude_gaps]" in table


def test_complete_attitude_has_no_gap_problem(tmp_path, capsys):
    t, mag_T, q = motion(500, rate_hz=100.0)
    jitter = np.random.default_rng(1).integers(-200_000, 200_000, 500)  # +-0.2 ms of 10 ms
    p = write_ros2(tmp_path / "r.mcap", [("/mag", MAG, DEFS[MAG], t, mag_T, ["imu"]),
                                         ("/pose", POSE, DEFS[POSE], t + jitter, q, ["w"])])
    out = json.loads(_info(capsys, str(p), "--json"))
    assert out["problems"] == []
    assert "problems: none" in _info(capsys, str(p))


def test_attitude_gaps_numbers():
    t = np.arange(1000, dtype=np.int64) * 10_000_000  # 100 Hz
    t = np.delete(t, np.r_[300:310, 600:601])
    g = attitude_gaps(t, span_ns=(-50_000_000, int(t[-1]) + 20_000_000))
    assert g["n_gaps"] == 2 and g["gap_samples"] == 11
    assert g["lead_samples"] == 5 and g["trail_samples"] == 2 and g["missing_samples"] == 18
    assert g["longest_gap_s"] == pytest.approx(0.11)
    assert g["gap_s"] == pytest.approx(0.11)  # 0.1 + 0.01 beyond one interval each
    assert g["missing_s"] == pytest.approx(0.11 + 0.05 + 0.02)
    assert attitude_gaps(np.arange(100, dtype=np.int64) * 10_000_000) is None


@pytest.mark.skipif(not REAL.is_dir(), reason=f"real lab recordings not present ({REAL})")
def test_real_lab_03_reports_the_missing_attitude(capsys):
    out = json.loads(_info(capsys, str(REAL / "lab_03.mcap"), "--json"))
    ch = {c["role"]: c for c in out["channels"]}
    missing = ch["magnetometer"]["count"] - ch["attitude"]["count"]
    assert missing == 1706
    gaps = [pr for pr in out["problems"] if pr["code"] == "attitude_gaps"]
    assert len(gaps) == 1 and gaps[0]["count"] == missing

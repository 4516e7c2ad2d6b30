"""``magalign export``: each format's numbers from a known calibration, and bad input."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.app.exports import (
    ardupilot_correct,
    ardupilot_params,
    matrix_from_rpy,
    rpy_from_matrix,
    to_ardupilot,
    to_magcal,
    to_ros_tf,
    to_yaml,
)
from pipeline.core.geometry import quat_to_matrix
from pipeline.core.verdict import Status, Verdict
from pipeline.model.calibration import Calibration

R_TRUE = Rotation.from_rotvec(np.radians([2.0, -3.5, 25.0])).as_matrix()
D_TRUE = np.array([[1.03, 0.012, -0.006], [0.012, 0.97, 0.004], [-0.006, 0.004, 1.01]])
O_TRUE = np.array([310.0, -1250.0, 480.0])  # nT


def _cal(status: Status | None = Status.OK, **kw) -> Calibration:
    verdict = None if status is None else Verdict(status, "because", 3.0, 4.0)
    base = dict(R_body_mag=R_TRUE, sigma_rotvec_deg=[0.02, 0.03, np.inf],
                B_enu_nT=[1300.0, 15000.0, -49000.0], estimator="ml", residual_rms_nT=4.0,
                n_samples=5000, D=D_TRUE, offset_nT=O_TRUE, time_offset_s=0.012,
                sigma_time_offset_s=0.001, verdict=verdict)
    base.update(kw)
    return Calibration(**base)


def _ours(cal: Calibration, y_nT: np.ndarray) -> np.ndarray:
    """The calibration applied to raw samples, body frame: R inv(D) (y - o)."""
    return cal.calibrated_mag(y_nT) @ cal.R_body_mag.T


def _params(text: str) -> dict[str, float]:
    rows = [ln.split(",") for ln in text.splitlines() if ln and not ln.startswith("#")]
    assert all(len(r) == 2 for r in rows)
    return {k: float(v) for k, v in rows}


RNG = np.random.default_rng(5)
Y_NT = RNG.normal(0, 30_000, (50, 3))  # raw samples of a 50,000 nT-scale field


# ------------------------------------------------------------------ ArduPilot

def test_ardupilot_offsets_in_milligauss_and_correction_equals_ours():
    cal = _cal()
    p = _params(to_ardupilot(cal))
    assert {"COMPASS_OFS_X", "COMPASS_DIA_Z", "COMPASS_ODI_Y", "COMPASS_CUS_YAW"} <= set(p)
    # ArduPilot adds the offset after rotating into the body frame: OFS = -R o, in mGauss
    ofs = np.array([p["COMPASS_OFS_X"], p["COMPASS_OFS_Y"], p["COMPASS_OFS_Z"]])
    assert np.allclose(ofs, -(R_TRUE @ O_TRUE) / 100.0, rtol=1e-8)
    assert np.abs(ofs).max() < 15.0  # 1250 nT = 12.5 mGauss, not 1250
    # ArduPilot's whole correction, with the printed numbers, gives our body-frame field
    got_mG = ardupilot_correct(p, Y_NT / 100.0)
    assert np.abs(got_mG * 100.0 - _ours(cal, Y_NT)).max() < 0.01  # nT, of ~50,000
    # the soft-iron matrix is normalised (det 1), the size is in COMPASS_SCALE
    S = np.array([[p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
                  [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
                  [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]]])
    assert abs(np.linalg.det(S) - 1.0) < 1e-7
    assert abs(p["COMPASS_SCALE"] ** 3 - 1.0 / np.linalg.det(D_TRUE)) < 1e-7
    assert p["COMPASS_ORIENT"] == 100


def test_ardupilot_custom_orientation_convention():
    """COMPASS_CUS_*: R_body_mag = Rz(yaw) Ry(pitch) Rx(roll), degrees (ArduPilot from_euler)."""
    def rx(a):
        return Rotation.from_euler("x", a, degrees=True).as_matrix()

    def rz(a):
        return Rotation.from_euler("z", a, degrees=True).as_matrix()

    for R, want in ((rz(30.0), (0.0, 0.0, 30.0)), (rx(10.0), (10.0, 0.0, 0.0)),
                    (rz(-40.0) @ rx(5.0), (5.0, 0.0, -40.0))):
        p = ardupilot_params(_cal(R_body_mag=R, D=None, offset_nT=None))
        got = (p["COMPASS_CUS_ROLL"], p["COMPASS_CUS_PIT"], p["COMPASS_CUS_YAW"])
        assert np.allclose(got, want, atol=1e-9), (got, want)
        assert p["COMPASS_DIA_X"] == 1.0 and p["COMPASS_ODI_Z"] == 0.0
    # intrinsic z-y'-x'' of scipy is the same composition
    r, pch, y = rpy_from_matrix(R_TRUE)
    assert np.allclose(Rotation.from_matrix(R_TRUE).as_euler("ZYX"), [y, pch, r], atol=1e-12)
    # round trip through the printed degrees
    p = _params(to_ardupilot(_cal()))
    back = matrix_from_rpy(*(math.radians(p[f"COMPASS_CUS_{k}"]) for k in ("ROLL", "PIT", "YAW")))
    assert np.abs(back - R_TRUE).max() < 1e-8


# ------------------------------------------------------------------ magcal

def _matlab(text: str, name: str) -> np.ndarray:
    m = re.search(rf"^{name} = \[(.*)\];$", text, re.M)
    assert m, text
    return np.array([[float(x) for x in row.split()] for row in m.group(1).split(";")])


def test_magcal_A_and_b():
    cal = _cal()
    text = to_magcal(cal)
    A, b = _matlab(text, "A"), _matlab(text, "b")
    assert A.shape == (3, 3) and b.shape == (1, 3)
    assert np.abs(A @ D_TRUE - np.eye(3)).max() < 1e-12
    assert np.allclose(b[0], O_TRUE, rtol=1e-15)
    # magcal's use, row vectors: (raw - b) * A is our mag-frame calibrated field
    assert np.abs((Y_NT - b) @ A - cal.calibrated_mag(Y_NT)).max() < 1e-8


def test_magcal_without_soft_iron_is_identity():
    text = to_magcal(_cal(D=None, offset_nT=None))
    assert np.array_equal(_matlab(text, "A"), np.eye(3))
    assert np.array_equal(_matlab(text, "b"), np.zeros((1, 3)))


# ------------------------------------------------------------------ ros-tf

def test_ros_tf_quaternion_is_R_body_mag():
    line = to_ros_tf(_cal(), "imu_link", "mag link")
    assert line.startswith("ros2 run tf2_ros static_transform_publisher --x 0 --y 0 --z 0 ")
    vals = {k: float(v) for k, v in re.findall(r"--q([xyzw]) (\S+)", line)}
    q = np.array([vals[k] for k in "xyzw"])
    assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[3] >= 0
    assert np.abs(quat_to_matrix(q) - R_TRUE).max() < 1e-12
    assert "--frame-id imu_link --child-frame-id 'mag link'" in line
    assert "--frame-id base_link --child-frame-id mag" in to_ros_tf(_cal())


# ------------------------------------------------------------------ yaml

def test_yaml_reads_back_with_a_yaml_parser():
    yaml = pytest.importorskip("yaml")
    cal = _cal(status=Status.QUESTIONABLE, time_offset_s=1e-5)
    d = yaml.safe_load(to_yaml(cal))
    assert np.abs(np.array(d["R_body_mag"]) - R_TRUE).max() < 1e-15
    assert np.allclose(d["rotvec_body_mag_deg"], cal.rotvec_body_mag_deg, rtol=1e-15)
    assert np.array_equal(d["D"], D_TRUE) and d["offset_nT"] == O_TRUE.tolist()
    assert d["sigma_rotvec_deg"][:2] == [0.02, 0.03] and d["sigma_rotvec_deg"][2] is None
    assert d["time_offset_s"] == 1e-5 and isinstance(d["time_offset_s"], float)
    assert d["verdict"] == {"status": "QUESTIONABLE", "reason": "because",
                            "sensor_noise_nT": 3.0, "residual_rms_nT": 4.0}
    assert d["estimator"] == "ml" and d["n_samples"] == 5000
    old = yaml.safe_load(to_yaml(_cal(status=None, D=None)))  # an older file: no verdict
    assert "verdict" not in old and old["D"] is None


# ------------------------------------------------------------------ the command

def _run(*args: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.app.cli", "export", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=120)


def _write(tmp_path, cal: Calibration, name="calibration.json"):
    p = tmp_path / name
    p.write_text(cal.to_json())
    return p


def test_command_prints_each_format(tmp_path):
    p = _write(tmp_path, _cal())
    for fmt, first in (("ardupilot", "#"), ("magcal", "%"), ("ros-tf", "ros2 run"),
                       ("yaml", "#")):
        r = _run(str(p), "--format", fmt, cwd=tmp_path)
        assert r.returncode == 0 and r.stderr == "", (fmt, r.stderr)
        assert r.stdout.startswith(first)
    r = _run(str(p), "--format", "ros-tf", "--body-frame", "base", "--mag-frame", "compass",
             cwd=tmp_path)
    assert r.stdout.rstrip().endswith("--frame-id base --child-frame-id compass")


def test_refused_is_not_exported_questionable_warns(tmp_path):
    r = _run(str(_write(tmp_path, _cal(Status.REFUSED))), "--format", "yaml", cwd=tmp_path)
    assert r.returncode == 2 and r.stdout == ""
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and "refused" in err[0] and "calibration.json" in err[0]
    r = _run(str(_write(tmp_path, _cal(Status.QUESTIONABLE))), "--format", "magcal",
             cwd=tmp_path)
    assert r.returncode == 0 and r.stdout.startswith("%")
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and "warning" in err[0] and "QUESTIONABLE" in err[0]
    r = _run(str(_write(tmp_path, _cal(None))), "--format", "magcal", cwd=tmp_path)
    assert r.returncode == 0 and r.stderr == ""  # older files have no verdict


@pytest.mark.parametrize("case", ["missing", "not_json", "not_calibration", "bad_format",
                                  "not_rotation"])
def test_bad_input_one_line_exit_2(tmp_path, case):
    p = tmp_path / "cal.json"
    fmt = "yaml"
    if case == "not_json":
        p.write_text("t,x,y,z\n1,2,3,4\n")
    elif case == "not_calibration":
        p.write_text(json.dumps({"format": "something/1"}))
    elif case == "bad_format":
        _write(tmp_path, _cal(), "cal.json")
        fmt = "px4"
    elif case == "not_rotation":
        d = _cal().to_dict()
        d["R_body_mag"] = (2 * R_TRUE).tolist()
        p.write_text(json.dumps(d))
    r = _run(str(p), "--format", fmt, cwd=tmp_path)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and r.stdout == ""
    assert len(err) == 1 and err[0].startswith("magalign: ") and "Traceback" not in r.stderr
    if case == "bad_format":
        assert "px4" in err[0] and "export -h" in err[0]
    else:
        assert str(p) in err[0]

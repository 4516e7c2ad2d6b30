"""``magalign export``: each format's numbers from a known calibration, and bad input."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.app.exports import (
    FORMATS,
    ardupilot_correct,
    ardupilot_params,
    export_text,
    matrix_from_rpy,
    rpy_from_matrix,
    to_ardupilot,
    to_magcal,
    to_ros_tf,
    to_yaml,
)
from pipeline.core.errors import InputError
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
        assert not {"COMPASS_DIA_X", "COMPASS_ODI_Z", "COMPASS_SCALE", "COMPASS_OFS_X"} & set(p)
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


def test_magcal_defines_only_what_was_estimated():
    text = to_magcal(_cal(D=None))
    assert re.search(r"^A =", text, re.M) is None and "A is left out" in text
    assert np.allclose(_matlab(text, "b")[0], O_TRUE)
    text = to_magcal(_cal(offset_nT=None))
    assert re.search(r"^b =", text, re.M) is None and "b is left out" in text
    assert np.abs(_matlab(text, "A") @ D_TRUE - np.eye(3)).max() < 1e-12
    with pytest.raises(InputError, match="D and offset_nT were not estimated"):
        to_magcal(_cal(D=None, offset_nT=None))


# ------------------------------------------------------------------ ros-tf

def test_ros_tf_quaternion_is_R_body_mag():
    text = to_ros_tf(_cal(), "imu_link", "mag link")
    line = text.splitlines()[-1]  # comments first, the command last
    assert all(ln.startswith("#") for ln in text.splitlines()[:-1])
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
    for fmt, first in (("ardupilot", "#"), ("magcal", "%"), ("ros-tf", "#"), ("yaml", "#")):
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


# ------------------------------------------------------------------ what a file holds

#: The extension each format's file gets when a user saves the output.
EXT = {"ardupilot": "parm", "magcal": "m", "ros-tf": "sh", "yaml": "yaml"}
COMMENT = {"ardupilot": "#", "magcal": "%", "ros-tf": "#", "yaml": "#"}


def _export_file(cal_path, fmt: str, tmp_path, *extra: str):
    """Run ``magalign export`` with stdout into a file, as a user saves it; return the result."""
    out = tmp_path / f"{cal_path.stem}.{EXT[fmt]}"
    with open(out, "w") as fh:
        r = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "export", str(cal_path),
                            "--format", fmt, *extra], cwd=tmp_path, stdout=fh,
                           stderr=subprocess.PIPE, text=True, timeout=120)
    return r, out.read_text()


def _comments(text: str, fmt: str) -> str:
    """The comment lines, unwrapped into one string (continuations joined by a space)."""
    c = COMMENT[fmt]
    return " ".join(ln[len(c):].strip() for ln in text.splitlines() if ln.startswith(c))


def _lab02_like(**kw) -> Calibration:
    """As lab_02's calibration: rotation and time offset only, D and offset null."""
    base = dict(D=None, offset_nT=None, status=Status.QUESTIONABLE,
                effects={"hard_iron_step": [{"windows_s": [[38.3, 95.3]],
                                             "offset_nT": [-6614.0, -1250.0, 57941.0]}]})
    base.update(kw)
    return _cal(**base)


def test_null_offset_and_D_are_left_out_of_every_file(tmp_path):
    cal = _lab02_like()
    p = _write(tmp_path, cal)
    # ArduPilot: the orientation only, no default that would overwrite the autopilot's own
    r, text = _export_file(p, "ardupilot", tmp_path)
    assert r.returncode == 0
    params = _params(text)
    assert set(params) == {"COMPASS_ORIENT", "COMPASS_CUS_ROLL", "COMPASS_CUS_PIT",
                           "COMPASS_CUS_YAW"}
    for name in ("COMPASS_OFS", "COMPASS_DIA", "COMPASS_ODI", "COMPASS_SCALE"):
        assert not [ln for ln in text.splitlines() if ln.startswith(name)], name
    notes = _comments(text, "ardupilot")
    assert "COMPASS_OFS_X/Y/Z are left out" in notes and "offset was not estimated" in notes
    assert "COMPASS_DIA_*, COMPASS_ODI_* and COMPASS_SCALE are left out" in notes
    assert "--estimate offset" in notes and "--estimate soft_iron" in notes
    assert "time offset +12.0 ms" in notes and "hard_iron_step" in notes
    # with the autopilot's offsets and soft iron at their defaults, ours again
    assert np.abs(ardupilot_correct(params, Y_NT / 100.0) * 100.0 - _ours(cal, Y_NT)).max() < 0.01
    # magcal: no A, no b and no rotation would be an empty file: refused, one line
    r, text = _export_file(p, "magcal", tmp_path)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and text == "" and len(err) == 1, r.stderr
    assert str(p) in err[0] and "D and offset_nT were not estimated" in err[0]
    # ros-tf: the rotation only, and the file says what else calibration.json holds
    r, text = _export_file(p, "ros-tf", tmp_path)
    assert r.returncode == 0 and "time_offset_s" in _comments(text, "ros-tf")
    # YAML: null (never a default) with the reason above it
    r, text = _export_file(p, "yaml", tmp_path)
    assert r.returncode == 0
    assert re.search(r"^# offset_nT: not estimated: .*\n(#.*\n)*offset_nT: null$", text, re.M)
    assert re.search(r"^# D: not estimated: .*\n(#.*\n)*D: null$", text, re.M)
    yaml = pytest.importorskip("yaml")
    d = yaml.safe_load(text)
    assert d["offset_nT"] is None and d["D"] is None and d["unobservable_axes_body"] == []


def test_one_null_term_is_left_out_the_other_kept(tmp_path):
    r, text = _export_file(_write(tmp_path, _cal(offset_nT=None)), "ardupilot", tmp_path)
    params = _params(text)
    assert r.returncode == 0 and "COMPASS_OFS_X" not in params
    assert {"COMPASS_DIA_X", "COMPASS_ODI_Y", "COMPASS_SCALE"} <= set(params)
    assert "COMPASS_OFS_X/Y/Z are left out" in _comments(text, "ardupilot")
    r, text = _export_file(_write(tmp_path, _cal(D=None)), "ardupilot", tmp_path)
    params = _params(text)
    assert {"COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_OFS_Z"} <= set(params)
    assert not {"COMPASS_DIA_X", "COMPASS_ODI_X", "COMPASS_SCALE"} & set(params)
    ofs = np.array([params[f"COMPASS_OFS_{k}"] for k in "XYZ"])
    assert np.allclose(ofs, -(R_TRUE @ O_TRUE) / 100.0, rtol=1e-8)
    r, text = _export_file(_write(tmp_path, _cal(D=None)), "magcal", tmp_path)
    assert r.returncode == 0 and re.search(r"^A =", text, re.M) is None
    assert np.allclose(_matlab(text, "b")[0], O_TRUE)
    assert "A is left out" in _comments(text, "magcal")


def test_reason_a_requested_term_was_dropped_is_in_the_file(tmp_path):
    cal = _cal(D=None, not_estimated=({"term": "soft_iron",
                                       "reason": "rotations about one axis only"},))
    for fmt in ("ardupilot", "magcal", "yaml"):
        r, text = _export_file(_write(tmp_path, cal), fmt, tmp_path)
        assert r.returncode == 0
        assert "motion could not determine it: rotations about one axis only" in \
            _comments(text, fmt), fmt


@pytest.mark.parametrize("status", [Status.OK, Status.QUESTIONABLE, None])
def test_every_file_carries_the_verdict_and_its_reason(tmp_path, status):
    cal = _cal(status, offset_nT=None)
    p = _write(tmp_path, cal)
    for fmt in FORMATS:
        r, text = _export_file(p, fmt, tmp_path)
        assert r.returncode == 0, r.stderr
        notes = _comments(text, fmt)
        if status is None:
            assert "verdict: none recorded" in notes and r.stderr == ""
        else:
            assert f"verdict {status.value}: because" in notes, (fmt, text)
            assert "residual RMS 4.0 nT; sensor noise 3.0 nT" in notes
        if status is Status.QUESTIONABLE:
            err = r.stderr.strip().splitlines()
            assert len(err) == 1 and "QUESTIONABLE" in err[0] and "comments" in err[0]
            assert "check the reason above before loading" in notes
        else:
            assert r.stderr == ""
        # the comments are the file's first lines, before any value
        assert text.startswith(COMMENT[fmt] + " magalign calibration from ")
        assert all(len(ln) <= 100 for ln in text.splitlines()
                   if ln.startswith(COMMENT[fmt]) and str(p) not in ln)


def test_magcal_says_the_rotation_is_not_in_it(tmp_path):
    r, text = _export_file(_write(tmp_path, _cal()), "magcal", tmp_path)
    notes = _comments(text, "magcal")
    assert r.returncode == 0
    assert "not part of magcal's model" in notes and "R_body_mag in calibration.json" in notes
    assert "--format yaml or ros-tf" in notes


@pytest.mark.parametrize("fmt", FORMATS)
def test_refused_is_never_exported(tmp_path, fmt):
    p = _write(tmp_path, _cal(Status.REFUSED))
    r, text = _export_file(p, fmt, tmp_path)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and text == "" and len(err) == 1, r.stderr
    assert err[0].startswith(f"magalign: {p}: the calibration was refused (because)")
    with pytest.raises(InputError, match="refused"):  # the functions refuse too
        export_text(_cal(Status.REFUSED), fmt)


@pytest.mark.parametrize("fmt", FORMATS)
def test_undetermined_rotation_axis(tmp_path, fmt):
    """Ardupilot and tf cannot leave one axis of a rotation out: refused; YAML says it."""
    cal = _cal(unobservable_axes_body=(np.array([0.0, 0.0, 1.0]),))
    p = _write(tmp_path, cal)
    r, text = _export_file(p, fmt, tmp_path)
    if fmt in ("ardupilot", "ros-tf"):
        err = r.stderr.strip().splitlines()
        assert r.returncode == 2 and text == "" and len(err) == 1, r.stderr
        assert str(p) in err[0] and "R_body_mag" in err[0] and "[+0.00, +0.00, +1.00]" in err[0]
    else:
        assert r.returncode == 0
        if fmt == "yaml":
            assert "unobservable_axes_body:" in text
            assert "R_body_mag about those axes is not a measurement" in _comments(text, fmt)


def test_ros_tf_file_runs_as_a_shell_script(tmp_path):
    """The comments do not get in the way of running the saved command."""
    sh = shutil.which("sh")
    if sh is None:
        pytest.skip("no POSIX shell")
    r, text = _export_file(_write(tmp_path, _cal()), "ros-tf", tmp_path, "--mag-frame", "mag 1")
    assert r.returncode == 0
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "ros2"
    fake.write_text('#!/bin/sh\nfor a in "$@"; do echo "$a"; done\n')
    fake.chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}
    got = subprocess.run([sh, str(tmp_path / "calibration.sh")], capture_output=True,
                         text=True, env=env, timeout=60)
    args = got.stdout.splitlines()
    assert got.returncode == 0 and args[:2] == ["run", "tf2_ros"], got
    assert args[-2:] == ["--child-frame-id", "mag 1"]
    q = np.array([float(args[args.index(f"--q{k}") + 1]) for k in "xyzw"])
    assert np.abs(quat_to_matrix(q) - R_TRUE).max() < 1e-12

"""A recording restored with a calibration made elsewhere gets its own verdict.

Recordings from the independent generator (``tests/indep_gen.py``: scipy and mcap_ros2 only):
a calibration run, then lines restored with its calibration.json through ``process``. Each
line's verdict names where the calibration came from, measures the line's own residual and,
where the line's motion determines it, compares the rotation refitted on the line with the
calibration's in combined sigmas.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from indep_gen import Spec, write

from pipeline.core.verdict import verdict_line
from pipeline.model.calibration import Calibration
from pipeline.run.runner import ProcessOptions, process_recording

OPTS = dict(write_rerun=False, write_report=False)


@pytest.fixture(scope="module")
def calibration(tmp_path_factory) -> Path:
    """The calibration run: 40 s of hand-held rotation, R = (1, -1.5, 2) deg (the rotation
    alone: what the diagnosis adds is not what these tests are about). The seed is one whose
    halves agree as most nulls' do: seeds 3 and 4 fall in the 5 % the halves check flags on
    a null by chance (chi-square 8.4 and 8.2 for 3; bench/halves_null.py), and these tests
    are about the line's verdict, not that rate."""
    d = tmp_path_factory.mktemp("cal")
    rec = write(Spec("cal", seed=5, duration_s=40.0, mag_noise_nT=2.0), d / "cal.mcap")
    row = process_recording(rec, d / "out", options=ProcessOptions(diagnose=False, **OPTS))
    assert row["verdict"] == "OK", row["verdict_reason"]
    return Path(row["paths"]["calibration.json"])


def _line(tmp_path: Path, cal: Path, spec: Spec) -> dict:
    rec = write(spec, tmp_path / f"{spec.name}.mcap")
    return process_recording(rec, tmp_path / "out", options=ProcessOptions(
        calibration_path=cal, **OPTS))


def test_a_line_of_the_same_installation_is_ok_on_its_own_evidence(tmp_path, calibration):
    row = _line(tmp_path, calibration, Spec("same", seed=4, duration_s=40.0, mag_noise_nT=2.0))
    assert row["verdict"] == "OK", row["verdict_reason"]
    reason = row["verdict_reason"]
    assert reason.startswith("Calibration from cal/calibration.json (OK there)."), reason
    assert "agrees within" in reason
    line_cal = json.loads(Path(row["paths"]["calibration.json"]).read_text())
    ap = line_cal["checks"]["applied"]
    assert ap["rotation"]["determined_axes"] == ["x", "y", "z"]
    assert ap["rotation"]["max_z"] < 3.0
    # the line's own residual, measured on the line: the same noise as the calibration run's
    # (one sensor), not a copy of its number
    src = ap["source_residual_rms_nT"]
    assert line_cal["verdict"]["residual_rms_nT"] == pytest.approx(row["residual_rms_nT"])
    assert row["residual_rms_nT"] != src and 0.8 * src < row["residual_rms_nT"] < 1.25 * src


def test_a_sensor_that_moved_on_its_mount_is_caught(tmp_path, calibration):
    """The line's sensor sits 0.5 deg further about body x than at the calibration."""
    row = _line(tmp_path, calibration, Spec("moved", seed=5, duration_s=40.0, mag_noise_nT=2.0,
                                            rotvec_body_mag_deg=(1.5, -1.5, 2.0)))
    assert row["verdict"] == "QUESTIONABLE"
    ap = json.loads(Path(row["paths"]["calibration.json"]).read_text())["checks"]["applied"]
    d = np.asarray(ap["rotation"]["difference_deg"])
    assert abs(d[0] - 0.5) < 0.02 and np.all(np.abs(d[1:]) < 0.02)  # deg
    assert "differs from the calibration's by +0.50 deg about body x" in row["verdict_reason"]
    assert "What to do: calibrate again" in row["verdict_reason"]


def test_a_disturbance_on_the_line_is_questionable_not_refused(tmp_path, calibration):
    row = _line(tmp_path, calibration, Spec(
        "dist", seed=7, duration_s=40.0, mag_noise_nT=2.0,
        effects={"disturbance": {"windows_s": [[15.0, 25.0]], "peak_nT": 200.0,
                                 "direction_enu": [0.6, 0.0, 0.8]}}))
    assert row["verdict"] == "QUESTIONABLE", row["verdict_reason"]
    assert "magalign diagnose on this recording tells" in row["verdict_reason"]
    assert "agrees within" in row["verdict_reason"]  # the rotation still holds


def test_a_line_that_does_not_determine_the_rotation_checks_only_its_residual(calibration):
    """A refit whose sigmas are degrees (a line that barely turns) compares nothing."""
    from stages.check_applied import applied_verdict, rotation_check

    cal = Calibration.load(str(calibration))
    from pipeline.core.geometry import so3_exp

    refit = cal.replace(R_body_mag=so3_exp(np.radians([3.0, 0.0, 0.0])) @ cal.R_body_mag,
                        sigma_rotvec_deg=np.array([4.0, np.inf, 2.0]))
    rot = rotation_check(cal, refit)
    assert rot["determined_axes"] == [] and rot["max_z"] is None
    cal = cal.replace(checks={**cal.checks, "applied": {
        "source": "cal/calibration.json", "source_status": "OK", "sensor_noise_nT": 2.0,
        "source_noise_nT": None, "source_residual_rms_nT": 2.0, "rotation": rot}})
    v = applied_verdict(cal, 2.2)
    assert v.status.value == "OK"
    assert "does not determine the rotation: only the residual is checked" in v.reason


def test_a_questionable_calibration_never_gives_an_ok_line(tmp_path, calibration):
    d = json.loads(calibration.read_text())
    d["verdict"] = {**d["verdict"], "status": "QUESTIONABLE", "reason": "test: doubtful"}
    doubtful = tmp_path / "doubtful" / "calibration.json"
    doubtful.parent.mkdir()
    doubtful.write_text(json.dumps(d))
    row = _line(tmp_path, doubtful, Spec("same2", seed=4, duration_s=40.0, mag_noise_nT=2.0))
    assert row["verdict"] == "QUESTIONABLE"
    assert row["verdict_reason"].startswith(
        "Calibration from doubtful/calibration.json (QUESTIONABLE there).")


@pytest.mark.parametrize(("sigma", "shown"), [(0.00014, "+- 0.00014"), (0.0123, "+- 0.012"),
                                              (0.34, "+- 0.34"), (2.5, "+- 2.50")])
def test_the_verdict_line_gives_the_sigma_its_digits(calibration, sigma, shown):
    cal = Calibration.load(str(calibration))
    cal = cal.replace(sigma_rotvec_deg=np.full(3, sigma / np.sqrt(1.0)))
    line = verdict_line(cal)
    assert shown in line and "+- 0.00 " not in line, line

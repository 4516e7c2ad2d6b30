"""Everything read back is checked (issue 16): calibration.json field by field."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.errors import InputError
from pipeline.core.geometry import quat_to_matrix, rotvec_to_quat
from pipeline.core.validate import (
    check_calibration_dict,
    check_diagnosis_dict,
    check_metrics_dict,
)
from pipeline.model.calibration import Calibration

HERE = Path(__file__).resolve().parent


def _good() -> dict:
    R = quat_to_matrix(rotvec_to_quat(np.radians([1.2, -1.0, 1.2])))
    cal = Calibration(R_body_mag=R, sigma_rotvec_deg=[0.01, 0.02, np.inf],
                      B_enu_nT=[500.0, 20000.0, -45000.0], estimator="ml",
                      residual_rms_nT=1.5, n_samples=400,
                      unobservable_axes_body=(np.array([0.0, 0.0, 1.0]),),
                      D=np.diag([1.01, 0.99, 1.0]), offset_nT=[10.0, -5.0, 3.0],
                      sigma_D=np.full((3, 3), 1e-3), sigma_offset_nT=[0.1, 0.1, 0.2],
                      time_offset_s=0.004, sigma_time_offset_s=0.001)
    return json.loads(cal.to_json())


def test_written_calibration_passes_and_loads():
    d = _good()
    check_calibration_dict(d, "c.json")
    cal = Calibration.from_json(json.dumps(d), path="c.json")
    assert cal.n_samples == 400
    # an old file without the verdict and with the CONVENTIONS verdict both pass
    d["verdict"] = {"status": "QUESTIONABLE", "reason": "residual 3x the sensor noise",
                    "sensor_noise_nT": 0.5, "residual_rms_nT": 1.5}
    check_calibration_dict(d, "c.json")
    d["verdict"]["sensor_noise_nT"] = None  # no still window in the recording
    check_calibration_dict(d, "c.json")


def _rotated(d: dict, deg: float) -> None:
    dR = quat_to_matrix(rotvec_to_quat(np.radians([0.0, 0.0, deg])))
    d["R_body_mag"] = (dR @ np.asarray(d["R_body_mag"])).tolist()


BAD = [
    # (change, field named in the message, words)
    (lambda d: d.pop("R_body_mag"), "R_body_mag", "missing"),
    (lambda d: d.__setitem__("R_body_mag", [[1, 0, 0], [0, 1, 0]]), "R_body_mag", "shape"),
    (lambda d: d.__setitem__("R_body_mag", [[1, 0, 0], [0, 1, 0], [0, 0, "1"]]),
     "R_body_mag[2][2]", "number"),
    (lambda d: d.__setitem__("R_body_mag", [[1.1, 0, 0], [0, 1, 0], [0, 0, 1]]),
     "R_body_mag", "not a rotation"),
    (lambda d: d.__setitem__("R_body_mag", [[1, 0, 0], [0, 1, 0], [0, 0, -1]]),
     "R_body_mag", "reflection"),
    (lambda d: _rotated(d, 0.01), "rotvec_body_mag_deg", "does not describe R_body_mag"),
    (lambda d: d["rotvec_body_mag_deg"].__setitem__(0, 1.3), "rotvec_body_mag_deg",
     "does not describe"),
    (lambda d: d["sigma_rotvec_deg"].__setitem__(1, -0.1), "sigma_rotvec_deg[1]", "at least"),
    (lambda d: d.__setitem__("sigma_rotvec_deg", [0.1, 0.1]), "sigma_rotvec_deg", "shape"),
    (lambda d: d.__setitem__("unobservable_axes_body", [[0.0, 0.0, 2.0]]),
     "unobservable_axes_body[0]", "unit vector"),
    (lambda d: d.__setitem__("D", [[1, 0.1, 0], [0, 1, 0], [0, 0, 1]]), "D", "symmetric"),
    (lambda d: d.__setitem__("D", [[1, 0, 0], [0, -1, 0], [0, 0, 1]]), "D",
     "positive-definite"),
    (lambda d: d.__setitem__("offset_nT", [1.0, 2.0]), "offset_nT", "shape"),
    (lambda d: d.__setitem__("time_offset_s", "4 ms"), "time_offset_s", "number"),
    (lambda d: d.__setitem__("B_enu_nT", None), "B_enu_nT", "null"),
    (lambda d: d.__setitem__("residual_rms_nT", -1.0), "residual_rms_nT", "at least"),
    (lambda d: d.__setitem__("n_samples", 12.5), "n_samples", "whole number"),
    (lambda d: d.__setitem__("estimator", 3), "estimator", "string"),
    (lambda d: d.__setitem__("warnings", "careful"), "warnings", "list of strings"),
    (lambda d: d.__setitem__("verdict", {"status": "FINE", "reason": "",
                                         "sensor_noise_nT": 1.0, "residual_rms_nT": 1.0}),
     "verdict.status", "OK, QUESTIONABLE, REFUSED"),
    (lambda d: d.__setitem__("verdict", {"status": "OK", "reason": None,
                                         "sensor_noise_nT": -1.0, "residual_rms_nT": 1.0}),
     "verdict.sensor_noise_nT", "at least"),
    (lambda d: d.__setitem__("verdict", "OK"), "verdict", "object"),
]


@pytest.mark.parametrize(("change", "field", "words"), BAD,
                         ids=[f"{k}-{b[1]}" for k, b in enumerate(BAD)])
def test_each_bad_field_is_named(change, field, words):
    d = copy.deepcopy(_good())
    change(d)
    with pytest.raises(InputError) as ei:
        check_calibration_dict(d, "dir/calibration.json")
    line = ei.value.one_line()
    assert line.startswith("dir/calibration.json: "), line
    assert f"field {field}:" in line and words in line, line
    # the same through the loader of every reader of calibrations
    with pytest.raises(InputError, match=f"field {field.replace('[', '.').replace(']', '.')}"):
        Calibration.from_json(json.dumps(d), path="dir/calibration.json")


@pytest.mark.parametrize("d", [[1, 2], "x", None, {"format": "acme/2"}])
def test_not_a_calibration_object(d):
    with pytest.raises(InputError, match="JSON object|not a magalign.calibration/1"):
        check_calibration_dict(d, "c.json")


def test_diagnosis_and_metrics_checks():
    check_diagnosis_dict({"format": "magalign.diagnosis/1", "findings": [
        {"effect": "hard_iron", "params": {"offset_nT": [1, 2, 3]}}]}, "d.json")
    for bad, field in (({"findings": {}}, "findings"),
                       ({"findings": [{"params": {}}]}, "findings[0].effect"),
                       ({"findings": [{"effect": "x", "params": [1]}]}, "findings[0].params")):
        with pytest.raises(InputError, match=rf"field {field.replace('[', '.')}"):
            check_diagnosis_dict(bad, "d.json")
    with pytest.raises(InputError, match="JSON object"):
        check_metrics_dict([1], "m.json")
    with pytest.raises(InputError, match="field scopes"):
        check_metrics_dict({"scopes": 3}, "m.json")


def test_process_refuses_an_edited_calibration(tmp_path):
    """A calibration.json whose vector was edited is refused at the command line, exit 2."""
    import corpus

    rec = corpus.valid(tmp_path)
    d = _good()
    d["rotvec_body_mag_deg"] = [1.2, -1.0, 1.5]  # edited by hand, the matrix not
    cal = tmp_path / "calibration.json"
    cal.write_text(json.dumps(d))
    r = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "process", str(rec), "--out",
                        str(tmp_path / "out"), "--calibration", str(cal), "--no-progress"],
                       capture_output=True, text=True, timeout=600, cwd=HERE.parent)
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and str(cal) in r.stderr
    assert "rotvec_body_mag_deg" in r.stderr
    assert not (tmp_path / "out" / "valid" / "calibration.json").exists()

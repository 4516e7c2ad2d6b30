"""One recording, one answer: ``calibrate``, ``diagnose`` and ``process`` agree (issue 29).

The three commands run the same analysis stages (``pipeline.run.plan.Plan.analysis_stages``);
these tests run the installed program on recordings of the independent generator and read
back what each wrote. A model the user restricts with ``--estimate`` stays the answer, but
its sigma carries the shift that the terms the data select and it leaves out cause.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from indep_gen import Spec, write

from pipeline.model.calibration import Calibration

MAGALIGN = [sys.executable, "-m", "pipeline.app.cli"]


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    r = subprocess.run(MAGALIGN + list(args), cwd=cwd, capture_output=True, text=True,
                       timeout=900)
    assert r.returncode == 0, r.stderr
    return r


def _cal(path: Path) -> Calibration:
    return Calibration.from_json(path.read_text(), path=str(path))


@pytest.fixture(scope="module")
def gradient_recording(tmp_path_factory) -> tuple[Path, Spec]:
    """A hand-held recording through a field gradient (positions in a room frame)."""
    G = [[2500.0, 600.0, -400.0], [600.0, -1500.0, 700.0], [-400.0, 700.0, -1000.0]]
    spec = Spec("grad", seed=31, duration_s=60.0, mag_noise_nT=5.0,
                effects={"field_gradient": {"G_nT_per_m": G}})
    d = tmp_path_factory.mktemp("one_answer")
    return write(spec, d / "grad.mcap"), spec


def test_calibrate_diagnose_and_process_give_one_answer(gradient_recording, tmp_path):
    rec, spec = gradient_recording
    _run("calibrate", str(rec), "--out", str(tmp_path / "c"), cwd=tmp_path)
    _run("diagnose", str(rec), "--out", str(tmp_path / "d"), cwd=tmp_path)
    _run("process", str(rec), "--out", str(tmp_path / "p"), cwd=tmp_path)
    cals = [_cal(tmp_path / "c" / "calibration.json"), _cal(tmp_path / "d" / "calibration.json"),
            _cal(tmp_path / "p" / rec.stem / "calibration.json")]
    ref = cals[0]
    for c in cals[1:]:
        # the same computation: equal to numerical noise (not float bytes: the JSON rounds)
        assert np.allclose(c.rotvec_body_mag_deg, ref.rotvec_body_mag_deg, atol=1e-9)
        assert np.allclose(c.sigma_rotvec_deg, ref.sigma_rotvec_deg, rtol=1e-9)
        assert c.verdict.status is ref.verdict.status
        assert c.verdict.reason == ref.verdict.reason
    # and it is right: the gradient was modelled, so R is the truth within its sigmas
    err = np.abs(np.asarray(ref.rotvec_body_mag_deg) - np.asarray(spec.rotvec_body_mag_deg))
    assert np.all(err < 3 * np.asarray(ref.sigma_rotvec_deg)), (err, ref.sigma_rotvec_deg)
    assert np.all(err < 0.01)
    diag = json.loads((tmp_path / "d" / "diagnosis.json").read_text())
    assert "field_gradient" in [f["effect"] for f in diag["findings"]]


def test_a_restricted_model_carries_the_shift_of_what_it_leaves_out(gradient_recording,
                                                                     tmp_path):
    """``--estimate offset`` leaves the gradient out: the same R as the restricted fit, its
    sigma widened to cover the diagnosis' answer, and the verdict says why."""
    rec, spec = gradient_recording
    _run("calibrate", str(rec), "--out", str(tmp_path / "full"), cwd=tmp_path)
    r = _run("calibrate", str(rec), "--out", str(tmp_path / "restr"), "--estimate", "offset",
             cwd=tmp_path)
    full = _cal(tmp_path / "full" / "calibration.json")
    restr = _cal(tmp_path / "restr" / "calibration.json")
    left = restr.checks["left_out"]
    assert "field_gradient" in left["effects"]
    shift = np.asarray(left["shift_rotvec_deg"])
    noise = np.asarray(left["sigma_rotvec_noise_deg"])
    # the widened sigma is the noise sigma and the shift in quadrature
    assert np.allclose(restr.sigma_rotvec_deg, np.hypot(noise, shift), rtol=1e-9)
    d = np.abs(np.asarray(restr.rotvec_body_mag_deg) - np.asarray(full.rotvec_body_mag_deg))
    assert np.all(d <= np.hypot(restr.sigma_rotvec_deg, full.sigma_rotvec_deg) + 1e-9)
    assert restr.verdict.status.value == "QUESTIONABLE"
    assert "field gradient" in restr.verdict.reason and "--estimate" in restr.verdict.reason
    assert "restricted" in r.stdout


#: the findings whose params repeat a field of calibration.json (diagnosis effect -> key)
_IN_CALIBRATION = {"hard_iron": "offset_nT", "time_offset": "time_offset_s"}


@pytest.mark.parametrize("folder", sorted(
    p for p in (Path(__file__).parent / "golden").rglob("diagnosis.json")))
def test_findings_quote_the_final_model_as_the_calibration_does(folder):
    """A finding and the calibration state one value of each quantity: the final model's.

    The archived results of every recording (the real lab recordings among them, whose
    sample-and-hold handling refits the model after the search named its terms).
    """
    diag = json.loads(folder.read_text())
    cal = json.loads((folder.parent / "calibration.json").read_text())
    for f in diag["findings"]:
        p, e = f["params"], f["effect"]
        if e in _IN_CALIBRATION:
            key = _IN_CALIBRATION[e]
            np.testing.assert_allclose(p[key], cal[key], rtol=1e-9, atol=0)
            np.testing.assert_allclose(f["sigma"][key], cal[f"sigma_{key}"], rtol=1e-9, atol=0)
        elif e == "soft_iron":
            np.testing.assert_allclose(p["D"], cal["D"], rtol=1e-9, atol=0)
        elif e == "sample_hold":
            for k in ("native_rate_hz", "repeated_fraction"):
                assert p[k] == pytest.approx(cal["effects"]["sample_hold"][k], rel=1e-12)
                assert p[k] == pytest.approx(cal["sample_hold"][k], rel=1e-12)
            assert f"native rate {p['native_rate_hz']:.1f} Hz" in " ".join(cal["warnings"])
        elif e in cal.get("effects", {}) and isinstance(cal["effects"][e], dict):
            for k, v in p.items():
                if isinstance(v, int | float | list) and not isinstance(v, bool):
                    np.testing.assert_allclose(v, cal["effects"][e][k], rtol=1e-9, atol=1e-12)

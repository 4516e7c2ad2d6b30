"""Diagnosis of the real lab recordings (MEMS magnetometer + motion capture, indoors).

Decimated for runtime. Asserts that every finding lowers the held-out error and prints what
was found (run with ``-s`` to see the tables) for the lead's note.
"""

from pathlib import Path

import numpy as np
import pytest

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
FILES = sorted(REAL.glob("*.mcap")) if REAL.is_dir() else []

pytestmark = pytest.mark.real


@pytest.mark.skipif(not FILES, reason="real recordings absent: ../shared/data/real not found")
@pytest.mark.parametrize("path", FILES, ids=[p.stem for p in FILES])
def test_real_recording_findings_improve_heldout(path):
    from pipeline.core.recording import Context
    from pipeline.io.mcap_read import read_recording
    from stages.diagnose.result import DiagnoseConfig
    from stages.diagnose.stage import Diagnose
    from stages.resample import Resample

    rec = read_recording(path)
    ctx = Resample().run(Context(source=str(path), recording=rec))
    ctx = ctx.replace(calibration=None)
    cfg = DiagnoseConfig(max_samples=3000, max_findings=4)
    out = Diagnose(config=cfg).run(ctx)
    diag = out.diagnosis
    print(f"\n{path.name}\n{diag.table()}")
    assert diag.baseline["residual_rms_nT"] > 0
    for f in diag.findings:
        ev = f.evidence
        assert ev["heldout_rms_after_nT"] < ev["heldout_rms_before_nT"], f.effect
        assert ev["delta_bic"] < 0
    assert diag.final["heldout_rms_nT"] <= diag.baseline["heldout_rms_nT"]


LAB_03 = REAL / "lab_03.mcap"


@pytest.mark.skipif(not FILES, reason="real recordings absent: ../shared/data/real not found")
def test_real_recordings_sample_hold_rate_and_repeats():
    """The lab magnetometer converts at about 202 Hz; 29 % of its 285.7 Hz messages repeat."""
    from pipeline.io.mcap_read import read_recording
    from pipeline.model.sample_hold import detect_sample_hold

    for path in FILES:
        rec = read_recording(path)
        sh = detect_sample_hold(rec.mag.t_ns, rec.mag.values)
        assert sh is not None, path.name
        assert abs(sh.native_rate_hz - 202.4) < 2.0, path.name  # Hz
        assert abs(sh.repeated_fraction - 0.291) < 0.01, path.name
        assert abs(sh.message_rate_hz - 285.714) < 0.1, path.name


@pytest.mark.skipif(not LAB_03.exists(), reason="real recordings absent: lab_03.mcap not found")
def test_real_recording_gradient_and_sample_hold_findings():
    """lab_03 (positions in the motion-capture room frame): the sensor holds samples at
    ~202 Hz with ~29 % repeats; a sample_hold or field_gradient finding, if any, lowers the
    held-out error."""
    from pipeline.core.recording import Context
    from pipeline.io.mcap_read import read_recording
    from stages.diagnose.result import DiagnoseConfig
    from stages.diagnose.stage import Diagnose
    from stages.resample import Resample

    rec = read_recording(LAB_03)
    assert rec.position is not None and rec.position.frame.value == "attitude_source_local"
    ctx = Resample().run(Context(source=str(LAB_03), recording=rec)).replace(calibration=None)
    diag = Diagnose(config=DiagnoseConfig(max_samples=3000, max_findings=4)).run(ctx).diagnosis
    print(f"\n{LAB_03.name}\n{diag.table()}")
    by = {f.effect: f for f in diag.findings}
    # the repeats are a fact of the sensor (detected, and left out of every fit); the
    # finding is named only when handling them lowers the held-out error block by block,
    # which on lab_03 it does by under 0.1 % (not named at this sample budget)
    from pipeline.model.sample_hold import detect_sample_hold

    info = detect_sample_hold(rec.mag.t_ns, rec.mag.values)
    assert info is not None
    p = info.params()
    assert abs(p["native_rate_hz"] - 202.6) < 2.0  # Hz
    assert abs(p["repeated_fraction"] - 0.291) < 0.01
    sh = by.get("sample_hold")
    if sh is not None:
        assert sh.evidence["heldout_rms_after_nT"] < sh.evidence["heldout_rms_before_nT"]
    g = by.get("field_gradient")
    if g is not None:
        ev = g.evidence
        assert ev["heldout_rms_after_nT"] < ev["heldout_rms_before_nT"]
        assert ev["delta_bic"] < 0
        assert 1.0 < np.linalg.norm(np.asarray(g.params["G_nT_per_m"])) / 1e3 < 20.0  # uT/m

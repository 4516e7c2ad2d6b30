"""Diagnosis of the real lab recordings (MEMS magnetometer + motion capture, indoors).

Decimated for runtime. Asserts that every finding lowers the held-out error and prints what
was found (run with ``-s`` to see the tables) for the lead's note.
"""

from pathlib import Path

import pytest

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
FILES = sorted(REAL.glob("*.mcap")) if REAL.is_dir() else []

pytestmark = pytest.mark.real


@pytest.mark.skipif(not FILES, reason="real recordings absent: ../shared/data/real not found")
@pytest.mark.parametrize("path", FILES, ids=[p.stem for p in FILES])
def test_real_recording_findings_improve_heldout(path):
    from pipeline.mcap_read import read_recording
    from pipeline.recording import Context
    from stages.diagnose import Diagnose, DiagnoseConfig
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

"""Restore times each conversion as the diagnosis' sample-and-hold handling did.

The lab magnetometer repeats its conversions over runs of 1 or 3 messages; the diagnosis
chooses, on held-out data, the times its fit predicts them at (``anchored`` on every lab
recording) and stores the choice beside the ``sample_hold`` finding. Restore must then
evaluate the model at those sensing times, not at the stamps: the restored residual is the
fitted model's, and a long recording restored chunk by chunk gives the same rows.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import semireal
from test_stream_process import assert_restores_alike, chunked

from pipeline.io.mcap_read import read_recording
from pipeline.model.calibration import Calibration
from pipeline.model.sample_hold import anchored_times_ns, handling_of, repeated
from stages.restore import restore_samples

LAB5 = semireal.REAL_DIR / "lab_05.mcap"
GOLDEN = Path(__file__).parent / "golden" / "real" / "lab_05" / "calibration.json"
pytestmark = [
    pytest.mark.skipif(not LAB5.exists(), reason="real recordings absent: ../shared/data/real "
                       "not found"),
    pytest.mark.filterwarnings("ignore::pipeline.core.errors.RecoveredDataWarning"),
]


def _cal(handling: str | None) -> Calibration:
    """lab_05's archived final model, fitted on the anchored times, with ``handling``."""
    d = json.loads(GOLDEN.read_text())
    sh = dict(d["effects"]["sample_hold"])
    sh.pop("handling", None)
    if handling is not None:
        sh["handling"] = handling
    d["effects"] = {**d["effects"], "sample_hold": sh}
    return Calibration.from_json(json.dumps(d))


def test_the_diagnosis_handling_is_carried_by_the_calibration():
    assert handling_of(json.loads(GOLDEN.read_text())["effects"]) == "anchored"
    assert handling_of({"sample_hold": {"native_rate_hz": 200.0}}) is None
    assert handling_of({}) is None


def test_restore_at_the_sensing_times_fits_better_than_at_the_stamps():
    """The same model restored at the anchored times and at the stamps: the model was fitted
    on the anchored times, so its residual is lower there (the diagnosis measured 786 to
    722 nT held out); repeats of one conversion are restored alike."""
    rec = read_recording(LAB5)
    at = restore_samples(rec, _cal("anchored"))
    stamps = restore_samples(rec, _cal(None))
    assert at.residual_rms_nT < 0.97 * stamps.residual_rms_nT, (
        at.residual_rms_nT, stamps.residual_rms_nT)
    rep = repeated(rec.mag.values)
    ok = at.valid & np.r_[False, at.valid[:-1]]
    np.testing.assert_allclose(at.enu_nT[rep & ok], at.enu_nT[np.flatnonzero(rep & ok) - 1],
                               atol=1e-9)  # nT
    # the output rows keep the message stamps
    np.testing.assert_array_equal(at.t_ns, rec.mag.t_ns)
    t_s = anchored_times_ns(rec.mag.t_ns, ~rep)
    assert np.any(t_s != rec.mag.t_ns)


def test_chunked_restore_times_the_conversions_as_the_whole_recording():
    """Chunk by chunk (each row waits for the messages around it, the positions that
    bracket its sensing time and the attitude its eddy term differences), the rows are the
    whole recording's to 1e-6 nT."""
    cal = _cal("anchored")
    rec, parts, _, chunks = chunked(LAB5, cal, 2_000, positions=True)
    assert len(chunks) > 10
    assert_restores_alike(parts, restore_samples(rec, cal))

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


def test_the_calibration_says_what_its_fit_did_with_the_repeats():
    """The estimate leaves repeated messages out and says so; the final model fits every
    message at its own stamp unless the diagnosis' sample_hold finding handles them. The
    calibration's warning then says which, with the diagnosis' figures (every message), and
    a recording whose messages hold no repeats carries no such warning."""
    from pipeline.model.calibration import Calibration
    from pipeline.model.sample_hold import detect_sample_hold
    from stages.diagnose.stage import _sample_hold_stated

    rng = np.random.default_rng(3)
    t_ns = np.arange(3000, dtype=np.int64) * 3_500_000  # 285.7 Hz messages
    fresh = rng.normal(size=(3000, 3))
    held = fresh[np.floor(np.arange(3000) * 200.0 / 285.7).astype(int)]  # 200 Hz samples
    sh = detect_sample_hold(t_ns, held)
    assert sh is not None
    estimate = ("sample-and-hold: 30 % of the magnetometer messages repeat the previous one "
                "(native rate 199.0 Hz, messages 285.7 Hz); the repeats were left out")
    cal = Calibration(R_body_mag=np.eye(3), sigma_rotvec_deg=np.full(3, 0.1),
                      B_enu_nT=np.array([0.0, 20000.0, -44000.0]), estimator="diagnose",
                      residual_rms_nT=1.0, n_samples=3000, warnings=("other", estimate),
                      sample_hold={"native_rate_hz": 199.0, "repeated_fraction": 0.3})
    kept = _sample_hold_stated(cal, sh, handled=False)
    said = [w for w in kept.warnings if w.startswith("sample-and-hold:")]
    assert len(said) == 1 and "every message was fitted at its own stamp" in said[0]
    assert not said[0].endswith("the repeats were left out")
    assert f"native rate {sh.native_rate_hz:.1f} Hz" in said[0]
    assert kept.sample_hold == sh.params() and kept.warnings[0] == "other"
    handled = _sample_hold_stated(cal, sh, handled=True)
    assert [w for w in handled.warnings if w.startswith("sample-and-hold:")][0].endswith(
        "the repeats were left out")
    none = _sample_hold_stated(cal, None, handled=False)
    assert none.sample_hold is None and none.warnings == ("other",)

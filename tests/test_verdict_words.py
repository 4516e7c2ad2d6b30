"""A verdict a person can act on: one cause in nT and degrees, then what to do.

Every check that writes a doubt or a refusal is exercised here through its own code, and its
words go through :func:`pipeline.core.verdict.plain_words`: a check whose words change
without the verdict's table following turns this red (the cause would fall back to the
check's raw words and lose its advice).
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.verdict import Status, judge, plain_words

INTERNAL = ("hard_iron", "soft_iron", "time_offset", "attitude_source_local", "chi-square",
            "modelled as", "explains all but")


def _plain(text: str) -> tuple[str, str]:
    cause, advice = plain_words(text)
    assert advice is not None, f"no plain words for: {text}"
    for word in INTERNAL:
        assert word not in cause and word not in advice, (word, cause, advice)
    return cause, advice


def test_split_halves_doubt():
    from pipeline.model.calibration import Calibration
    from stages.estimators.checks import SplitCheck, apply_split

    split = SplitCheck(np.zeros(3), np.zeros(3), np.array([0.6, -0.5, 0.3]), 30.0, 60.0)
    cal = Calibration(R_body_mag=np.eye(3), sigma_rotvec_deg=np.full(3, 0.01),
                      B_enu_nT=np.array([0.0, 20000.0, -44000.0]), estimator="test",
                      residual_rms_nT=10.0, n_samples=100)
    cal = apply_split(cal, split, " under the final model")
    (doubt,) = [d for d in cal.checks["doubts"] if d.startswith("the two halves")]
    cause, advice = _plain(doubt)
    assert "0.84 deg apart" in cause and "three axes" in advice  # |(0.6, -0.5, 0.3)|


def test_poorly_determined_axis_and_residual_words():
    from stages.estimate import POOR_AXIS_SIGMA_DEG

    doubt = (f"the rotation about body y is only known to {4 * POOR_AXIS_SIGMA_DEG:.1f} deg: "
             "the motion barely turned the sensor about that axis")
    cause, advice = _plain(doubt)
    assert "+-4.0 deg" in cause and "about body y" in advice
    v = judge(1162.0, 632.0, doubts=[doubt], diagnosed=True)
    assert v.status is Status.QUESTIONABLE
    assert v.reason.startswith("The model leaves 1162 nT, 1.8 times the sensor's noise (632 nT).")
    assert "run magalign diagnose" not in v.reason and "--exclude" in v.reason
    assert "(1 more doubt in the report.)" in v.reason
    assert v.reason.count("QUESTIONABLE") == 0
    v = judge(1162.0, 632.0)
    assert "run magalign diagnose" in v.reason


@pytest.mark.parametrize("text", [
    "the motion cannot determine hard iron or soft iron: the misalignment assumes there is "
    "none; a magnetised or soft-magnetic part near the sensor would bias it (see the "
    "diagnosis)",
    "not estimated (the motion cannot determine them): offset, soft_iron",
    "the motion barely determines the rotation about one axis (only 2.9e-05 of its "
    "information survives the field being unknown): rotate about a second, very different "
    "axis",
    "the model was restricted: the data also ask for field gradient, time offset, which move "
    "the misalignment by 3.95 deg; the sigmas include that shift (run without --estimate for "
    "the model the data select)",
    "the rotation refitted on this recording differs from the calibration's by +0.50 deg "
    "about body x (4905.7 sigmas): the sensor may have moved on its mount since the "
    "calibration; calibrate again",
])
def test_other_checks_in_plain_words(text):
    _plain(text)


def test_ok_and_refused_in_one_sentence_each():
    ok = judge(700.0, 660.0)
    assert ok.status is Status.OK
    assert ok.reason == "The model leaves 700 nT against a sensor noise of 660 nT."
    bad = judge(4000.0, 600.0, diagnosed=True)
    assert bad.status is Status.REFUSED and bad.reason.startswith(
        "The model leaves 4000 nT, 7 times the sensor's noise (600 nT)")
    none = judge(20.0, None)
    assert "record a few seconds without moving" in none.reason


def test_the_report_box_says_the_status_once_and_lists_every_doubt():
    from pipeline.model.calibration import Calibration
    from stages.report import _verdict_html

    doubts = ["the two halves of the recording disagree by 0.85 deg (chi-square 30 for 3 "
              "degrees of freedom): the model leaves out physics; sigmas include it",
              "the motion cannot determine soft iron: the fit leaves it out; the sigmas "
              "include what one of typical size (0.01 soft iron) would do"]
    cal = Calibration(R_body_mag=np.eye(3), sigma_rotvec_deg=np.full(3, 0.3),
                      B_enu_nT=np.array([0.0, 20000.0, -44000.0]), estimator="test",
                      residual_rms_nT=700.0, n_samples=100, checks={"doubts": doubts})
    cal = cal.replace(verdict=judge(700.0, 660.0, doubts=doubts))
    box = _verdict_html(cal)
    assert box.count("QUESTIONABLE") == 1, box
    assert box.count("<li id=doubt>") == 2 and "chi-square" not in box
    assert "(1 more doubt in the report.)" in box


def test_the_report_table_names_poorly_determined_axes():
    from pipeline.model.calibration import Calibration
    from stages.report import _undetermined_axes

    cal = Calibration(R_body_mag=np.eye(3), sigma_rotvec_deg=np.array([3.58, 0.2, 4.45]),
                      B_enu_nT=np.array([0.0, 20000.0, -44000.0]), estimator="test",
                      residual_rms_nT=700.0, n_samples=100)
    text = _undetermined_axes(cal)
    assert text.startswith("none; poorly determined") and "x (\u00b1 3.6\u00b0)" in text
    assert "z (\u00b1 4.5\u00b0)" in text and "y (" not in text


def test_the_verdict_line_quotes_the_figure_the_verdict_judged():
    """The held-out error, when the diagnosis measured one, in the line and in the file."""
    from pipeline.core.verdict import verdict_line
    from pipeline.model.calibration import Calibration

    cal = Calibration(R_body_mag=np.eye(3), sigma_rotvec_deg=np.full(3, 0.01),
                      B_enu_nT=np.array([0.0, 20000.0, -44000.0]), estimator="diagnose",
                      residual_rms_nT=761.0, n_samples=100, time_offset_s=-1e-7)
    held = cal.replace(verdict=judge(761.0, 655.0, heldout_rms_nT=822.0))
    line = verdict_line(held)
    assert "held-out error 822 nT vs noise 655 nT" in line and "761" not in line
    assert "time offset 0.00 ms" in line or "time offset +0.00 ms" in line
    assert "822 nT" in held.verdict.reason
    back = Calibration.from_json(held.to_json())
    assert back.verdict == held.verdict and verdict_line(back) == line
    # not measured (calibrate without the diagnosis): the residual, and the file's verdict
    # holds only the CONVENTIONS keys
    plain = cal.replace(verdict=judge(761.0, 655.0))
    assert "residual 761 nT vs noise 655 nT" in verdict_line(plain)
    assert "heldout_rms_nT" not in plain.verdict.to_dict()


def test_a_lab_residual_below_ten_nT_keeps_its_decimal_everywhere():
    """0.50 nT against 0.42 nT is not "1 nT vs 0 nT": one decimal below 10 nT, line and reason."""
    from pipeline.core.verdict import verdict_line
    from pipeline.model.calibration import Calibration

    cal = Calibration(R_body_mag=np.eye(3), sigma_rotvec_deg=np.full(3, 0.01),
                      B_enu_nT=np.array([0.0, 20000.0, -44000.0]), estimator="diagnose",
                      residual_rms_nT=0.48, n_samples=100)
    held = cal.replace(verdict=judge(0.48, 0.42, heldout_rms_nT=0.50))
    assert "held-out error 0.5 nT vs noise 0.4 nT" in verdict_line(held)
    assert "0.5 nT against a sensor noise of 0.4 nT" in held.verdict.reason
    # whole nanoteslas from 10 nT on, as before
    big = cal.replace(verdict=judge(12.3, 9.96))
    assert "residual 12 nT vs noise 10.0 nT" in verdict_line(big)

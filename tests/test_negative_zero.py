"""No number a person reads is a negative zero ("-0 nT", "-0.00 deg").

Whether a sum of floats ends a hair below or above zero depends on the numerics of the build
(SIMD paths, summation order): a fresh clone printed "held at -0 nT" where the development
machine printed "0". Numbers are formatted by ``pipeline.core.style.num``, and text put
together elsewhere passes ``unsigned_zeros`` on its way out (terminal, result files, report).
"""

from __future__ import annotations

import copy
import json
import re

import corpus
import pytest

from pipeline.app.cli import main
from pipeline.app.simulate import scenario_from_dict, simulate, write_simulated
from pipeline.core.style import num, unsigned_zeros

#: a negative zero as a token: "-0", "-0.0", "-0.000" (hyphen or true minus), not "-0.5"
NEGATIVE_ZERO = re.compile(r"(?<![\w.])[-\u2212]0(\.0+)?(?![\w.])")


@pytest.mark.parametrize(("x", "spec", "want"), [
    (-1e-12, ".2f", "0.00"), (-0.004, ".2f", "0.00"), (-0.004, "+.2f", "+0.00"),
    (-0.0, ".0f", "0"), (-0.4, ".0f", "0"), (-0.03, "8.1f", "     0.0"), (-0.0, "g", "0"),
    (-0.006, ".2f", "-0.01"), (-0.6, ".0f", "-1"), (0.004, "+.2f", "+0.00"),
    (-2.5e-7, ".3g", "-2.5e-07"), (float("-inf"), ".1f", "-inf"), (float("nan"), ".1f", "nan"),
])
def test_num_never_writes_a_negative_zero(x, spec, want):
    assert num(x, spec) == want


@pytest.mark.parametrize(("text", "want"), [
    ("held at -0 nT", "held at 0 nT"),
    ("[-0.00, +1.00, -0.000]", "[0.00, +1.00, 0.000]"),
    ("by \u22120.00 deg", "by 0.00 deg"),
    ("(-0)", "(0)"),
    # not negative zeros: left alone
    ("-0.5 and -0.05 and -10", "-0.5 and -0.05 and -10"),
    ("2026-01-01, lab-0, +-0.03, 1e-0", "2026-01-01, lab-0, +-0.03, 1e-0"),
])
def test_unsigned_zeros(text, want):
    assert unsigned_zeros(text) == want


@pytest.fixture(scope="module")
def aligned(tmp_path_factory):
    """A noise-free recording of a sensor mounted without misalignment: every estimated
    angle is a hair from zero, on one side or the other."""
    root = tmp_path_factory.mktemp("negzero")
    d = copy.deepcopy(corpus.BASE_SCENARIO)
    d["sensor"]["misalignment_rotvec_deg"] = [0.0, 0.0, 0.0]
    d["noise"] = {"mag_sigma_nT": 0.0, "heading_sigma_deg": 0.0, "pitch_roll_sigma_deg": 0.0}
    rec = write_simulated(simulate(scenario_from_dict(d, path="aligned")), root / "aligned.mcap")
    return root, rec


def _run(capsys, *argv: str) -> str:
    status = main(list(argv))
    got = capsys.readouterr()
    assert status == 0, got.err
    return got.out + got.err


def test_no_command_output_shows_a_negative_zero(aligned, capsys):
    root, rec = aligned
    out = root / "cal"
    texts = {"info": _run(capsys, "info", str(rec)),
             "calibrate": _run(capsys, "calibrate", str(rec), "--out", str(out))}
    cal = out / "calibration.json"
    for fmt in ("yaml", "ardupilot", "ros-tf"):  # magcal: nothing estimated to export
        texts[f"export {fmt}"] = _run(capsys, "export", str(cal), "--format", fmt)
    words = json.loads(cal.read_text(encoding="utf-8"))
    texts["calibration.json"] = json.dumps(
        [words["verdict"]["reason"], words["warnings"], words["checks"].get("doubts")])
    for what, text in texts.items():
        bad = [ln for ln in text.splitlines() if NEGATIVE_ZERO.search(ln)]
        assert not bad, f"{what} shows a negative zero: {bad}"

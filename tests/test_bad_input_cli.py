"""The whole ``magalign`` program against a corpus of bad inputs (issue 9, CONVENTIONS).

Every case of :mod:`corpus` is run through the real program (``python -m pipeline.app.cli`` in
a subprocess) with ``info``, ``calibrate``, ``simulate`` or ``process`` as fits, and must get
its intended answer:

- recoverable damage: exit status 0 and a ``magalign: warning:`` line on stderr saying what
  was lost; the calibration still matches the simulated truth;
- anything else: exit status 2 and exactly one line on stderr naming the file, what is wrong
  (and what to do), no traceback (``--debug`` adds one);
- always: the input's sha256 is unchanged, and after a failure no output exists under its
  final name (nor a leftover temporary file).

The corpus is generated once and all runs go through a pool of two subprocesses (the CI
machine has two cores); each test then checks one (case, command) result.
"""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import corpus
import numpy as np
import pytest

from pipeline.model.calibration import Calibration

#: Rotation vector of R_body_mag in the corpus scenario, deg (corpus.BASE_SCENARIO).
TRUE_ROTVEC_DEG = np.array(corpus.BASE_SCENARIO["sensor"]["misalignment_rotvec_deg"])
#: A recovered recording still gives the rotation within this, deg (the intact one: ~0.002).
ROTVEC_TOL_DEG = 0.05
#: Names of final outputs; none of them may appear after a failed run.
FINAL_OUTPUTS = ("calibration.json", "diagnosis.json", "metrics.json", "metrics.parquet",
                 "report.html", ".magalign-done.json")


@dataclass(frozen=True)
class Expect:
    """The intended answer to one run.

    Attributes
    ----------
    ok : bool
        Exit status 0 (recovered) rather than 2 (refused).
    words : tuple of str
        Regular expressions (case-insensitive) the stderr line must contain: the warning
        line when ``ok``, the one error line otherwise.
    xfail : str, optional
        Why the program does not give this answer yet (strict xfail).
    """

    ok: bool
    words: tuple[str, ...] = ()
    xfail: str | None = None


def ok(*words: str, xfail: str | None = None) -> Expect:
    return Expect(True, words, xfail)


def fails(*words: str, xfail: str | None = None) -> Expect:
    return Expect(False, words, xfail)


# (case, command) -> intended answer. Commands: "info" (info --json), "calibrate",
# "calibrate:TOPIC" (with --mag TOPIC), "process" (single recording), "simulate"
# (scenario files), "process-cal" (the valid recording with --calibration FILE),
# "process-truthcal" (the case's recording with --calibration of the simulated truth: a
# survey line restored with a calibration run's result).
ANSWERS: dict[tuple[str, str], Expect] = {
    ("valid", "info"): ok(),
    ("valid", "calibrate"): ok(),
    ("valid", "process"): ok(),
    ("empty", "info"): fails(r"empty file"),
    ("empty", "calibrate"): fails(r"empty file"),
    ("text_file", "info"): fails(r"not an MCAP file"),
    ("text_file", "calibrate"): fails(r"not an MCAP file"),
    ("png_file", "calibrate"): fails(r"not an MCAP file"),
    ("cut_in_header", "info"): fails(r"cut inside the MCAP header"),
    ("cut_in_header", "calibrate"): fails(r"cut inside the MCAP header"),
    ("cut_in_chunk", "info"): ok(r"cut inside a chunk", r"lost"),
    ("cut_in_chunk", "calibrate"): ok(r"cut inside a chunk", r"lost"),
    ("cut_in_chunk", "process"): ok(r"cut inside a chunk", r"lost"),
    ("cut_before_footer", "info"): ok(r"before its footer", r"summary was lost"),
    ("cut_before_footer", "calibrate"): ok(r"before its footer", r"summary was lost"),
    ("cut_at_data_end", "calibrate"): ok(r"cut at byte \d+", r"no footer"),
    ("bad_crc", "info"): ok(r"CRC", r"\d+ messages were skipped"),
    ("bad_crc", "calibrate"): ok(r"CRC", r"\d+ messages were skipped"),
    ("undecompressable", "calibrate"): ok(r"does not decompress", r"\d+ messages were skipped"),
    ("missing_mag", "calibrate"): fails(r"no magnetometer channel", r"/attitude"),
    ("missing_attitude", "calibrate"): fails(r"no attitude", r"/mag"),
    ("two_mags", "calibrate"): fails(r"two or more candidate magnetometer", r"--mag"),
    ("two_mags", "calibrate:/mag_b"): ok(),
    ("unknown_schema", "calibrate"): fails(r"no magnetometer channel", corpus.UNKNOWN_TYPE),
    ("unknown_schema", "calibrate:/mag"): fails(corpus.UNKNOWN_TYPE, r"not a supported"),
    ("nan_inf", "info"): ok(r"NaN"),
    ("nan_inf", "calibrate"): ok(r"10 samples with NaN or Inf", r"dropped"),
    ("nan_inf", "process"): ok(r"10 samples with NaN or Inf", r"dropped"),
    ("bad_quaternions", "calibrate"): ok(r"3 zero quaternions were dropped"),
    ("stamps_backwards", "info"): ok(r"6 stamps going backwards"),
    ("stamps_backwards", "calibrate"): ok(r"6 stamps going backwards", r"sorted"),
    ("stamps_duplicated", "info"): ok(r"6 duplicated stamps"),
    ("stamps_duplicated", "calibrate"): ok(r"6 samples with a duplicated stamp", r"dropped"),
    ("stamps_jump_hours", "info"): ok(r"gaps? longer"),
    ("stamps_jump_hours", "calibrate"): ok(r"4 samples with stamps more than an hour",
                                           r"dropped"),
    ("long_gap", "info"): ok(r"gaps? longer than"),
    ("long_gap", "calibrate"): ok(r"gaps? longer than"),
    ("microtesla_as_tesla", "calibrate"): fails(r"far outside the Earth", r"tesla"),
    ("stuck", "calibrate"): fails(r"stuck"),
    ("stuck", "process"): fails(r"stuck"),
    ("saturated", "calibrate"): fails(r"saturated"),
    ("partly_saturated", "calibrate"): ok(r"\d+ samples pinned", r"saturated", r"dropped"),
    ("static", "calibrate"): fails(r"did not rotate|not observable", r"rotat"),
    ("static", "process"): fails(r"did not rotate|not observable", r"rotat"),
    ("static", "process-truthcal"): ok(),
    ("too_short", "calibrate"): fails(r"only 5 usable", r"too short"),
    ("scenario_bad_key", "simulate"): fails(r"line 7", r"timing\.mag_rate'", r"unknown key"),
    ("scenario_bad_value", "simulate"): fails(r"line 6", r"timing\.duration_s",
                                              r"must be a number"),
    ("scenario_not_toml", "simulate"): fails(r"line 1", r"not valid TOML"),
    ("calibration_other_format", "process-cal"): fails(r"magalign\.calibration/1",
                                                       r"acme\.magcal/2"),
    ("calibration_not_json", "process-cal"): fails(r"not valid JSON"),
}
#: Failing runs repeated with --debug: they must show a traceback (and still exit 2).
DEBUG_RUNS = (("empty", "calibrate"), ("stuck", "calibrate"), ("scenario_bad_key", "simulate"))


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _argv(cmd: str, inp: Path, out: Path, valid: Path, truth_cal: Path) -> list[str]:
    name, _, topic = cmd.partition(":")
    if name == "info":
        return ["info", "--json", str(inp)]
    if name == "calibrate":
        return ["calibrate", str(inp), "--out", str(out)] + (["--mag", topic] if topic else [])
    if name == "process":
        return ["process", str(inp), "--out", str(out), "--no-progress"]
    if name == "process-cal":
        return ["process", str(valid), "--out", str(out), "--calibration", str(inp),
                "--no-progress"]
    if name == "process-truthcal":
        return ["process", str(inp), "--out", str(out), "--calibration", str(truth_cal),
                "--no-progress"]
    if name == "simulate":
        return ["simulate", str(inp), "--out", str(out / "sim.mcap")]
    raise AssertionError(cmd)


def magalign(argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """Run the real program."""
    return subprocess.run([sys.executable, "-m", "pipeline.app.cli", *argv], cwd=cwd,
                          capture_output=True, text=True, timeout=600)


@dataclass
class Run:
    """One run of the program on one corpus input."""

    input: Path
    out: Path
    result: subprocess.CompletedProcess
    sha_before: str
    debug: subprocess.CompletedProcess | None = None


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[tuple[str, str], Run]:
    """Generate the corpus, run every (case, command) of ANSWERS, two at a time."""
    root = tmp_path_factory.mktemp("corpus")
    valid = corpus.valid(root)
    truth = corpus.base_sim().truth
    truth_cal = root / "truth_calibration.json"
    truth_cal.write_text(Calibration(
        R_body_mag=truth.R_body_mag, sigma_rotvec_deg=np.zeros(3), B_enu_nT=truth.B_enu_nT,
        estimator="truth", residual_rms_nT=0.0, n_samples=0).to_json())
    inputs = {"valid": valid}
    for name, gen in corpus.CASES.items():
        (root / name).mkdir()
        inputs[name] = gen(root / name)
    before = {name: sha256(p) for name, p in inputs.items()}
    jobs = {}
    for k, (case, cmd) in enumerate(ANSWERS):
        out = root / "out" / f"{k:02d}_{case}_{cmd.replace(':', '_').replace('/', '')}"
        out.mkdir(parents=True)
        jobs[(case, cmd)] = (inputs[case], out, _argv(cmd, inputs[case], out, valid, truth_cal))
    with ThreadPoolExecutor(max_workers=2) as pool:
        futs = {key: pool.submit(magalign, argv, out) for key, (_, out, argv) in jobs.items()}
        dbg = {key: pool.submit(magalign, ["--debug", *jobs[key][2]], jobs[key][1].parent)
               for key in DEBUG_RUNS}
        res = {key: Run(jobs[key][0], jobs[key][1], f.result(), before[key[0]])
               for key, f in futs.items()}
        for key, f in dbg.items():
            res[key].debug = f.result()
    # The valid recording was read by every process-cal run; it must be unchanged too.
    assert sha256(valid) == before["valid"]
    return res


def _check_calibration(out: Path) -> None:
    """A calibration.json that parses and gives the simulated rotation."""
    cals = list(out.rglob("calibration.json"))
    assert cals, f"no calibration.json under {out}"
    cal = Calibration.from_json(cals[0].read_text(), path=str(cals[0]))
    err = np.abs(np.asarray(cal.rotvec_body_mag_deg) - TRUE_ROTVEC_DEG).max()
    assert err < ROTVEC_TOL_DEG, f"rotation off by {err:.4f} deg"


def _params():
    for (case, cmd), exp in ANSWERS.items():
        marks = [pytest.mark.xfail(strict=True, reason=exp.xfail)] if exp.xfail else []
        yield pytest.param(case, cmd, exp, id=f"{case}-{cmd}", marks=marks)


@pytest.mark.parametrize(("case", "cmd", "exp"), list(_params()))
def test_intended_answer(runs, case: str, cmd: str, exp: Expect):
    run = runs[(case, cmd)]
    r = run.result
    assert sha256(run.input) == run.sha_before, "the input file was modified"
    assert "Traceback" not in r.stderr, r.stderr
    assert not list(run.out.rglob("*.tmp")), "a temporary file was left behind"
    if exp.ok:
        assert r.returncode == 0, r.stderr
        warn = [ln for ln in r.stderr.splitlines() if re.search(r"warning", ln, re.I)]
        # one line per warning, each once, also from process's worker processes
        for ln in r.stderr.splitlines():
            assert ln.startswith("magalign: warning: "), f"not a warning line: {ln!r}"
        assert len(set(warn)) == len(warn), f"a warning was issued twice: {r.stderr}"
        if exp.words:
            # info also reports what it found in its JSON "problems"
            text = "\n".join(warn)
            if cmd == "info":
                text += "\n".join(p["message"] for p in json.loads(r.stdout)["problems"])
            for w in exp.words:
                assert re.search(w, text, re.I), f"{w!r} not in {text!r} (stderr {r.stderr!r})"
        elif cmd != "info":
            assert not warn, f"unexpected warning on an intact input: {r.stderr}"
        if cmd.startswith(("calibrate", "process")):
            _check_calibration(run.out)
        if cmd == "info":
            roles = {c["role"] for c in json.loads(r.stdout)["channels"]}
            assert {"magnetometer", "attitude"} <= roles
    else:
        assert r.returncode == 2, f"exit {r.returncode}: {r.stderr}"
        lines = r.stderr.splitlines()
        assert len(lines) == 1, f"expected one line on stderr, got {lines}"
        line = lines[0]
        assert line.startswith("magalign: ")
        assert str(run.input) in line, f"the file is not named: {line}"
        for w in exp.words:
            assert re.search(w, line, re.I), f"{w!r} not in {line!r}"
        for name in FINAL_OUTPUTS:
            assert not list(run.out.rglob(name)), f"{name} written by a failed run"
        assert not list(run.out.rglob("*.corrected.mcap"))
        assert not list(run.out.rglob("*.rrd"))
        assert not (run.out / "sim.mcap").exists()
    if run.debug is not None:
        d = run.debug
        assert d.returncode == 2 and "Traceback (most recent call last)" in d.stderr
        assert d.stderr.rstrip().splitlines()[-1] == r.stderr.rstrip()


def test_configuration_is_never_executed(runs):
    """A scenario that is Python code is refused as TOML; nothing of it runs."""
    r = runs[("scenario_not_toml", "simulate")].result
    assert "owned" not in r.stdout + r.stderr


def test_every_corpus_case_has_an_answer():
    assert set(corpus.CASES) <= {case for case, _ in ANSWERS}

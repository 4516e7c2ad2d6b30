"""Every command with every kind of file in each of its file arguments: no traceback.

Each file argument of each command (``magalign --help`` lists them) is given, in turn, a
recording, a calibration.json, a results folder, a CSV file, an empty file, an empty
directory and a path that does not exist. Every answer must be exit status 0 (warnings
allowed, one line each) or exit status 2 with exactly one line on stderr that names the
file; never a traceback, and after a failure no output folder.

The inputs are small (the test recording of ``tests/data``, processed once), so the whole
module runs in well under a minute. The shared lab recordings add a few cases that need
no fit (a real recording where a calibration, a scenario or a folder is wanted); they are
skipped, saying why, when ``../shared`` is absent.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import fuzz_mcap as fz
import pytest

DATA = Path(__file__).parent / "data"
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"

KINDS = ("recording", "calibration", "folder", "csv", "empty", "directory", "missing")

#: command -> argv templates; ``{X}`` is the fuzzed file argument, ``{out}`` a fresh output
#: path, ``{rec}`` / ``{cal}`` / ``{folder}`` the valid inputs for the other arguments.
SLOTS: dict[str, list[str]] = {
    "info": ["info", "--json", "{X}"],
    "info-text": ["info", "{X}"],
    "export": ["export", "{X}", "--format", "yaml"],
    "export-ardupilot": ["export", "{X}", "--format", "ardupilot"],
    "simulate": ["simulate", "{X}", "--out", "{out}/sim.mcap"],
    "calibrate": ["calibrate", "{X}", "--out", "{out}"],
    "diagnose": ["diagnose", "{X}", "--out", "{out}"],
    "process": ["process", "{X}", "--out", "{out}", "--no-progress"],
    "process-calibration": ["process", "{rec}", "--calibration", "{X}", "--out", "{out}",
                            "--no-progress"],
    "regress-results": ["regress", "{X}", "--baseline", "{folder}"],
    "regress-baseline": ["regress", "{folder}", "--baseline", "{X}"],
    "regress-tolerances": ["regress", "{folder}", "--baseline", "{folder}", "--tolerances",
                           "{X}"],
    "score-challenge": ["score", "{X}", "{folder}"],
    "score-results": ["score", "{folder}", "{X}", "--key", "{key}"],
    "score-key": ["score", "{folder}", "{folder}", "--key", "{X}"],
    "view": ["view", "{X}"],
}
#: The runs that fit a model on the test recording (the slow ones) happen once, in the
#: fixture; these slots reuse its output folder for the valid recording.
REUSE_FOLDER = {"process"}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("cli_fuzz")
    rec = root / "rotation.mcap"
    shutil.copyfile(DATA / "rotation.mcap", rec)
    folder = root / "results"
    status, _, err = fz.run_cli(["process", str(rec), "--out", str(folder), "--no-progress"],
                                timeout_s=120)
    assert status == 0, err
    csv = root / "table.csv"
    csv.write_text("t_s,x_nT,y_nT,z_nT\n0.0,1.0,2.0,3.0\n", encoding="utf-8")
    empty = root / "empty.mcap"
    empty.write_bytes(b"")
    key = root / "key.json"  # a challenge's key naming the test recording, nothing in it
    key.write_text(json.dumps({"recordings": {"rotation": {
        "effects": [], "strength_x_threshold": {}, "params": {}}}}), encoding="utf-8")
    directory = root / "nothing_here"
    directory.mkdir()
    return {"recording": rec, "calibration": folder / "rotation" / "calibration.json",
            "folder": folder, "csv": csv, "empty": empty, "directory": directory,
            "missing": root / "missing.mcap", "key": key}


def _check(argv: list[str], status, err: str, named: Path, out: Path | None) -> None:
    what = "magalign " + " ".join(argv)
    assert status in (0, 2), f"{what}: status {status}\n{err}"
    assert "Traceback" not in err, f"{what}\n{err}"
    lines = err.splitlines()
    if status == 0:
        bad = [ln for ln in lines if not ln.startswith("magalign: warning: ")]
        assert not bad, f"{what}: not a warning line: {bad}"
        return
    assert len(lines) == 1, f"{what}: expected one line on stderr, got {lines}"
    assert lines[0].startswith("magalign: "), lines[0]
    assert named.name in lines[0], f"{what}: the line does not name {named.name}: {lines[0]}"
    if out is not None:
        assert not out.exists(), f"{what}: failed but left {out}"


def _run(argv: list[str], tmp_path: Path, named: Path, monkeypatch) -> tuple:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setenv("MAGALIGN_PROGRESS", "never")
    out = tmp_path / "out" if any("{out}" in a for a in argv) else None
    status, stdout, err = fz.run_cli(argv, timeout_s=60)
    _check(argv, status, err, named, out)
    return status, stdout


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("slot", sorted(SLOTS))
def test_every_file_argument_takes_every_kind_of_file(inputs, tmp_path, monkeypatch, slot,
                                                      kind):
    if kind == "recording" and slot in ("calibrate", "diagnose", "process-calibration"):
        # a full fit on the valid recording: checked by tests of their own (test_cli,
        # test_outputs); here the wrong kinds of file are what counts
        pytest.skip("the fit itself is tested elsewhere")
    x = inputs[kind]
    fill = {"X": str(x), "rec": str(inputs["recording"]), "cal": str(inputs["calibration"]),
            "folder": str(inputs["folder"]), "key": str(inputs["key"]),
            "out": str(tmp_path / "out")}
    if slot in REUSE_FOLDER and kind == "recording":
        fill["out"] = str(inputs["folder"])  # the fixture's run: reused, not redone
    argv = [a.format(**fill) for a in SLOTS[slot]]
    before = fz.sha256(x) if x.is_file() else None
    status, _ = _run(argv, tmp_path, x, monkeypatch)
    if before is not None:
        assert fz.sha256(x) == before, f"{slot} changed its input {x.name}"


REAL_SLOTS = ("info", "export", "simulate", "process-calibration", "regress-results",
              "regress-baseline", "regress-tolerances", "score-challenge", "score-key",
              "view")


@pytest.mark.real
@pytest.mark.parametrize("slot", REAL_SLOTS)
def test_a_real_recording_in_every_fast_file_argument(inputs, tmp_path, monkeypatch, slot):
    if not (REAL / "lab_03.mcap").is_file():
        pytest.skip(f"the shared lab recordings are not here ({REAL})")
    x = REAL / "lab_03.mcap"
    fill = {"X": str(x), "rec": str(inputs["recording"]), "cal": str(inputs["calibration"]),
            "folder": str(inputs["folder"]), "key": str(inputs["key"]),
            "out": str(tmp_path / "out")}
    argv = [a.format(**fill) for a in SLOTS[slot]]
    _run(argv, tmp_path, x, monkeypatch)


@pytest.mark.real
def test_a_recording_as_the_calibration_of_a_real_recording(tmp_path, monkeypatch):
    """The surveyor's case: ``process lab_03.mcap --calibration lab_02.mcap``."""
    if not (REAL / "lab_02.mcap").is_file():
        pytest.skip(f"the shared lab recordings are not here ({REAL})")
    argv = ["process", str(REAL / "lab_03.mcap"), "--calibration", str(REAL / "lab_02.mcap"),
            "--out", str(tmp_path / "out"), "--no-progress"]
    status, _ = _run(argv, tmp_path, REAL / "lab_02.mcap", monkeypatch)
    assert status == 2


#: commands whose --out is a folder, given an existing file there: refused before any work
OUT_FOLDER_SLOTS = {
    "calibrate": ["calibrate", "{rec}", "--out", "{X}"],
    "diagnose": ["diagnose", "{rec}", "--out", "{X}"],
    "process": ["process", "{rec}", "--out", "{X}", "--no-progress"],
    "reproduce": ["reproduce", "li2020", "--out", "{X}"],
}


@pytest.mark.parametrize("kind", ["recording", "calibration", "csv", "empty"])
@pytest.mark.parametrize("slot", sorted(OUT_FOLDER_SLOTS))
def test_an_output_folder_that_is_a_file_is_refused(inputs, tmp_path, monkeypatch, slot,
                                                    kind):
    x = inputs[kind]
    rec = tmp_path / "input.mcap"
    shutil.copyfile(inputs["recording"], rec)
    argv = [a.format(X=str(x), rec=str(rec)) for a in OUT_FOLDER_SLOTS[slot]]
    before = fz.sha256(x)
    status, _ = _run(argv, tmp_path, x, monkeypatch)
    assert status == 2
    assert fz.sha256(x) == before


@pytest.mark.parametrize("kind", ["folder", "directory", "recording-in-a-file"])
def test_simulate_output_that_cannot_be_a_file_is_refused(inputs, tmp_path, monkeypatch, kind):
    scenario = Path(__file__).resolve().parents[1] / "pipeline" / "scenarios" / \
        "li2020_section41.toml"
    if kind == "recording-in-a-file":
        x, named = inputs["empty"] / "rec.mcap", inputs["empty"]
    else:
        x = named = inputs[kind]
    status, _ = _run(["simulate", str(scenario), "--out", str(x)], tmp_path, named,
                     monkeypatch)
    assert status == 2

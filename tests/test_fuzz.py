"""Damaged recordings never crash a command (issue 16): seeded mutation fuzzing.

Small valid recordings, one per reader path (``fuzz_mcap.BASES``), are damaged by seeded
mutations (bit flips, zeroed runs, cuts, splices, random record lengths, and mixes of them).
Every reader entry point and every command that reads a recording (``info``,
``calibrate``, ``diagnose``, ``process`` and ``view``'s loader) is run on each damaged file.
Every answer must be exit status 0 (warnings allowed, one line each) or exit status 2 with
exactly one line on stderr naming the file; never a traceback, never longer than 30 s, never
a changed input, never a partial output under a final name.

``make test`` runs 60 damaged files (``process`` on every second one). The slow mode runs
more: ``MAGALIGN_FUZZ_N=500 pytest tests/test_fuzz.py`` (``MAGALIGN_FUZZ_SEED`` picks another
set of damaged files). A failure names the file, whose name gives the base recording, the
mutation and its seed (``fuzz_mcap.case_name``, ``fuzz_mcap.damage``).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import warnings
from collections import Counter
from pathlib import Path

import fuzz_mcap as fz
import pytest

from pipeline.core.errors import MagalignError

N_FILES = int(os.environ.get("MAGALIGN_FUZZ_N", "60"))
SEED = int(os.environ.get("MAGALIGN_FUZZ_SEED", "16"))
#: ``process`` (the slowest command) runs on every PROCESS_EVERY-th damaged file
PROCESS_EVERY = 2
#: damaged files run again through the real program in a subprocess (hang guard, real pool)
N_SUBPROCESS = 4
HANG_S = 30.0
TEMP_NAME = re.compile(r"\..+\.tmp")


@pytest.fixture(scope="module")
def damaged(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("fuzz")
    (root / "base").mkdir()
    bases = {k: f(root / "base") for k, f in fz.BASES.items()}
    return fz.make_cases(bases, root / "damaged", N_FILES, SEED)


@pytest.fixture(scope="module")
def outcomes() -> Counter:
    """Outcomes by command, printed at the end of the module (the slow run's report)."""
    c: Counter = Counter()
    yield c
    print("\nfuzz outcomes (command, exit status): " + ", ".join(
        f"{k[0]} {k[1]}: {v}" for k, v in sorted(c.items(), key=str)), file=sys.stderr)


def test_bases_are_valid_and_cover_the_reader_paths(tmp_path):
    from pipeline.io.mcap_read import read_recording
    from pipeline.io.mcap_scan import index_chunks, scan_file

    layouts = {}
    for name, make in fz.BASES.items():
        p = make(tmp_path)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            rec = read_recording(p)
        assert len(rec.mag) >= 400 and rec.attitude is not None, name
        scan = scan_file(p)
        indexed = [c.index_trusted for c in scan.chunks]
        index_chunks(scan)
        layouts[name] = (len(scan.chunks), bool(scan.top_messages), all(indexed))
    assert layouts["indexed"][0] > 5 and layouts["indexed"][2]
    assert layouts["unindexed_lz4"][0] > 5 and not any(layouts["unindexed_lz4"][1:])
    assert layouts["unchunked"] == (0, True, True)
    assert layouts["json"][0] > 5
    assert layouts["simulated"][0] == 1


def test_mutations_are_reproducible_and_damage(tmp_path):
    data = fz.BASES["indexed"](tmp_path).read_bytes()
    for k, mut in enumerate(sorted(fz.MUTATIONS)):
        a, b = fz.damage(data, mut, k), fz.damage(data, mut, k)
        assert a == b and a != data, mut
    assert len(fz.MUTATIONS) >= 6


def _check_answer(status, err: str, path: Path, what: str) -> None:
    assert status in (0, 2), f"{what}: {path.name}: status {status}\n{err}"
    assert "Traceback" not in err and "internal error" not in err, f"{what}: {path.name}\n{err}"
    lines = err.splitlines()
    if status == 0:
        bad = [ln for ln in lines if not ln.startswith("magalign: warning: ")]
        assert not bad, f"{what}: {path.name}: not a warning line: {bad}"
    else:
        assert len(lines) == 1, f"{what}: {path.name}: expected one line, got {lines}"
        assert lines[0].startswith("magalign: ") and path.name in lines[0], lines[0]


def _check_outputs(out: Path, status: int, finals: tuple[str, ...]) -> None:
    """Only complete outputs under final names; none at all after a failure."""
    if not out.exists():
        assert status != 0 or not finals, f"{out}: nothing written"
        return
    files = [f for f in out.rglob("*") if f.is_file()]
    assert not [f for f in files if TEMP_NAME.fullmatch(f.name)], f"temporary left in {out}"
    names = {f.name for f in files}
    if status != 0:
        assert not names & {"calibration.json", "diagnosis.json", "metrics.json"}, names
        assert not [n for n in names if n.endswith((".corrected.mcap", ".rrd"))], names
        return
    for name in finals:
        assert name in names, f"{name} missing from {out}"
    for f in files:
        if f.name == "calibration.json":
            from pipeline.model.calibration import Calibration

            Calibration.load(f)
        elif f.suffix == ".json":
            json.loads(f.read_text())


def test_reader_entry_points(damaged):
    """Every reader function answers a damaged file or raises a MagalignError."""
    from pipeline.io import mcap_read as mr

    readers = {
        "read_recording": mr.read_recording,
        "inspect_recording": mr.inspect_recording,
        "read_raw_channels": mr.read_raw_channels,
        "iter_raw_channels": lambda p: list(mr.iter_raw_channels(p, max_messages=100)),
        "iter_recording_chunks": lambda p: list(mr.iter_recording_chunks(p, max_messages=100)),
    }
    answered = Counter()
    for p in damaged:
        before = fz.sha256(p)
        for name, read in readers.items():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    read(p)
                    answered[name] += 1
                except MagalignError as exc:
                    assert exc.path is not None, f"{name}: {p.name}: {exc} names no file"
        assert fz.sha256(p) == before, p.name
    # most damaged files still give their data (the damage is local)
    assert answered["read_raw_channels"] > len(damaged) // 2, answered


@pytest.mark.parametrize("command", ["info", "calibrate", "diagnose", "process"])
def test_command_answers_every_damaged_file(damaged, outcomes, tmp_path, command):
    finals = {"info": (), "calibrate": ("calibration.json",),
              "diagnose": ("calibration.json", "diagnosis.json"),
              "process": ("calibration.json", "metrics.json", ".magalign-done.json")}[command]
    files = damaged[::PROCESS_EVERY] if command == "process" else damaged
    for p in files:
        out = tmp_path / p.stem
        argv = [command, str(p)]
        argv += ["--json"] if command == "info" else ["--out", str(out)]
        if command == "process":
            argv.append("--no-progress")
        before = fz.sha256(p)
        status, stdout, err = fz.run_cli(argv, timeout_s=HANG_S)
        outcomes[(command, status)] += 1
        _check_answer(status, err, p, command)
        assert fz.sha256(p) == before, f"{command} changed its input {p.name}"
        _check_outputs(out, status, finals)
        if command == "info" and status == 0:
            info = json.loads(stdout)
            assert {"channels", "duration_s", "problems"} <= set(info)


def test_view_loader_answers_every_damaged_file(damaged, outcomes):
    from pipeline.app.commands.view import files_to_view

    for p in damaged:
        try:
            got = files_to_view(p)
        except MagalignError as exc:
            assert exc.exit_code == 2 and exc.path == str(p)
            outcomes[("view", 2)] += 1
        else:
            assert got == [p]
            outcomes[("view", 0)] += 1


def test_real_program_on_damaged_files(damaged, tmp_path):
    """A few damaged files through the installed program (worker pool, own process)."""
    picked = damaged[:: max(1, len(damaged) // N_SUBPROCESS)][:N_SUBPROCESS]
    for k, p in enumerate(picked):
        cmd = "process" if k % 2 else "calibrate"
        out = tmp_path / p.stem
        argv = [cmd, str(p), "--out", str(out)] + (["--no-progress"] if k % 2 else [])
        try:
            r = subprocess.run([sys.executable, "-m", "pipeline.app.cli", *argv],
                               capture_output=True, text=True, timeout=HANG_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"{cmd} {p.name} ran longer than {HANG_S} s")
        _check_answer(r.returncode, r.stderr, p, cmd)


def test_damaged_campaign_toml_is_refused_or_read(tmp_path):
    """A damaged campaign file is read or refused with a ConfigError naming it; never a crash."""
    import shutil

    from pipeline.app.campaign import load_campaign
    from pipeline.core.errors import ConfigError, InputError, UsageError

    data = Path(__file__).resolve().parent / "data"
    for f in data.glob("*.mcap"):
        shutil.copy(f, tmp_path / f.name)  # the campaign's relative paths resolve
    src = (data / "campaign.toml").read_bytes()
    read = refused = 0
    for i in range(max(200, N_FILES * 3)):
        p = tmp_path / "campaign.toml"
        p.write_bytes(fz.damage(src, sorted(fz.MUTATIONS)[i % len(fz.MUTATIONS)], SEED + i))
        try:
            load_campaign(p)
            read += 1
        except (ConfigError, InputError, UsageError) as exc:
            assert exc.path == str(p), exc.one_line()
            refused += 1
    assert read and refused

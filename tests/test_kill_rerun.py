"""Kill ``magalign`` with SIGKILL in the middle of its work; nothing partial may pass for finished.

Issue 9, "Nothing lost": every output is written to a temporary name and renamed when
complete, so after a run killed at any point each file under a final name is complete
(``calibration.json`` parses and is a whole calibration, a corrected ``.mcap`` opens with
mcap's own reader and passes its CRC checks, ...); the only other files allowed are
leftover temporaries named ``.*.tmp``. A rerun then completes.

Issue 16: the kill points are chosen by the test, not by the clock, so the test holds on a
slow or loaded machine. A reference run lists the events of every atomic write
(``created``, ``written``, ``renamed`` of each output: the test hook of
``pipeline.core.atomic``); each iteration pauses a run at one of them (seeded choice), kills it
there and checks what is left. A few more runs are killed at seeded random moments, which
reach other points (reading, estimating); whether those ended before the kill does not
matter to the test.

The program is started in its own session and the whole process group is killed (as a
crash or power loss would), so worker processes of ``process`` die with it.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import corpus
import numpy as np
import pyarrow.parquet as pq
import pytest
from _pause import wait_paused
from mcap.reader import make_reader

from pipeline.model.calibration import Calibration

N_ITERATIONS = 20
N_RANDOM = 3
SEED = 9_2026
TEMP_NAME = re.compile(r"\..+\.tmp")


def _start(argv: list[str], cwd: Path, env: dict[str, str] | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "pipeline.app.cli", *argv], cwd=cwd,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, env={**os.environ, **(env or {})})


def run_to_end(argv: list[str], cwd: Path, env: dict[str, str] | None = None
               ) -> tuple[int, str, float]:
    """Run the program to its end: exit status, stderr, wall time (s)."""
    t0 = time.monotonic()
    p = _start(argv, cwd, env)
    _, err = p.communicate(timeout=600)
    return p.returncode, err, time.monotonic() - t0


def run_and_kill(argv: list[str], cwd: Path, after_s: float) -> bool:
    """Start the program, SIGKILL its process group after ``after_s``; True if it was killed."""
    p = _start(argv, cwd)
    try:
        p.communicate(timeout=after_s)
        return False
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.communicate()
        return True


def run_and_kill_at(argv: list[str], cwd: Path, hook: Path, at: int) -> str:
    """Start the program paused at atomic-write event number ``at``; SIGKILL it there.

    Returns the event it was killed at (``pipeline.core.atomic``'s hook).
    """
    from pipeline.core.atomic import PAUSE_AT_ENV, PAUSE_DIR_ENV

    hook.mkdir()
    p = _start(argv, cwd, {PAUSE_DIR_ENV: str(hook), PAUSE_AT_ENV: str(at)})
    try:
        return wait_paused(p, hook)
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.communicate()


def _check_mcap(path: Path) -> None:
    with open(path, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None, path
        n = sum(1 for _ in reader.iter_messages())
    assert n == summary.statistics.message_count > 0, path


def check_no_partial_output(out: Path) -> dict[str, int]:
    """Every file under ``out`` is complete or a ``.*.tmp`` temporary; counts by kind."""
    seen = {"tmp": 0, "final": 0}
    for f in sorted(out.rglob("*")):
        if not f.is_file():
            continue
        name = f.name
        if TEMP_NAME.fullmatch(name):
            seen["tmp"] += 1
            continue
        seen["final"] += 1
        if name == "calibration.json":
            cal = Calibration.from_json(f.read_text(), path=str(f))
            assert cal.R_body_mag.shape == (3, 3) and cal.n_samples > 0, f
        elif name.endswith(".json"):
            json.loads(f.read_text())
        elif name.endswith(".mcap"):
            _check_mcap(f)
        elif name.endswith(".parquet"):
            pq.read_table(f)
        elif name.endswith(".html"):
            assert f.read_text().rstrip().endswith("</html>"), f
        elif name.endswith(".png"):
            assert f.read_bytes()[-8:-4] == b"IEND", f
        elif name.endswith(".rrd"):
            assert f.read_bytes()[:4] == b"RRF2", f
        else:
            raise AssertionError(f"unexpected file {f}")
    return seen


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return corpus.valid(tmp_path_factory.mktemp("kill"))


def _rerun_and_check(argv: list[str], out: Path, cwd: Path, finished, what: str) -> None:
    if out.exists():
        check_no_partial_output(out)
    status, err, _ = run_to_end(argv, cwd)
    assert status == 0, f"{what}: rerun failed: {err}"
    seen = check_no_partial_output(out)
    assert seen["final"] > 0
    finished(out)


def _event(line: str) -> tuple[str, str]:
    """``(kind, file name)`` of an event line ``kind folder/name``."""
    kind, name = line.split(" ", 1)
    return kind, name.rsplit("/", 1)[-1]


def _loop(tmp_path: Path, recording: Path, argv_for, finished) -> None:
    from pipeline.core.atomic import PAUSE_DIR_ENV

    rng = np.random.default_rng(SEED)
    ref_hook = tmp_path / "reference_events"
    ref_hook.mkdir()
    status, err, wall = run_to_end(argv_for(tmp_path / "reference"), tmp_path,
                                   {PAUSE_DIR_ENV: str(ref_hook)})
    assert status == 0, err
    events = (ref_hook / "events").read_text().splitlines()
    assert events and all(e.split()[0] in ("created", "written", "renamed") for e in events)
    # every event when there are few, else a seeded choice (always the first and the last)
    n = len(events)
    picks = list(range(1, n + 1)) if n <= N_ITERATIONS else sorted(
        {1, n, *(int(k) + 1 for k in rng.choice(n, N_ITERATIONS - 2, replace=False))})
    for i, at in enumerate(picks):
        out = tmp_path / f"run{i:02d}"
        got = run_and_kill_at(argv_for(out), tmp_path, tmp_path / f"hook{i:02d}", at)
        # the same event as in the reference run (the output folder's name differs)
        assert _event(got.split(" ", 1)[1]) == _event(events[at - 1]), (got, events[at - 1])
        assert out.exists()
        if events[at - 1].startswith(("written", "renamed")):
            # the output of that event is complete (renamed or about to be)
            assert any(out.rglob("*")), f"nothing written at {got}"
        _rerun_and_check(argv_for(out), out, tmp_path, finished, f"killed at {got}")
    # kills at seeded random moments reach what lies between the writes
    for i in range(N_RANDOM):
        out = tmp_path / f"random{i:02d}"
        run_and_kill(argv_for(out), tmp_path, float(rng.uniform(0.0, 1.1 * wall)))
        _rerun_and_check(argv_for(out), out, tmp_path, finished, f"random kill {i}")


def test_kill_and_rerun_calibrate(tmp_path, recording):
    def argv_for(out: Path) -> list[str]:
        return ["calibrate", str(recording), "--out", str(out)]

    def finished(out: Path) -> None:
        assert (out / "calibration.json").is_file()

    _loop(tmp_path, recording, argv_for, finished)


@pytest.mark.slow
def test_kill_and_rerun_process(tmp_path, recording):
    stem = recording.stem

    def argv_for(out: Path) -> list[str]:
        return ["process", str(recording), "--out", str(out), "--no-progress"]

    def finished(out: Path) -> None:
        folder = out / stem
        for name in ("calibration.json", "metrics.json", f"{stem}.corrected.mcap",
                     ".magalign-done.json", "report.html"):
            assert (folder / name).is_file(), name
        assert (out / "summary.parquet").is_file()

    _loop(tmp_path, recording, argv_for, finished)

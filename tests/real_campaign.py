"""The shared real recordings processed once per run of the suite, for every test reading them.

``process`` of make_golden's campaign of the real recordings (each calibrated on its own,
with its diagnosis) is what ``test_regress`` holds to the goldens; the tests of lab_02's
magnet read the same outputs. Each of those files analysing the recordings anew cost the
suite a lab_02 diagnosis (45 s) per file. Under pytest-xdist the workers share the one run
through a lock in the run's common temporary folder: the first to ask runs it, the others
wait for it and read its files. Nobody writes into them.
"""

from __future__ import annotations

import dataclasses
import fcntl
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
REAL = HERE.parents[1] / "shared" / "data" / "real"
NAMES = ("lab_01", "lab_02", "lab_03", "lab_04", "lab_05")


@dataclasses.dataclass(frozen=True)
class RealRun:
    """``process`` of the real recordings: its output folder, exit status and stderr."""

    out: Path
    returncode: int
    stderr: str

    def folder(self, name: str) -> Path:
        """The outputs of one recording (``lab_02``)."""
        return self.out / name

    def json(self, name: str, file: str) -> dict:
        """One recording's JSON output (``calibration.json``, ``diagnosis.json``)."""
        return json.loads((self.folder(name) / file).read_text(encoding="utf-8"))


def _process(root: Path) -> dict:
    from make_golden import REAL_CAMPAIGN_TOML

    camp = root / "real.toml"
    camp.write_text(REAL_CAMPAIGN_TOML.format(real=REAL.as_posix()), encoding="utf-8")
    out = root / "out"
    shutil.rmtree(out, ignore_errors=True)  # a run killed before it wrote its record
    p = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "process", str(camp),
                        "--out", str(out), "--jobs", "2", "--no-progress"],
                       capture_output=True, text=True, timeout=1500, cwd=HERE.parent,
                       env={**os.environ, "MAGALIGN_PROGRESS": "never"})
    return {"returncode": p.returncode, "stderr": p.stderr}


def real_run(tmp_path_factory: pytest.TempPathFactory) -> RealRun:
    """Process the real recordings once per run of the suite (shared by xdist's workers)."""
    if not all((REAL / f"{n}.mcap").is_file() for n in NAMES):
        pytest.skip(f"the shared real recordings (../shared/data/real) are not here: {REAL}")
    base = tmp_path_factory.getbasetemp()
    # under xdist each worker has its own folder below the run's common one
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "real_campaign"
    root.mkdir(exist_ok=True)
    with open(root / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        record = root / "run.json"
        if not record.is_file():
            record.write_text(json.dumps(_process(root)), encoding="utf-8")
        done = json.loads(record.read_text(encoding="utf-8"))
    return RealRun(root / "out", int(done["returncode"]), str(done["stderr"]))

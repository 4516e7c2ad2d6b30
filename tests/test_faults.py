"""Faults beyond SIGKILL (issue 16): full disk, read-only output, unusable TMPDIR, a worker dying.

Each leaves nothing partial under a final name (every file there is complete, checked as in
``test_kill_rerun``), answers in one line when it fails, and a rerun without the fault
finishes.
"""

from __future__ import annotations

import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import corpus
import pyarrow.parquet as pq
import pytest
from _pause import kill_paused_worker
from test_kill_rerun import check_no_partial_output

from pipeline.core.atomic import PAUSE_AT_ENV, PAUSE_DIR_ENV
from pipeline.model.calibration import Calibration

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"


#: Run as root without the capabilities that let root ignore file permissions (CI runs as
#: root): a read-only folder is then read-only for the program too.
NO_DAC_OVERRIDE = ["setpriv", "--inh-caps=-dac_override,-dac_read_search",
                   "--bounding-set=-dac_override,-dac_read_search", "--"]


def magalign(argv: list[str], *, fsize: int | None = None, env: dict | None = None,
             timeout: float = 600, permissions_bind: bool = False
             ) -> subprocess.CompletedProcess:
    """Run the program; ``fsize`` limits the size of every file it writes (a full disk).

    ``permissions_bind``: file permissions bind the program even when the tests run as root
    (its capability to override them is dropped with util-linux's ``setpriv``).
    """

    def limit() -> None:
        if fsize is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

    prefix: list[str] = []
    if permissions_bind and os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.fail("running as root: setpriv (util-linux) is needed to drop the "
                        "capability to override file permissions")
        prefix = NO_DAC_OVERRIDE
    return subprocess.run([*prefix, sys.executable, "-m", "pipeline.app.cli", *argv],
                          capture_output=True,
                          text=True, timeout=timeout, cwd=HERE.parent, preexec_fn=limit,
                          env={**os.environ, **(env or {})})


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return corpus.valid(tmp_path_factory.mktemp("faults"))


def _one_line_failure(r: subprocess.CompletedProcess, *words: str) -> str:
    assert r.returncode == 2, r.stderr
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("magalign: "), lines
    assert "Traceback" not in r.stderr and "internal error" not in r.stderr, r.stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def test_full_disk_calibrate(tmp_path, recording):
    out = tmp_path / "out"
    # the failure comes after the analysis: on a busy machine that can outlast the wait of
    # the log of stages (tests/test_progress.py), which would come first
    r = magalign(["calibrate", str(recording), "--out", str(out)], fsize=300,
                 env={"MAGALIGN_PROGRESS": "never"})
    _one_line_failure(r, str(out), "calibration.json", "File too large", "disk space")
    assert not [f for f in out.rglob("*") if f.is_file()]  # not even a temporary
    r = magalign(["calibrate", str(recording), "--out", str(out)])
    assert r.returncode == 0, r.stderr
    Calibration.load(out / "calibration.json")


def test_full_disk_process(tmp_path, recording):
    out = tmp_path / "out"
    argv = ["process", str(recording), "--out", str(out), "--no-progress"]
    r = magalign(argv, fsize=60_000)  # the small outputs fit, the larger ones do not
    _one_line_failure(r, str(out), "File too large", "disk space")
    seen = check_no_partial_output(out)
    assert seen["tmp"] == 0
    assert not (out / recording.stem / ".magalign-done.json").exists()
    r = magalign(argv)
    assert r.returncode == 0, r.stderr
    check_no_partial_output(out)
    assert (out / recording.stem / ".magalign-done.json").is_file()
    rows = pq.read_table(out / "summary.parquet").to_pylist()
    assert [row["status"] for row in rows] == ["ok"]


def test_read_only_output_folder(tmp_path, recording):
    """Also as root (CI): the program runs without the capability to ignore permissions."""
    out = tmp_path / "out"
    out.mkdir()
    out.chmod(0o555)
    try:
        for argv in (["calibrate", str(recording), "--out", str(out)],
                     ["process", str(recording), "--out", str(out), "--no-progress"]):
            r = magalign(argv, permissions_bind=True)
            _one_line_failure(r, str(out))
            assert not list(out.iterdir())
    finally:
        out.chmod(0o755)
    r = magalign(["calibrate", str(recording), "--out", str(out)])
    assert r.returncode == 0, r.stderr


def test_unusable_tmpdir(tmp_path, recording):
    """TMPDIR naming a file (no folder can be made in it): outputs never go through it."""
    bad = tmp_path / "not_a_folder"
    bad.write_text("x")
    env = {"TMPDIR": str(bad), "TMP": str(bad), "TEMP": str(bad)}
    out = tmp_path / "out"
    r = magalign(["calibrate", str(recording), "--out", str(out)], env=env)
    assert r.returncode == 0, r.stderr
    r = magalign(["process", str(recording), "--out", str(out), "--no-progress"], env=env)
    assert r.returncode == 0, r.stderr
    seen = check_no_partial_output(out)
    assert seen["tmp"] == 0 and seen["final"] > 5
    assert bad.read_text() == "x"


def test_worker_dies_in_a_local_pool_campaign(tmp_path):
    """A worker killed midway: the pool is rebuilt, the recording redone, the rest finish."""
    from test_campaign import _tiny_campaign

    camp = _tiny_campaign(tmp_path)
    out = tmp_path / "out"
    hook = tmp_path / "hook"
    hook.mkdir()
    env = {PAUSE_DIR_ENV: str(hook), PAUSE_AT_ENV: "written line_restored/calibration.json"}
    p = subprocess.Popen([sys.executable, "-m", "pipeline.app.cli", "process", str(camp), "--out",
                          str(out), "--jobs", "2", "--no-progress"], cwd=HERE.parent,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, **env}, start_new_session=True)
    err = kill_paused_worker(p, hook, lambda pid: pid != p.pid, timeout_s=600)
    assert p.returncode == 0, err
    rows = {row["name"]: row["status"] for row in pq.read_table(out / "summary.parquet")
            .to_pylist()}
    assert rows == {"rotation": "ok", "line_restored": "ok", "line_disturbed": "ok"}
    seen = check_no_partial_output(out)
    assert seen["tmp"] == 0
    r = magalign(["process", str(camp), "--out", str(out), "--jobs", "2", "--no-progress"])
    assert r.returncode == 0, r.stderr
    rows = {row["name"]: row["status"] for row in pq.read_table(out / "summary.parquet")
            .to_pylist()}
    assert set(rows.values()) == {"reused"}


def test_read_only_file_system_in_process(tmp_path, recording, monkeypatch, capsys):
    """The same answer when the folder cannot take a file (as root, emulated: EROFS)."""
    import errno
    import tempfile

    from pipeline.app.cli import main

    def refuse(*_a, **_k):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    out = tmp_path / "out"
    assert main(["calibrate", str(recording), "--out", str(out)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and str(out) in err[0] and "Read-only file system" in err[0], err
    assert "write to" in err[0]  # what to do
    assert not [f for f in out.rglob("*") if f.is_file()]

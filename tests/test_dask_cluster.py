"""A campaign on a real Dask cluster: a scheduler and two workers started as separate processes.

Issue 18: the results are the same as the local pool's. Issue 16: a worker that dies in the
middle of a Dask campaign leaves nothing partial and the campaign finishes on the other one.

The cluster is ``dask scheduler`` plus two ``dask worker`` processes (no nanny, one thread each)
on 127.0.0.1, started and stopped by the test, exactly as docs/campaigns.md tells a user to
start them on several machines (there with a shared file system for the recordings).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

# a hard dependency (dask[distributed] in pyproject.toml): missing, the module fails to
# import, it is not skipped
import distributed  # noqa: F401
import pyarrow.parquet as pq
from _pause import kill_paused_worker
from test_campaign import _tiny_campaign
from test_kill_rerun import check_no_partial_output

from pipeline.core.atomic import PAUSE_AT_ENV, PAUSE_DIR_ENV
from pipeline.model.calibration import Calibration

HERE = Path(__file__).resolve().parent


def _start(args: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen:
    with open(log, "wb") as fh:
        return subprocess.Popen([sys.executable, "-m", *args], stdout=fh, stderr=subprocess.STDOUT,
                                cwd=HERE.parent, env={**os.environ, **env},
                                start_new_session=True)


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGTERM)
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()


@contextlib.contextmanager
def dask_cluster(folder: Path, env: dict[str, str] | None = None,
                 n_workers: int = 2) -> Iterator[tuple[str, list[subprocess.Popen]]]:
    """Start a scheduler and ``n_workers`` workers on 127.0.0.1; yield (address, workers).

    The waits are for events (the scheduler file appears, the workers register), each with a
    generous guard against a hang; nothing is timed.
    """
    from distributed import Client

    env = env or {}
    sched_file = folder / "scheduler.json"
    procs: list[subprocess.Popen] = []
    try:
        sched = _start(["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
                        "--no-dashboard", "--scheduler-file", str(sched_file)],
                       folder / "scheduler.log", env)
        procs.append(sched)
        t_end = time.monotonic() + 120
        while not sched_file.exists() or not sched_file.read_text().strip().endswith("}"):
            assert sched.poll() is None, (folder / "scheduler.log").read_text()
            assert time.monotonic() < t_end, "the scheduler did not start"
            time.sleep(0.05)
        address = json.loads(sched_file.read_text())["address"]
        workers = [
            _start(["distributed.cli.dask_worker", "--scheduler-file", str(sched_file),
                    "--host", "127.0.0.1", "--nthreads", "1", "--no-nanny", "--no-dashboard",
                    "--name", f"w{i}"], folder / f"worker{i}.log", env)
            for i in range(n_workers)]
        procs.extend(workers)
        with Client(address, timeout=120) as client:
            client.wait_for_workers(n_workers, timeout=300)
        yield address, workers
    finally:
        for p in reversed(procs):
            _stop(p)


def _cli(*argv: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.app.cli", *argv], capture_output=True,
                          text=True, cwd=HERE.parent, timeout=900,
                          env={**os.environ, **(env or {})})


def _rows(out: Path) -> list[dict]:
    return pq.read_table(out / "summary.parquet").to_pylist()


def _same(a: object, b: object, where: str) -> None:
    """Equal values; floats equal to 1e-9 relative (the same code on the same machine)."""
    if isinstance(a, float) and isinstance(b, float):
        if math.isnan(a) and math.isnan(b):
            return
        assert math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12), f"{where}: {a} != {b}"
    elif isinstance(a, dict) and isinstance(b, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list) and isinstance(b, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{where}[{i}]")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


# columns that say where the outputs went or how long the run took, not what was found
_RUN_COLUMNS = {"elapsed_s", "out_dir", "paths", "report", "rrd", "corrected_mcap"}


def test_cluster_gives_the_local_pools_results(tmp_path):
    camp = _tiny_campaign(tmp_path)
    local = tmp_path / "local"
    r = _cli("process", str(camp), "--out", str(local), "--jobs", "2", "--no-progress")
    assert r.returncode == 0, r.stderr
    with dask_cluster(tmp_path) as (address, _):
        out = tmp_path / "dask"
        r = _cli("process", str(camp), "--out", str(out), "--scheduler", address,
                 "--no-progress")
        assert r.returncode == 0, r.stderr
        assert f"Dask scheduler {address} (2 worker(s))" in r.stdout
    rows_local, rows_dask = _rows(local), _rows(out)
    assert [x["status"] for x in rows_dask] == ["ok", "ok", "ok"]
    assert [x["name"] for x in rows_dask] == [x["name"] for x in rows_local]
    for a, b in zip(rows_local, rows_dask, strict=True):
        keep = {k: v for k, v in a.items() if k not in _RUN_COLUMNS}
        assert len(keep) > 20 and "time_offset_s" in keep
        _same(keep, {k: b[k] for k in keep}, a["name"])
    for row in rows_local:
        name = row["name"]
        assert sorted(p.name for p in (local / name).iterdir()) == \
            sorted(p.name for p in (out / name).iterdir())
        cal_l = Calibration.load(local / name / "calibration.json")
        cal_d = Calibration.load(out / name / "calibration.json")
        _same(cal_l.R_body_mag.tolist(), cal_d.R_body_mag.tolist(), f"{name} R_body_mag")
        for f in ("metrics.json", "diagnosis.json"):
            if (local / name / f).exists():
                _same(json.loads((local / name / f).read_text()),
                      json.loads((out / name / f).read_text()), f"{name}/{f}")


def test_worker_dies_in_a_dask_campaign(tmp_path):
    """A worker killed while it writes a result: the other worker redoes the recording."""
    camp = _tiny_campaign(tmp_path)
    hook = tmp_path / "hook"
    hook.mkdir()
    env = {PAUSE_DIR_ENV: str(hook), PAUSE_AT_ENV: "written line_restored/calibration.json"}
    with dask_cluster(tmp_path, env=env) as (address, workers):
        out = tmp_path / "out"
        p = subprocess.Popen([sys.executable, "-m", "pipeline.app.cli", "process", str(camp),
                              "--out", str(out), "--scheduler", address, "--no-progress"],
                             cwd=HERE.parent, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, start_new_session=True)
        err = kill_paused_worker(p, hook, lambda pid: pid in [w.pid for w in workers])
        assert p.returncode == 0, err
        assert sum(w.poll() is None for w in workers) == 1
    rows = {row["name"]: row["status"] for row in _rows(out)}
    assert rows == {"rotation": "ok", "line_restored": "ok", "line_disturbed": "ok"}
    seen = check_no_partial_output(out)
    assert seen["tmp"] == 0
    Calibration.load(out / "line_restored" / "calibration.json")

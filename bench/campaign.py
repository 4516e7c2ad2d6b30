"""Campaign throughput: N recordings through 1 and 2 local workers and a Dask LocalCluster.

Default (issue 7): 40 survey recordings of 10 minutes at 200 Hz (120,000 magnetometer and
attitude samples each). ``--small``: 6 recordings of 1 minute, for a quick check.

The recordings are simulated once (demo survey line, a different seed each) into a scratch
folder; each configuration then processes them into a fresh output folder (no reuse), with
diagnosis on and the Rerun and HTML outputs off (this measures the executors, not the
writers). Prints wall time, recordings per minute and the speed-up over one worker.

    python bench/campaign.py [--small] [--n N] [--minutes M] [--rate-hz R] [--keep DIR]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def scenario_text(minutes: float, rate_hz: float, seed: int, name: str) -> str:
    """The demo survey line stretched to ``minutes`` at ``rate_hz``."""
    text = (ROOT / "pipeline" / "demo" / "line_01.toml").read_text(encoding="utf-8")
    turn_s = min(40.0, 0.1 * minutes * 60.0)
    line_s = (minutes * 60.0 - turn_s) / 2.0
    for key, val in (("name", f'"{name}"'), ("seed", str(seed)),
                     ("mag_rate_hz", str(rate_hz)), ("attitude_rate_hz", str(rate_hz)),
                     ("line_duration_s", str(line_s)), ("turn_duration_s", str(turn_s))):
        text = re.sub(rf"^{key}\s*=.*$", f"{key} = {val}", text, count=1, flags=re.MULTILINE)
    return text


def generate(job: tuple[str, str]) -> str:
    """Simulate one scenario text into an MCAP file (runs in a worker)."""
    from pipeline.app.simulate import scenario_from_doc, simulate, write_simulated
    from pipeline.core.config import TomlDoc

    text, dest = job
    sim = simulate(scenario_from_doc(TomlDoc.parse(text, dest)))
    write_simulated(sim, dest)
    return dest


CAMPAIGN = """\
[campaign]
name = "bench"

[channels]
mag = "/mag"
attitude = "/novatel/oem7/inspva"

[outputs]
diagnose = true
rerun = false
report = false

[[recordings]]
glob = "rec_*.mcap"
"""


def run_config(camp: Path, out: Path, args: list[str]) -> float:
    """Wall time (s) of one ``magalign process`` run."""
    from pipeline.app.cli import main

    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        status = main(["process", str(camp), "--out", str(out), "--no-progress", *args])
    dt = time.perf_counter() - t0
    if status != 0:
        raise SystemExit(f"process {' '.join(args)} exited with {status}")
    return dt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="6 recordings of 1 minute")
    ap.add_argument("--n", type=int, default=None)
    ap.add_argument("--minutes", type=float, default=None)
    ap.add_argument("--rate-hz", type=float, default=200.0)
    ap.add_argument("--keep", default=None, help="scratch folder to keep (default: temporary)")
    a = ap.parse_args()
    n = a.n or (6 if a.small else 40)
    minutes = a.minutes or (1.0 if a.small else 10.0)
    scratch = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="magalign-bench-"))
    data = scratch / "data"
    data.mkdir(parents=True, exist_ok=True)
    from pipeline.app.executors import LocalExecutor

    jobs = [(scenario_text(minutes, a.rate_hz, 1000 + i, f"rec_{i:03d}"),
             str(data / f"rec_{i:03d}.mcap")) for i in range(n)]
    todo = [j for j in jobs if not Path(j[1]).is_file()]
    t0 = time.perf_counter()
    ex = LocalExecutor(2)
    try:
        for _, res in ex.map(generate, todo):
            if isinstance(res, BaseException):
                raise res
    finally:
        ex.close()
    size_mb = sum(Path(j[1]).stat().st_size for j in jobs) / 1e6
    print(f"{n} recordings of {minutes:g} min at {a.rate_hz:g} Hz "
          f"({int(minutes * 60 * a.rate_hz)} samples each, {size_mb:.0f} MB) simulated in "
          f"{time.perf_counter() - t0:.1f} s; {os.cpu_count()} CPU(s)")
    camp = data / "campaign.toml"
    camp.write_text(CAMPAIGN, encoding="utf-8")
    results = {}
    for label, args in (("1 local worker", ["--jobs", "1"]),
                        ("2 local workers", ["--jobs", "2"]),
                        ("Dask LocalCluster, 2 workers", ["--dask-local", "2"])):
        dt = run_config(camp, scratch / f"out_{len(results)}", args)
        results[label] = dt
        print(f"{label:30s} {dt:8.1f} s  {n / dt * 60:6.1f} recordings/min  "
              f"speed-up x{results['1 local worker'] / dt:.2f}", flush=True)
    (scratch / "bench_campaign.json").write_text(json.dumps(
        {"n": n, "minutes": minutes, "rate_hz": a.rate_hz, "wall_s": results}, indent=1))
    if not a.keep:
        shutil.rmtree(scratch, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

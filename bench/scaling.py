"""``magalign process`` against recording length: wall time and peak memory, and their plot.

For each length (default 15 min, 1 h, 2 h and 10 h at 200 Hz: magnetometer + attitude,
``bench/scale.py``'s synthetic motion, ROS 2 CDR, zstd), the recording is generated in a
child process, then ``magalign process REC --out DIR`` runs with its defaults (all outputs:
calibration, diagnosis, metrics, corrected MCAP, rerun recording, report) in a fresh process,
measured as ``bench/process.py`` measures it: wall time and the peak resident memory of the
largest process of its tree (``VmHWM``, sampled every 0.25 s). One run per length, lengths in
increasing order; a length whose run exceeds ``--limit`` seconds is stopped and reported as
such, and the longer ones are not tried.

Prints the table, appends each figure to ``bench/results.csv`` and draws ``docs/scaling.png``
(time and peak memory against hours of recording, with the straight line (a fixed cost plus
a cost per hour) fitted to the measured points, so that a departure from linear scaling
shows).

    python bench/scaling.py [--minutes 15,60,120,600] [--limit S] [--keep DIR] [--png PATH]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from process import MAGALIGN, _tree_hwm_mb  # noqa: E402
from results import record  # noqa: E402
from scale import RATE_HZ  # noqa: E402

DEFAULT_MINUTES = "15,60,120,600"
DEFAULT_PNG = ROOT / "docs" / "scaling.png"


def generate(path: Path, n: int) -> None:
    """Write ``n`` + ``n`` messages to ``path`` in a child process (its memory is not ours)."""
    subprocess.run([sys.executable, "-c", "import sys; sys.path[:0] = sys.argv[3:]; "
                    "from scale import make_recording; from pathlib import Path; "
                    "make_recording(Path(sys.argv[1]), int(sys.argv[2]))",
                    str(path), str(n), str(Path(__file__).resolve().parent), str(ROOT)],
                   check=True, cwd=ROOT)


def run_limited(cmd: list[str], limit_s: float) -> tuple[float, float, bool]:
    """Wall seconds, peak RSS (MB, largest process of the tree) and whether it finished."""
    seen: dict[int, float] = {}
    with tempfile.TemporaryFile() as err:
        t = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, cwd=ROOT,
                                start_new_session=True)
        finished = True
        while proc.poll() is None:
            _tree_hwm_mb(proc.pid, seen)
            if time.perf_counter() - t > limit_s:
                os.killpg(proc.pid, 9)  # the command's own process group (its workers)
                proc.wait()
                finished = False
                break
            time.sleep(0.25)
        wall = time.perf_counter() - t
        if finished and proc.returncode != 0:
            err.seek(0)
            raise SystemExit(f"{cmd[:3]} failed ({proc.returncode}): "
                             f"{err.read().decode(errors='replace')[-2000:]}")
    return wall, max(seen.values(), default=float("nan")), finished


def plot(rows: list[dict], png: Path) -> None:
    """Draw time and peak memory against hours of recording, with the fitted straight line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    done = [r for r in rows if r["finished"]]
    h = np.array([r["minutes"] / 60 for r in done])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    for ax, key, label in ((axes[0], "wall_s", "wall time (s)"),
                           (axes[1], "peak_mb", "peak RSS (MB)")):
        y = np.array([r[key] for r in done])
        ax.plot(h, y, "o", color="#1f77b4", label="measured")
        for hi, yi in zip(h, y, strict=True):
            ax.annotate(f"{yi:,.0f}", (hi, yi), textcoords="offset points", xytext=(4, -12),
                        fontsize=8)
        if len(h) >= 2:
            slope, fixed = np.polyfit(h, y, 1)  # a fixed cost plus a cost per hour
            xs = np.linspace(0, h.max() * 1.05, 50)
            unit = label.split(" (")[1][:-1]
            ax.plot(xs, fixed + slope * xs, "--", color="#7f7f7f",
                    label=f"straight line: {fixed:,.0f} {unit} + {slope:,.0f} {unit} per hour")
        ax.set_xlabel("recording length (h at 200 Hz, magnetometer + attitude)")
        ax.set_ylabel(label)
        ax.set_xlim(left=0)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize=8)  # the points rise to the upper right
    for r in rows:
        if not r["finished"]:
            axes[0].axvline(r["minutes"] / 60, color="#d62728", alpha=0.4)
            axes[0].annotate(f"{r['minutes'] / 60:g} h: stopped after {r['wall_s']:.0f} s",
                             (r["minutes"] / 60, 0), rotation=90, fontsize=8,
                             color="#d62728", xytext=(-10, 10), textcoords="offset points")
    fig.suptitle("magalign process, all outputs (2 cores)", fontsize=10)
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", default=DEFAULT_MINUTES, help="comma-separated lengths")
    ap.add_argument("--limit", type=float, default=900.0, help="seconds per run at most")
    ap.add_argument("--keep", default=None, help="folder to keep the recordings in")
    ap.add_argument("--png", default=str(DEFAULT_PNG))
    args = ap.parse_args()
    cli = [str(MAGALIGN)] if MAGALIGN.exists() else [sys.executable, "-m", "pipeline.cli"]
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.keep or tmp)
        work.mkdir(parents=True, exist_ok=True)
        for minutes in (float(m) for m in args.minutes.split(",")):
            n = int(minutes * 60 * RATE_HZ)
            rec = work / f"scale_{n}.mcap"
            if not rec.exists():
                generate(rec, n)
            size_mb = rec.stat().st_size / 1e6
            out = Path(tempfile.mkdtemp(prefix="out_", dir=work))
            load = os.getloadavg()[0]
            wall, peak, finished = run_limited(cli + ["process", str(rec), "--out", str(out)],
                                               args.limit)
            shutil.rmtree(out, ignore_errors=True)
            if args.keep is None:
                rec.unlink()
            row = {"minutes": minutes, "n": n, "size_mb": size_mb, "wall_s": wall, "peak_mb": peak,
                   "finished": finished, "load": max(load, os.getloadavg()[0])}
            rows.append(row)
            print(f"{minutes / 60:6.2f} h  {n:>9,} + {n:,} messages ({size_mb:,.0f} MB)  "
                  f"wall {wall:7.1f} s  "
                  f"peak RSS {peak:7,.0f} MB  load {row['load']:.1f}"
                  + ("" if finished else f"  (stopped at the {args.limit:.0f} s limit)"),
                  flush=True)
            if finished:
                record("scaling", f"magalign process {minutes:.0f} min, wall", wall, "s")
                record("scaling", f"magalign process {minutes:.0f} min, peak RSS", peak, "MB")
            else:
                break
    print("\n| length | messages | file | wall time | peak RSS | s per hour | MB per hour | load |"
          "\n| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        h = r["minutes"] / 60
        state = "" if r["finished"] else " (stopped)"
        print(f"| {h:.3g} h | {r['n']:,} + {r['n']:,} | {r['size_mb']:,.0f} MB | "
              f"{r['wall_s']:.1f} s{state} | "
              f"{r['peak_mb']:,.0f} MB | {r['wall_s'] / h:.1f} | {r['peak_mb'] / h:,.0f} | "
              f"{r['load']:.1f} |")
    plot(rows, Path(args.png))
    print(f"plot: {args.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``magalign calibrate`` end to end against mcap_ros2 merely decoding the same file.

A recording of 240k magnetometer + 240k attitude messages (20 minutes at 200 Hz, ROS 2 CDR,
zstd; ``bench/scale.py``'s synthetic motion) is written into a temporary folder. Timed, in
the same run, as wall time of a fresh process each (interpreter start and imports included):

- ``magalign calibrate REC --out DIR`` (the default ML estimator; median of RUNS);
- the streaming estimate (the runner's analysis of the file read in ranges, from the sums
  of every sample, without the diagnosis; median of RUNS), the path of long recordings;
- ``mcap_ros2``'s ``iter_decoded_messages`` over every message, doing nothing with them
  (median of ROS2_RUNS).

Target (issue 8): ``magalign calibrate`` at least 10x faster than the decoding alone.

    python bench/calibrate.py [--n N] [--runs RUNS] [--ros2-runs ROS2_RUNS]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from scale import make_recording  # noqa: E402

MAGALIGN = Path(sys.executable).with_name("magalign")

STREAM = ("import sys; from pipeline.run.runner import ProcessOptions, analyse_recording; "
          "from pathlib import Path; c = analyse_recording(sys.argv[1], ProcessOptions("
          "diagnose=False, scale_samples=0)).need_calibration(); "
          "Path(sys.argv[2]).write_text(c.to_json())")
ROS2 = ("import sys; from mcap.reader import make_reader; "
        "from mcap_ros2.decoder import DecoderFactory; fh = open(sys.argv[1], 'rb'); "
        "r = make_reader(fh, decoder_factories=[DecoderFactory()]); "
        "n = sum(1 for _ in r.iter_decoded_messages(log_time_order=False)); print(n)")


def wall(cmd: list[str]) -> float:
    """Wall seconds of a subprocess (must succeed)."""
    t = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, cwd=ROOT)
    return time.perf_counter() - t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=240_000, help="messages per channel")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--ros2-runs", type=int, default=1)
    args = ap.parse_args()
    cli = [str(MAGALIGN)] if MAGALIGN.exists() else [sys.executable, "-m", "pipeline.app.cli"]
    with tempfile.TemporaryDirectory() as tmp:
        rec = make_recording(Path(tmp) / "cal.mcap", args.n)
        size = rec.stat().st_size / 1e6
        ours = [wall(cli + ["calibrate", str(rec), "--out", str(Path(tmp) / f"o{i}")])
                for i in range(args.runs)]
        stream = [wall([sys.executable, "-c", STREAM, str(rec), str(Path(tmp) / "s.json")])
                      for _ in range(args.runs)]
        theirs = [wall([sys.executable, "-c", ROS2, str(rec)]) for _ in range(args.ros2_runs)]
    t_ours, t_stream, t_theirs = (statistics.median(x) for x in (ours, stream, theirs))
    print(f"file: {args.n} magnetometer + {args.n} attitude messages, {size:.0f} MB; "
          f"load average {os.getloadavg()[0]:.1f}")
    print(f"{'':<44} {'wall_s':>8} {'ratio':>8}")
    print(f"{'mcap_ros2 iter_decoded_messages (decode only)':<44} {t_theirs:8.2f} {'1.0x':>8}")
    print(f"{'magalign calibrate (ML)':<44} {t_ours:8.2f} {t_theirs / t_ours:7.1f}x")
    print(f"{'streaming estimate (chunked statistics)':<44} {t_stream:8.2f} "
          f"{t_theirs / t_stream:7.1f}x")
    print(f"ratio: {t_theirs / t_ours:.1f}x (target >= 10x)")
    from results import record

    record("calibrate", f"magalign calibrate {2 * args.n} messages", t_ours, "s",
           reference=t_theirs, ratio=t_theirs / t_ours)
    record("calibrate", f"streaming estimate {2 * args.n} messages", t_stream, "s",
           reference=t_theirs, ratio=t_theirs / t_stream)
    return 0


if __name__ == "__main__":
    sys.exit(main())

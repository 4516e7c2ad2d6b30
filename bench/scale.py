"""Scale benchmark: each step on a long recording, time and peak memory, in its own process.

A recording of MINUTES (default 120) at 200 Hz (magnetometer and attitude, 2 x 1.44M
messages for two hours) is generated once into a temporary folder with
``pipeline.mcap_write.write_recording`` from simple synthetic arrays (a slow heading rotation
with pitch and roll swings; rotation vector [1, -2, 3] deg). Then each step runs in a fresh
subprocess that reports its wall time and its peak resident memory (``VmHWM`` of /proc,
else ``ru_maxrss``), also minus the resident memory after the imports (the interpreter,
numpy, the pipeline):

- ``ingest``: ``read_recording`` (whole file into arrays);
- ``estimate_stream``: the runner's streaming estimate on the file (chunks of 100k messages: the
  path for recordings larger than memory; sufficient statistics per chunk);
- ``restore``: ingest + attitude at the magnetometer stamps + ``restore_samples``;
- ``write_mcap``: ingest + ``write_corrected_mcap`` (input copied range by range);
- ``write_rrd``: ingest + ``write_rrd`` (rerun);
- ecosystem: ``mcap_ros2`` ``iter_decoded_messages`` into numpy arrays (the same arrays).

Printed per step: our time and peak, the numeric arrays involved (bytes of the input and
output arrays of the step), and peak / arrays (the issue's bound: at most 4x). For ingest the
ecosystem's time and peak are printed beside ours with the ratio.

    python bench/scale.py [--minutes M] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

RATE_HZ = 200.0
ROTVEC_DEG = (1.0, -2.0, 3.0)
B_ENU_NT = (10_000.0, 30_000.0, -20_000.0)
#: bytes per sample pair held by a Recording: mag t (8) + xyz (24), attitude t (8) + q (32)
RECORDING_BYTES = 72
#: bytes per sample of RestoreResult: t 8, calibrated 24, q 32, enu 24, residual 24, valid 1
RESTORED_BYTES = 113


def synthetic_arrays(n: int, seed: int = 1) -> dict[str, np.ndarray]:
    """Stamps, field and attitude of ``n`` samples at 200 Hz (vectorised, seconds per 1M)."""
    from pipeline.core.geometry import li2020_euler_to_quat, quat_conj, quat_rotate, rotvec_to_quat

    rng = np.random.default_rng(seed)
    t0 = 1_700_000_000 * 1_000_000_000
    t = t0 + np.arange(n, dtype=np.int64) * int(1e9 / RATE_HZ)
    s = np.arange(n) / RATE_HZ
    heading = 2 * np.pi * s / 60.0  # one turn a minute
    pitch = np.radians(15.0) * np.sin(2 * np.pi * s / 35.0)
    roll = np.radians(15.0) * np.sin(2 * np.pi * s / 45.0)
    q = li2020_euler_to_quat(heading, pitch, roll)
    q_mag = rotvec_to_quat(np.radians(ROTVEC_DEG))  # R_body_mag
    b_body = quat_rotate(quat_conj(q), np.broadcast_to(np.asarray(B_ENU_NT), (n, 3)))
    mag = quat_rotate(quat_conj(q_mag), b_body) + 1.0 * rng.standard_normal((n, 3))
    return {"t_ns": t, "mag_nT": mag, "q_enu_body": q}


def make_recording(path: Path, n: int) -> Path:
    """Write ``n`` magnetometer + ``n`` attitude messages (ROS 2 CDR, zstd) to ``path``."""
    from pipeline.io.mcap_write import write_recording

    a = synthetic_arrays(n)
    return write_recording(path, mag_t_ns=a["t_ns"], mag_nT=a["mag_nT"],
                           attitude_t_ns=a["t_ns"] + 1_000_000, q_enu_body=a["q_enu_body"],
                           mag_log_delay_ns=200_000, attitude_log_delay_ns=900_000)


def ros2_decode_s(path: Path, into_arrays: bool = False) -> float:
    """Seconds ``mcap_ros2`` needs to decode every message (optionally into numpy arrays)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    t = time.perf_counter()
    mag: list = []
    att: list = []
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _s, ch, _m, msg in reader.iter_decoded_messages(log_time_order=False):
            if into_arrays:
                st = msg.header.stamp
                tt = st.sec * 1_000_000_000 + st.nanosec
                if ch.topic == "/mag":
                    f = msg.magnetic_field
                    mag.append((tt, f.x * 1e9, f.y * 1e9, f.z * 1e9))
                else:
                    o = msg.orientation
                    att.append((tt, o.x, o.y, o.z, o.w))
    if into_arrays:
        m, a = np.array(mag), np.array(att)
        _ = (m[:, 0].astype(np.int64), m[:, 1:], a[:, 0].astype(np.int64), a[:, 1:])
    return time.perf_counter() - t


# --------------------------------------------------------------------------- child steps
def _rss_mb() -> float:
    """Peak resident memory of this process, MB.

    ``VmHWM`` of /proc (this process image only): ``ru_maxrss`` of a child started by
    fork + exec also counts the parent's resident memory at the fork.
    """
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _current_rss_mb() -> float:
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return _rss_mb()


def child(step: str, path: str, work: str) -> None:
    """Run one step in this process and print one JSON line."""
    import warnings

    from pipeline.io.mcap_read import read_recording
    from pipeline.model.calibration import Calibration
    from pipeline.run.runner import ProcessOptions, analyse_recording
    from stages.restore import restore_samples
    from stages.write_mcap import write_corrected_mcap
    from stages.write_rerun import write_rrd

    warnings.simplefilter("ignore")
    base = _current_rss_mb()
    t = time.perf_counter()
    n = 0
    extra = 0
    cal_path = Path(work) / "calibration.json"
    if step == "ingest":
        rec = read_recording(path)
        n = len(rec.mag)
    elif step == "estimate_stream":
        cal = analyse_recording(path, ProcessOptions(diagnose=False, scale_samples=0)
                                ).need_calibration()
        n = cal.n_samples
        cal_path.write_text(cal.to_json())
    elif step == "ros2_arrays":
        ros2_decode_s(Path(path), into_arrays=True)
    else:
        rec = read_recording(path)
        n = len(rec.mag)
        cal = Calibration.load(cal_path)
        if step == "restore":
            restore_samples(rec, cal)
            extra = RESTORED_BYTES * n
        elif step == "write_mcap":
            write_corrected_mcap(rec, cal, Path(work) / "out.corrected.mcap")
            extra = RESTORED_BYTES * n
        elif step == "write_rrd":
            write_rrd(rec, cal, Path(work) / "out.rrd")
            extra = RESTORED_BYTES * n + 8 * 24 * n  # view_data's eight more (N, 3) series
    print(json.dumps({"step": step, "time_s": time.perf_counter() - t, "peak_mb": _rss_mb(),
                      "base_mb": base, "n": n, "extra_bytes": extra}))


def run_child(step: str, path: Path, work: Path) -> dict:
    """Run :func:`child` in a fresh interpreter; return its JSON line."""
    out = subprocess.run([sys.executable, __file__, "--child", step, str(path), str(work)],
                         check=True, capture_output=True, text=True, cwd=ROOT)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=120.0)
    ap.add_argument("--keep", default=None, help="folder to keep the recording in")
    ap.add_argument("--child", nargs=3, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return 0
    n = int(args.minutes * 60 * RATE_HZ)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.keep or tmp)
        work.mkdir(parents=True, exist_ok=True)
        path = work / f"scale_{n}.mcap"
        t = time.perf_counter()
        if not path.exists():
            make_recording(path, n)
        print(f"recording: {n} magnetometer + {n} attitude messages at {RATE_HZ:.0f} Hz, "
              f"{path.stat().st_size / 1e6:.0f} MB (generated in {time.perf_counter() - t:.0f} s)"
              f"; load average {os.getloadavg()[0]:.1f}")
        arrays_mb = RECORDING_BYTES * n / 2**20
        rows = {s: run_child(s, path, work) for s in (
            "ingest", "estimate_stream", "restore", "write_mcap", "write_rrd", "ros2_arrays")}
    print(f"{'step':<16} {'time_s':>8} {'peak_MB':>8} {'work_MB':>8} {'arrays_MB':>9} "
          f"{'peak/arrays':>11} {'work/arrays':>11}")
    for s, r in rows.items():
        arr = arrays_mb + r["extra_bytes"] / 2**20
        work_mb = r["peak_mb"] - r["base_mb"]
        print(f"{s:<16} {r['time_s']:8.1f} {r['peak_mb']:8.0f} {work_mb:8.0f} {arr:9.0f} "
              f"{r['peak_mb'] / arr:10.2f}x {work_mb / arr:10.2f}x")
    ours, theirs = rows["ingest"], rows["ros2_arrays"]
    print(f"ingest vs mcap_ros2 into arrays: time {ours['time_s']:.1f} s vs "
          f"{theirs['time_s']:.1f} s, ratio {theirs['time_s'] / ours['time_s']:.1f}x; peak "
          f"{ours['peak_mb']:.0f} MB vs {theirs['peak_mb']:.0f} MB, ratio "
          f"{theirs['peak_mb'] / ours['peak_mb']:.1f}x")
    print("bound (issue 8): peak <= 4x the numeric arrays; 'work' excludes the interpreter "
          "and imports (resident size after importing, before the step)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

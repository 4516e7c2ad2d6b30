"""Benchmark: writing, against mcap_ros2 and against the zstd ceiling of the same bytes.

Two parts, in the same run:

1. **Encoding and writing 200k messages** (issues 5 and 8): 200k
   ``sensor_msgs/msg/MagneticField`` messages (one frame_id) encoded and written with zstd
   chunks of 1 MiB by ``messages.encode`` + :class:`pipeline.mcap_write.McapColumnWriter` and
   by mcap_ros2's ``Writer.write_message``; medians of several runs. Target: >= 10x.
2. **The outputs of ``process`` against the ceiling** (issue 18): on a recording of
   ``--minutes`` (default 120: 1.44M magnetometer + 1.44M attitude messages at 200 Hz,
   ``bench/scale.py``'s synthetic motion), read, calibrated and restored once (not timed):

   - ``write_corrected_mcap`` (the corrected MCAP, whole) against its **ceiling**: the
     uncompressed contents of every chunk of the file it wrote, compressed chunk by chunk with
     ``zstandard`` at the level it uses (1), one thread;
   - ``write_rrd`` (the rerun recording, whole) against its **ceiling**: the bytes of every
     array ``write_rrd`` hands to rerun (time columns and values, as captured from
     ``RecordingStream.send_columns``), compressed with ``zstandard`` level 1 in 1 MiB frames,
     one thread; and against rerun's own **floor**: the same captured columns sent again with
     ``send_columns`` alone into a fresh file and flushed (what the rerun SDK needs for these
     arrays, whatever the caller does).

   Target: each writer within 2x of its ceiling (ratio = ours / ceiling <= 2). Medians of
   ``--repeat`` runs (default 3).

Every figure is appended to ``bench/results.csv`` (``bench/results.py``).

    python bench/write.py [--minutes M] [--repeat K] [--keep DIR] [--skip-ros2]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from results import record  # noqa: E402
from scale import RATE_HZ, make_recording  # noqa: E402

from pipeline.io.mcap_write import McapColumnWriter  # noqa: E402
from pipeline.io.messages import encode, schema_for  # noqa: E402

N = 200_000
TYPE = "sensor_msgs/msg/MagneticField"
#: zstd level of the corrected MCAP (stages/write_mcap.py), used for both ceilings
ZSTD_LEVEL = 1
FRAME = 1 << 20


def ours(path: Path, t_ns: np.ndarray, mag_T: np.ndarray) -> None:
    """Encode and write ``t_ns``/``mag_T`` as MagneticField messages with magalign."""
    name, s_enc, s_data, m_enc = schema_for(TYPE)
    with McapColumnWriter(path, compression="zstd") as w:
        cid = w.add_channel("/mag", m_enc, w.add_schema(name, s_enc, s_data))
        data, off = encode(TYPE, t_ns, {"mag_T": mag_T}, "mag")
        w.add_messages(cid, t_ns, data, off)


def theirs(path: Path, t_ns: np.ndarray, mag_T: np.ndarray) -> None:
    """The same messages written with mcap_ros2, one ``write_message`` each."""
    from mcap_ros2.writer import Writer as Ros2Writer

    name, _, s_data, _ = schema_for(TYPE)
    with open(path, "wb") as fh:
        w = Ros2Writer(fh)
        schema = w.register_msgdef(name, s_data.decode())
        for t, (x, y, z) in zip(t_ns.tolist(), mag_T.tolist(), strict=True):
            sec, nsec = divmod(t, 1_000_000_000)
            msg = {
                "header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": "mag"},
                "magnetic_field": {"x": x, "y": y, "z": z},
                "magnetic_field_covariance": [0.0] * 9,
            }
            w.write_message("/mag", schema, msg, log_time=t, publish_time=t)
        w.finish()


def timed(fn: Callable[..., Any], *args: Any, **kw: Any) -> float:
    """Wall seconds of ``fn(*args, **kw)``."""
    t0 = time.perf_counter()
    fn(*args, **kw)
    return time.perf_counter() - t0


def part_ros2() -> None:
    """Part 1: 200k messages, magalign against mcap_ros2."""
    rng = np.random.default_rng(0)
    t_ns = 1_700_000_000_000_000_000 + np.arange(N, dtype=np.int64) * 5_000_000
    mag_T = rng.normal(size=(N, 3)) * 2e-5
    with tempfile.TemporaryDirectory() as d:
        a, b = Path(d) / "ours.mcap", Path(d) / "theirs.mcap"
        t_ours = statistics.median(timed(ours, a, t_ns, mag_T) for _ in range(5))
        t_theirs = statistics.median(timed(theirs, b, t_ns, mag_T) for _ in range(3))
        size_a, size_b = a.stat().st_size, b.stat().st_size
    r_ours, r_theirs = N / t_ours, N / t_theirs
    print(f"write {N} MagneticField messages (zstd), medians:")
    print(f"  magalign encode+McapColumnWriter : {r_ours:12,.0f} msg/s  ({t_ours:.3f} s, "
          f"{size_a / 1e6:.1f} MB)")
    print(f"  mcap_ros2 Writer.write_message   : {r_theirs:12,.0f} msg/s  ({t_theirs:.3f} s, "
          f"{size_b / 1e6:.1f} MB)")
    print(f"  ratio: {r_ours / r_theirs:.1f}x (target >= 10x); load average "
          f"{os.getloadavg()[0]:.1f}")
    record("write", f"McapColumnWriter {N} MagneticField", r_ours, "msg/s",
           reference=r_theirs, ratio=r_ours / r_theirs)


# ------------------------------------------------------------------------------ ceilings
def chunk_contents(path: Path) -> list[bytes]:
    """The uncompressed contents of every Chunk record of an MCAP file (mcap's reader)."""
    import zstandard
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    out = []
    dec = zstandard.ZstdDecompressor()
    with open(path, "rb") as fh:
        for r in StreamReader(fh, emit_chunks=True).records:
            if isinstance(r, Chunk):
                if r.compression == "zstd":
                    out.append(dec.decompress(r.data, max_output_size=r.uncompressed_size))
                elif r.compression == "":
                    out.append(bytes(r.data))
                else:
                    raise SystemExit(f"unexpected chunk compression {r.compression!r}")
    return out


def zstd_seconds(pieces: list[Any], level: int = ZSTD_LEVEL) -> float:
    """Seconds to compress each of ``pieces`` (buffers) with one zstd compressor, one thread."""
    import zstandard

    c = zstandard.ZstdCompressor(level=level)
    t0 = time.perf_counter()
    for p in pieces:
        c.compress(p)
    return time.perf_counter() - t0


class SendCapture:
    """Wrap ``rerun.RecordingStream.send_columns`` to keep every call's arguments."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, Any, Any]] = []

    def __enter__(self) -> SendCapture:
        import rerun as rr

        self._orig = orig = rr.RecordingStream.send_columns
        calls = self.calls

        def send_columns(rec: Any, entity_path: str, indexes: Any, columns: Any,
                         **kw: Any) -> None:
            calls.append((entity_path, list(indexes), list(columns)))
            orig(rec, entity_path, indexes=indexes, columns=columns, **kw)

        rr.RecordingStream.send_columns = send_columns  # type: ignore[method-assign]
        return self

    def __exit__(self, *exc: object) -> None:
        import rerun as rr

        rr.RecordingStream.send_columns = self._orig  # type: ignore[method-assign]

    def frames(self) -> list[memoryview]:
        """The captured arrays' buffers cut in ``FRAME``-byte frames."""
        out: list[memoryview] = []
        for _e, idx, cols in self.calls:
            arrays = [i.as_arrow_array() for i in idx] + [c.as_arrow_array() for c in cols]
            for a in arrays:
                for b in a.buffers():
                    if b is None or b.size == 0:
                        continue
                    mv = memoryview(b).cast("B")
                    out += [mv[i:i + FRAME] for i in range(0, len(mv), FRAME)]
        return out

    def resend(self, dest: Path) -> float:
        """Seconds to send the captured columns alone into ``dest`` and flush (rerun's floor)."""
        import rerun as rr

        t0 = time.perf_counter()
        rec = rr.RecordingStream("magalign", recording_id="floor")
        rec.save(str(dest))
        for entity, idx, cols in self.calls:
            self._orig(rec, entity, indexes=idx, columns=cols)
        rec.flush()
        rec.disconnect()
        return time.perf_counter() - t0


def part_outputs(minutes: float, repeat: int, keep: str | None) -> None:
    """Part 2: corrected MCAP and .rrd writing against their zstd ceilings."""
    os.environ.setdefault("RUST_LOG", "off")
    from pipeline.io.mcap_read import read_recording
    from pipeline.run.runner import ProcessOptions, analyse_recording
    from stages.restore import restore_samples
    from stages.write_mcap import write_corrected_mcap
    from stages.write_rerun import write_rrd

    warnings.simplefilter("ignore")
    n = int(minutes * 60 * RATE_HZ)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(keep or tmp)
        work.mkdir(parents=True, exist_ok=True)
        src = work / f"scale_{n}.mcap"  # the file of bench/scale.py (shared with --keep)
        if not src.exists():
            make_recording(src, n)
        rec = read_recording(src)
        cal = analyse_recording(src, ProcessOptions(diagnose=False, scale_samples=0)
                                ).need_calibration()
        rs = restore_samples(rec, cal)
        out_mcap, out_rrd = work / "bench_write.corrected.mcap", work / "bench_write.rrd"
        load = os.getloadavg()[0]

        t_mcap = statistics.median(
            timed(write_corrected_mcap, rec, cal, out_mcap, restored=rs) for _ in range(repeat))
        chunks = chunk_contents(out_mcap)
        raw_mcap = sum(len(c) for c in chunks)
        size_mcap = out_mcap.stat().st_size
        c_mcap = statistics.median(zstd_seconds(chunks) for _ in range(repeat))
        del chunks

        times_rrd = []
        for _ in range(repeat):
            cap = SendCapture()  # the last run's columns are kept
            with cap:
                times_rrd.append(timed(write_rrd, rec, cal, out_rrd, restored=rs))
        t_rrd = statistics.median(times_rrd)
        size_rrd = out_rrd.stat().st_size
        frames = cap.frames()
        raw_rrd = sum(len(f) for f in frames)
        c_rrd = statistics.median(zstd_seconds(frames) for _ in range(repeat))
        del frames
        floor = statistics.median(cap.resend(work / "bench_floor.rrd") for _ in range(repeat))
        for p in (out_mcap, out_rrd, work / "bench_floor.rrd"):
            p.unlink(missing_ok=True)
    load = max(load, os.getloadavg()[0])
    print(f"\noutputs of process on {n} + {n} messages ({minutes:.0f} min at {RATE_HZ:.0f} Hz), "
          f"medians of {repeat}; load average {load:.1f}")
    print(f"{'':<44} {'ours_s':>7} {'ceiling_s':>9} {'ratio':>6}   bytes in -> file")
    print(f"{'corrected MCAP (write_corrected_mcap)':<44} {t_mcap:7.2f} {c_mcap:9.2f} "
          f"{t_mcap / c_mcap:5.2f}x   {raw_mcap / 1e6:,.0f} MB -> {size_mcap / 1e6:,.0f} MB")
    print(f"{'rerun recording (write_rrd)':<44} {t_rrd:7.2f} {c_rrd:9.2f} "
          f"{t_rrd / c_rrd:5.2f}x   {raw_rrd / 1e6:,.0f} MB -> {size_rrd / 1e6:,.0f} MB")
    print(f"{'  rerun floor (send_columns + flush alone)':<44} {floor:7.2f} {c_rrd:9.2f} "
          f"{floor / c_rrd:5.2f}x   ours / floor {t_rrd / floor:.2f}x")
    print(f"ceiling: zstd level {ZSTD_LEVEL}, one thread, the same bytes; target ours / "
          "ceiling <= 2")
    label = f"{minutes:.0f} min"
    record("write", f"write_corrected_mcap {label}", t_mcap, "s", reference=c_mcap,
           ratio=t_mcap / c_mcap)
    record("write", f"write_rrd {label}", t_rrd, "s", reference=c_rrd, ratio=t_rrd / c_rrd)
    record("write", f"rerun send_columns+flush floor {label}", floor, "s", reference=c_rrd,
           ratio=floor / c_rrd)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=120.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--keep", default=None, help="folder to keep the recording in")
    ap.add_argument("--skip-ros2", action="store_true", help="only part 2 (the ceilings)")
    args = ap.parse_args()
    if not args.skip_ros2:
        part_ros2()
    part_outputs(args.minutes, args.repeat, args.keep)
    return 0


if __name__ == "__main__":
    sys.exit(main())

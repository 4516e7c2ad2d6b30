"""Ingest benchmark: our vectorised reader against mcap_ros2's per-message decoder.

Writes, in a temporary folder, 1M sensor_msgs/MagneticField and 1M sensor_msgs/Imu messages
interleaved by log time as a logger writes them (zstd chunks, message indexes, summary),
then reads the same file with ``pipeline.io.mcap_read.read_recording`` (median of 3 runs), with
mcap's ``iter_decoded_messages`` using mcap_ros2's decoder (one run), and the ceiling: reading
the file and zstd-decompressing every chunk, nothing decoded (median of 3). The ceiling's runs
and ours alternate, so that both see the same load from other work on a shared machine (the
ratio is what is compared; the seconds move with the load). Prints messages/s,
the ratio to mcap_ros2 (target, issue 8: at least 30x) and our speed as a fraction of the
ceiling (target, issue 18: at least 50 %).
Run by ``make bench``; not a test.
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

N = int(os.environ.get("BENCH_INGEST_N", "1000000"))


def make_file(path: Path, n: int) -> None:
    rng = np.random.default_rng(1)
    t0 = 1_700_000_000 * 1_000_000_000
    t_mag = t0 + np.arange(n, dtype=np.int64) * 5_000_000  # 200 Hz
    t_att = t0 + 1_300_000 + np.arange(n, dtype=np.int64) * 5_000_000
    mag_T = (np.array([2e-5, 3e-5, -4e-5]) + 1e-7 * rng.standard_normal((n, 3)))
    yaw = np.linspace(0, 40 * np.pi, n)
    q = np.stack([np.zeros(n), np.zeros(n), np.sin(yaw / 2), np.cos(yaw / 2)], -1)
    try:
        from pipeline.io.mcap_write import write_recording
    except ImportError:
        write_recording = None
    if write_recording is not None:
        write_recording(path, mag_t_ns=t_mag, mag_nT=mag_T * 1e9, attitude_t_ns=t_att,
                        q_enu_body=q, mag_log_delay_ns=200_000, attitude_log_delay_ns=900_000)
        return
    # fallback: the WRITER's encoders and mcap's own writer, one message at a time
    from mcap.writer import CompressionType, Writer

    from pipeline.io.messages import encode, schema_for

    d_mag, o_mag = encode("sensor_msgs/msg/MagneticField", t_mag, {"mag_T": mag_T}, "mag")
    d_att, o_att = encode("sensor_msgs/msg/Imu", t_att, {"q_xyzw": q}, "body")
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start("ros2", "bench")
        ids = []
        for typ in ("sensor_msgs/msg/MagneticField", "sensor_msgs/msg/Imu"):
            name, enc, data, menc = schema_for(typ)
            sid = w.register_schema(name, enc, data)
            ids.append(w.register_channel("/mag" if "Mag" in typ else "/imu", menc, sid))
        log = np.concatenate([t_mag + 200_000, t_att + 900_000])
        order = np.argsort(log, kind="stable")
        mb, ab = d_mag.tobytes(), d_att.tobytes()
        for k in order.tolist():
            if k < n:
                w.add_message(ids[0], int(log[k]), mb[o_mag[k]:o_mag[k + 1]], int(log[k]))
            else:
                i = k - n
                w.add_message(ids[1], int(log[k]), ab[o_att[i]:o_att[i + 1]], int(log[k]))
        w.finish()


def read_and_decompress(path: Path) -> int:
    """The ceiling: read the file, zstd-decompress every chunk; return the bytes inflated."""
    import struct

    import zstandard
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        data = fh.read()
        fh.seek(0)
        summary = make_reader(fh).get_summary()
    assert summary is not None
    dctx = zstandard.ZstdDecompressor()
    total = 0
    for ci in summary.chunk_indexes:
        o = ci.chunk_start_offset + 9  # opcode, record length
        uncompressed = struct.unpack_from("<Q", data, o + 16)[0]
        o += 32 + struct.unpack_from("<I", data, o + 28)[0]  # compression name
        n = struct.unpack_from("<Q", data, o)[0]
        total += len(dctx.decompress(data[o + 8 : o + 8 + n], max_output_size=uncompressed))
    return total


def main() -> int:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from pipeline.io.mcap_read import read_recording

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.mcap"
        t = time.perf_counter()
        make_file(path, N)
        t_gen = time.perf_counter() - t
        total = 2 * N
        ours = []
        ceiling = []
        for _ in range(3):
            t = time.perf_counter()
            read_and_decompress(path)
            ceiling.append(time.perf_counter() - t)
            t = time.perf_counter()
            rec = read_recording(path)
            ours.append(time.perf_counter() - t)
            assert len(rec.mag) == N and len(rec.attitude) == N
        t = time.perf_counter()
        k = 0
        with open(path, "rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for _s, _c, _m, _ros in reader.iter_decoded_messages(log_time_order=False):
                k += 1
        theirs = time.perf_counter() - t
        assert k == total
        t_ours = statistics.median(ours)
        t_ceiling = statistics.median(ceiling)
        size_mb = path.stat().st_size / 1e6
    print(f"file: {N} magnetometer + {N} attitude messages, {size_mb:.0f} MB "
          f"(generated in {t_gen:.1f} s)")
    print(f"{'reader':<40} {'time_s':>8} {'msgs/s':>12}")
    print(f"{'pipeline.io.mcap_read.read_recording':<40} {t_ours:8.2f} {total / t_ours:12,.0f}")
    print(f"{'mcap_ros2 iter_decoded_messages':<40} {theirs:8.2f} {total / theirs:12,.0f}")
    print(f"{'ceiling: read + zstd-decompress':<40} {t_ceiling:8.2f} {total / t_ceiling:12,.0f}")
    print(f"ours at {t_ceiling / t_ours:.0%} of the ceiling (target >= 50 %)")
    print(f"ratio: {theirs / t_ours:.1f}x (target >= 30x); load average {os.getloadavg()[0]:.1f}")
    from results import record

    record("ingest", f"read_recording {total} messages", t_ours, "s", reference=theirs,
           ratio=theirs / t_ours)
    record("ingest", "fraction of the read-and-decompress ceiling", t_ceiling / t_ours, "1",
           reference=t_ceiling, ratio=t_ceiling / t_ours)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark: corrected-MCAP writing, magalign vs mcap_ros2 ``Writer.write_message``.

200k ``sensor_msgs/msg/MagneticField`` messages (one frame_id) are encoded and written with
zstd chunks of 1 MiB by both writers, in the same run; medians of several runs. Target
(issues 5 and 8): magalign at least 10x faster.
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

from mcap_ros2.writer import Writer as Ros2Writer  # noqa: E402

from pipeline.io.mcap_write import McapColumnWriter  # noqa: E402
from pipeline.io.messages import encode, schema_for  # noqa: E402

N = 200_000
TYPE = "sensor_msgs/msg/MagneticField"


def ours(path: Path, t_ns: np.ndarray, mag_T: np.ndarray) -> None:
    name, s_enc, s_data, m_enc = schema_for(TYPE)
    with McapColumnWriter(path, compression="zstd") as w:
        cid = w.add_channel("/mag", m_enc, w.add_schema(name, s_enc, s_data))
        data, off = encode(TYPE, t_ns, {"mag_T": mag_T}, "mag")
        w.add_messages(cid, t_ns, data, off)


def theirs(path: Path, t_ns: np.ndarray, mag_T: np.ndarray) -> None:
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


def timed(fn, *args) -> float:
    t0 = time.perf_counter()
    fn(*args)
    return time.perf_counter() - t0


def main() -> None:
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


if __name__ == "__main__":
    main()

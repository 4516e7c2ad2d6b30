"""Seeded mutation fuzzing of MCAP recordings (issue 16).

Small valid recordings, one per reader path, are damaged byte by byte the way disks, copies
and crashing loggers damage files: bits flipped, runs of bytes zeroed, the file cut short,
a piece of the file copied over another place or inserted into it, and the length field
of a record replaced by a random value. Every damaged file is a pure function of
``(base, seed)``, so a failing case is reproduced from its name alone.

Reader paths covered by the bases (see ``pipeline/io/mcap_read.py``):

- ``indexed``: the project's writer, zstd chunks of 4 KiB with message indexes;
- ``unindexed_lz4``: mcap's writer, lz4 chunks without message indexes (the reader walks
  the records inside each chunk);
- ``unchunked``: mcap's writer, messages at the top level of the file (what a
  streaming, non-seeking writer produces);
- ``json``: JSON-encoded magalign channels in zstd chunks;
- ``simulated``: the simulator's own output, one large chunk (a cut tears it: the torn
  chunk recovery path).

The module is imported by tests as ``fuzz_mcap`` (``tests/`` is on ``sys.path``).
"""

from __future__ import annotations

import hashlib
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np

MAGIC = b"\x89MCAP0\r\n"

#: base recording name -> writer ``f(folder) -> path``; filled below
BASES: dict[str, Callable[[Path], Path]] = {}

#: mutation operators, by name; each ``f(data, rng) -> bytes``
MUTATIONS: dict[str, Callable[[bytes, np.random.Generator], bytes]] = {}


def _base(f: Callable[[Path], Path]) -> Callable[[Path], Path]:
    BASES[f.__name__.removeprefix("base_")] = f
    return f


def _mutation(f: Callable[[bytes, np.random.Generator], bytes]):
    MUTATIONS[f.__name__.removeprefix("mut_")] = f
    return f


# --------------------------------------------------------------------------- base recordings
def _streams():
    import corpus

    return corpus.streams()


@_base
def base_indexed(folder: Path) -> Path:
    """The corpus' chunked recording: zstd, 4 KiB chunks, message indexes."""
    import corpus

    return corpus.valid_chunked(folder)


@_base
def base_unindexed_lz4(folder: Path) -> Path:
    """lz4 chunks with no message index records (the reader must walk each chunk)."""
    from mcap.writer import CompressionType, IndexType

    return _write_plain(folder / "unindexed_lz4.mcap", use_chunking=True,
                        compression=CompressionType.LZ4, index_types=IndexType.NONE)


@_base
def base_unchunked(folder: Path) -> Path:
    """Messages at the top level of the file, no chunks."""
    from mcap.writer import CompressionType, IndexType

    return _write_plain(folder / "unchunked.mcap", use_chunking=False,
                        compression=CompressionType.NONE, index_types=IndexType.ALL)


@_base
def base_json(folder: Path) -> Path:
    """JSON channels (``magalign.Magnetometer``, ``magalign.AttitudeQuaternion``)."""
    from pipeline.io.mcap_write import write_recording

    s = _streams()
    return write_recording(folder / "json.mcap", mag_t_ns=s.mag_t_ns, mag_nT=s.mag_nT,
                           attitude_t_ns=s.att_t_ns, q_enu_body=s.q_enu_body,
                           mag_type="magalign.Magnetometer",
                           attitude_type="magalign.AttitudeQuaternion",
                           mag_log_delay_ns=2_000_000, attitude_log_delay_ns=2_000_000,
                           chunk_size=4096)


@_base
def base_simulated(folder: Path) -> Path:
    """The simulator's output (NovAtel INSPVA attitude, one chunk)."""
    import corpus

    return corpus.valid(folder)


def _write_plain(path: Path, *, use_chunking: bool, compression, index_types) -> Path:
    """Magnetometer and IMU streams through mcap's own Writer, interleaved by log time."""
    from _reader_fixtures import DEFS
    from mcap.writer import Writer
    from mcap_ros2._dynamic import serialize_dynamic

    s = _streams()
    streams = [("/mag", "sensor_msgs/msg/MagneticField", s.mag_t_ns, s.mag_log_ns),
               ("/attitude", "sensor_msgs/msg/Imu", s.att_t_ns, s.att_log_ns)]
    events = sorted((int(log[i]), k, i) for k, (_, _, _, log) in enumerate(streams)
                    for i in range(len(log)))
    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=4096, compression=compression, index_types=index_types,
                   use_chunking=use_chunking)
        w.start("ros2", "fuzz")
        ids, enc = [], []
        for topic, name, _, _ in streams:
            sid = w.register_schema(name, "ros2msg", DEFS[name].encode())
            ids.append(w.register_channel(topic, "cdr", sid))
            enc.append(serialize_dynamic(name, DEFS[name])[name])
        for log, k, i in events:
            t = int(streams[k][2][i])
            stamp = {"sec": t // 1_000_000_000, "nanosec": t % 1_000_000_000}
            hdr = {"stamp": stamp, "frame_id": "mag" if k == 0 else "body"}
            if k == 0:
                v = s.mag_nT[i] * 1e-9
                msg = {"header": hdr, "magnetic_field": dict(zip("xyz", map(float, v),
                                                                 strict=True)),
                       "magnetic_field_covariance": [0.0] * 9}
            else:
                z3 = {"x": 0.0, "y": 0.0, "z": 0.0}
                msg = {"header": hdr,
                       "orientation": dict(zip("xyzw", map(float, s.q_enu_body[i]),
                                               strict=True)),
                       "orientation_covariance": [0.0] * 9, "angular_velocity": z3,
                       "angular_velocity_covariance": [0.0] * 9,
                       "linear_acceleration": z3, "linear_acceleration_covariance": [0.0] * 9}
            w.add_message(ids[k], log, enc[k](msg), log, sequence=i)
        w.finish()
    return path


# --------------------------------------------------------------------------- mutations
def _records(data: bytes) -> list[tuple[int, int]]:
    """``(offset, content length)`` of the top-level records that frame correctly."""
    out, pos = [], len(MAGIC)
    while pos + 9 <= len(data):
        _, n = struct.unpack_from("<BQ", data, pos)
        if pos + 9 + n > len(data):
            break
        out.append((pos, n))
        pos += 9 + n
    return out


@_mutation
def mut_bitflip(data: bytes, rng: np.random.Generator) -> bytes:
    """Flip 1 to 16 random bits."""
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 17))):
        i = int(rng.integers(0, len(b)))
        b[i] ^= 1 << int(rng.integers(0, 8))
    return bytes(b)


@_mutation
def mut_zero_run(data: bytes, rng: np.random.Generator) -> bytes:
    """Zero a run of 1 byte to 4 KiB (a bad sector, a sparse file)."""
    n = int(rng.integers(1, 4097))
    i = int(rng.integers(0, max(1, len(data) - 1)))
    return data[:i] + bytes(min(n, len(data) - i)) + data[i + n:]


@_mutation
def mut_cut(data: bytes, rng: np.random.Generator) -> bytes:
    """Cut the file at a random byte (a logger crash, an interrupted copy)."""
    return data[: int(rng.integers(0, len(data)))]


@_mutation
def mut_splice(data: bytes, rng: np.random.Generator) -> bytes:
    """Copy a random piece of the file over, or into, another place."""
    n = int(rng.integers(1, min(8192, len(data))))
    src = int(rng.integers(0, len(data) - n))
    dst = int(rng.integers(0, len(data)))
    piece = data[src : src + n]
    if rng.random() < 0.5:
        return data[:dst] + piece + data[dst:]  # inserted
    return data[:dst] + piece + data[dst + n:]  # overwritten


@_mutation
def mut_record_length(data: bytes, rng: np.random.Generator) -> bytes:
    """Replace the length field of a random top-level record by a random value."""
    recs = _records(data)
    if not recs:
        return mut_bitflip(data, rng)
    off, n = recs[int(rng.integers(0, len(recs)))]
    choice = int(rng.integers(0, 5))
    new = [0, max(0, n - int(rng.integers(1, 64))), n + int(rng.integers(1, 64)),
           int(rng.integers(0, 1 << 32)), int(rng.integers(0, 1 << 63))][choice]
    return data[: off + 1] + struct.pack("<Q", new) + data[off + 9:]


@_mutation
def mut_mixed(data: bytes, rng: np.random.Generator) -> bytes:
    """Two or three of the other mutations one after the other."""
    ops = [f for k, f in MUTATIONS.items() if k != "mixed"]
    for _ in range(int(rng.integers(2, 4))):
        data = ops[int(rng.integers(0, len(ops)))](data, rng)
        if len(data) < 16:
            break
    return data


# --------------------------------------------------------------------------- cases
def case_name(index: int, seed: int = 0) -> tuple[str, str, int]:
    """The ``(base, mutation, case seed)`` of damaged file number ``index`` of a run."""
    bases, muts = sorted(BASES), sorted(MUTATIONS)
    base = bases[index % len(bases)]
    mut = muts[(index // len(bases)) % len(muts)]
    return base, mut, seed * 1_000_003 + index


def damage(data: bytes, mutation: str, case_seed: int) -> bytes:
    """Apply ``mutation`` to ``data`` with a generator seeded by ``case_seed``."""
    rng = np.random.default_rng(case_seed)
    return MUTATIONS[mutation](data, rng)


def make_cases(base_files: dict[str, Path], folder: Path, n: int, seed: int = 0
               ) -> list[Path]:
    """Write ``n`` damaged files into ``folder``; names say base, mutation and case seed."""
    folder.mkdir(parents=True, exist_ok=True)
    raw = {k: p.read_bytes() for k, p in base_files.items()}
    out = []
    for i in range(n):
        base, mut, cs = case_name(i, seed)
        p = folder / f"{i:04d}_{base}_{mut}_{cs}.mcap"
        p.write_bytes(damage(raw[base], mut, cs))
        out.append(p)
    return out


def sha256(path: Path) -> str:
    """SHA-256 of a file's bytes (inputs must be unchanged by every command)."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


# --------------------------------------------------------------------------- running
class Hang(Exception):
    """A command ran longer than the hang guard."""


def run_cli(argv: list[str], timeout_s: float = 30.0) -> tuple[int | str, str, str]:
    """Run ``magalign argv`` in this process: ``(status, stdout, stderr)``.

    ``status`` is the exit status, ``"crash"`` when an exception escaped the command
    (its traceback is the stderr), or ``"hang"`` when it ran longer than ``timeout_s``.
    ``process`` runs its recordings in this process (a serial executor), so a crash in a
    worker is seen as such.
    """
    import contextlib
    import io
    import signal
    import traceback

    import pipeline.app.executors as ex
    from pipeline.app.cli import main

    out, err = io.StringIO(), io.StringIO()

    def alarm(*_):
        raise Hang(f"over {timeout_s} s")

    saved_make, saved_alarm = ex.make_executor, signal.signal(signal.SIGALRM, alarm)
    ex.make_executor = lambda **kw: ex.SerialExecutor()
    signal.setitimer(signal.ITIMER_REAL, timeout_s)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                status: int | str = main(argv)
            except SystemExit as exc:
                status = exc.code if isinstance(exc.code, int) else 2
            except Hang:
                status = "hang"
            except Exception:  # noqa: BLE001 - the finding
                status = "crash"
                err.write(traceback.format_exc())
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, saved_alarm)
        ex.make_executor = saved_make
    return status, out.getvalue(), err.getvalue()

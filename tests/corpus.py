"""A corpus of bad inputs for the whole-program robustness tests (issue 9).

Every generator writes one damaged or wrong input into a folder and returns its path. They
start from one small valid simulated recording (``pipeline.app.simulate``, 20 s of the
multi-axis calibration manoeuvre at 20 Hz) and damage it the way survey loggers, disks and
people do: files cut short, bytes flipped, channels missing or doubled, values in the wrong
unit, stamps out of order, a sensor stuck or clipped, a platform that never turned.

Hand-made variants are written with the project's own writer (``pipeline.io.mcap_write``,
``pipeline.io.messages``); byte-level damage is done on a file whose records are located with
:func:`records` (the MCAP record framing: opcode u8, length u64, content).

The module is imported by tests as ``corpus`` (pytest puts ``tests/`` on ``sys.path``
because ``tests/`` is not a package).
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.app.simulate import Simulated, scenario_from_dict, simulate, write_simulated
from pipeline.io import messages
from pipeline.io.mcap_write import McapColumnWriter, write_recording

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_CHUNK, OP_DATA_END = 0x01, 0x02, 0x06, 0x0F

#: Chunk size of the corpus files (bytes, uncompressed): small, so a 20 s recording spans
#: tens of chunks and losing one of them loses a small part of it.
CHUNK_SIZE = 4096

#: The valid base recording: the multi-axis manoeuvre of ``pipeline/scenarios/multiaxis.toml``
#: shortened to 20 s at 20 Hz (400 samples per stream, every rotation axis observable).
BASE_SCENARIO: dict = {
    "name": "corpus_base",
    "seed": 9,
    "timing": {"start": "2026-01-01T00:00:00Z", "duration_s": 20.0, "mag_rate_hz": 20.0,
               "attitude_rate_hz": 20.0},
    "motion": {"profile": "multiaxis", "yaw_rate_deg_s": 36.0, "yaw_amplitude_deg": 20.0,
               "yaw_period_s": 17.0, "pitch_amplitude_deg": 25.0, "pitch_period_s": 7.0,
               "roll_amplitude_deg": 25.0, "roll_period_s": 11.0},
    "field": {"enu_nT": [500.0, 20000.0, -45000.0]},
    "sensor": {"misalignment_rotvec_deg": [1.2, -1.0, 1.2]},
    "noise": {"mag_sigma_nT": 0.5, "heading_sigma_deg": 0.02, "pitch_roll_sigma_deg": 0.01},
}

#: A valid scenario file (the base scenario in TOML); bad variants change one line of it.
SCENARIO_TOML = """\
name = "corpus_base"
seed = 9

[timing]
start = "2026-01-01T00:00:00Z"
duration_s = 20.0
mag_rate_hz = 20.0
attitude_rate_hz = 20.0

[motion]
profile = "multiaxis"

[field]
enu_nT = [500.0, 20000.0, -45000.0]

[sensor]
misalignment_rotvec_deg = [1.2, -1.0, 1.2]
"""


@functools.lru_cache(maxsize=1)
def base_sim() -> Simulated:
    """The simulated base recording (computed once per process)."""
    return simulate(scenario_from_dict(BASE_SCENARIO, path="corpus_base"))


@dataclass
class Streams:
    """Editable copies of the base recording's columns (stamps ns, mag nT, q_enu_body)."""

    mag_t_ns: np.ndarray
    mag_nT: np.ndarray
    att_t_ns: np.ndarray
    q_enu_body: np.ndarray
    mag_log_ns: np.ndarray
    att_log_ns: np.ndarray

    def write(self, path: Path, **kw) -> Path:
        """Write as a logger would (log time given per message), small chunks."""
        return write_recording(
            path, mag_t_ns=self.mag_t_ns, mag_nT=self.mag_nT,
            attitude_t_ns=self.att_t_ns, q_enu_body=self.q_enu_body,
            mag_log_delay_ns=self.mag_log_ns - self.mag_t_ns,
            attitude_log_delay_ns=self.att_log_ns - self.att_t_ns,
            chunk_size=CHUNK_SIZE, **kw)


def streams() -> Streams:
    """Fresh copies of the base recording's columns; log time = stamp + 2 ms."""
    rec = base_sim().recording
    assert rec.attitude is not None
    return Streams(rec.mag.t_ns.copy(), rec.mag.values.copy(), rec.attitude.t_ns.copy(),
                   rec.attitude.q_enu_body.copy(), rec.mag.t_ns + 2_000_000,
                   rec.attitude.t_ns + 2_000_000)


def records(path: Path) -> list[tuple[int, int, int]]:
    """``(opcode, record offset, content length)`` of every record of an intact MCAP file."""
    b = path.read_bytes()
    out, pos = [], len(MAGIC)
    while pos + 9 <= len(b) - len(MAGIC):
        op, n = struct.unpack_from("<BQ", b, pos)
        out.append((op, pos, n))
        pos += 9 + n
    return out


def chunks(path: Path) -> list[tuple[int, int]]:
    """``(record offset, content length)`` of every Chunk record."""
    return [(off, n) for op, off, n in records(path) if op == OP_CHUNK]


def _chunk_fields(b: bytes, off: int) -> tuple[int, int, int]:
    """Offsets of a chunk's uncompressed_crc field and of its compressed records, and length."""
    c = off + 9
    crc_at = c + 24  # message_start_time, message_end_time, uncompressed_size (u64 each)
    slen = struct.unpack_from("<I", b, crc_at + 4)[0]
    rl_at = crc_at + 8 + slen
    rec_len = struct.unpack_from("<Q", b, rl_at)[0]
    return crc_at, rl_at + 8, rec_len


def _base_file(folder: Path, name: str) -> Path:
    return streams().write(folder / name)


# ------------------------------------------------------------------ valid inputs
def valid(folder: Path) -> Path:
    """The valid base recording, written by the SIMULATOR's ``write_simulated``."""
    return write_simulated(base_sim(), folder / "valid.mcap")


def valid_chunked(folder: Path) -> Path:
    """The valid base recording in small chunks (the starting point of byte damage)."""
    return _base_file(folder, "valid_chunked.mcap")


# ------------------------------------------------------------------ not an MCAP at all
def empty(folder: Path) -> Path:
    """A 0-byte file (a logger that crashed before writing anything)."""
    p = folder / "empty.mcap"
    p.write_bytes(b"")
    return p


def text_file(folder: Path) -> Path:
    """A text file given an .mcap name."""
    p = folder / "notes.mcap"
    p.write_text("survey line 3, operator notes\nweather: fine\n" * 20)
    return p


def png_file(folder: Path) -> Path:
    """A PNG image (only its signature and IHDR) given an .mcap name."""
    p = folder / "picture.mcap"
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00\x00\x00\rIHDR" + bytes(64))
    return p


# ------------------------------------------------------------------ cut files
def cut_in_header(folder: Path) -> Path:
    """Cut inside the Header record (magic and a few bytes)."""
    src = _base_file(folder, "_src_header.mcap")
    p = folder / "cut_header.mcap"
    p.write_bytes(src.read_bytes()[: len(MAGIC) + 5])
    src.unlink()
    return p


def cut_in_chunk(folder: Path) -> Path:
    """Cut in the middle of a chunk about 60 % into the file: the rest is lost."""
    src = _base_file(folder, "_src_chunk.mcap")
    ch = chunks(src)
    off, n = ch[int(len(ch) * 0.6)]
    p = folder / "cut_chunk.mcap"
    p.write_bytes(src.read_bytes()[: off + 9 + n // 2])
    src.unlink()
    return p


def cut_before_footer(folder: Path) -> Path:
    """Cut just before the Footer record: every chunk and the summary are intact."""
    src = _base_file(folder, "_src_footer.mcap")
    off = next(o for op, o, _ in records(src) if op == OP_FOOTER)
    p = folder / "cut_footer.mcap"
    p.write_bytes(src.read_bytes()[:off])
    src.unlink()
    return p


def cut_at_data_end(folder: Path) -> Path:
    """Cut after the last chunk: the summary section and footer are lost (logger crash)."""
    src = _base_file(folder, "_src_dataend.mcap")
    off = next(o for op, o, _ in records(src) if op == OP_DATA_END)
    p = folder / "cut_data_end.mcap"
    p.write_bytes(src.read_bytes()[:off])
    src.unlink()
    return p


# ------------------------------------------------------------------ damaged chunks
def bad_crc(folder: Path) -> Path:
    """One chunk in the middle of the file has a wrong uncompressed CRC."""
    p = _base_file(folder, "bad_crc.mcap")
    b = bytearray(p.read_bytes())
    ch = chunks(p)
    crc_at, _, _ = _chunk_fields(b, ch[len(ch) // 2][0])
    b[crc_at] ^= 0xFF
    p.write_bytes(bytes(b))
    return p


def undecompressable(folder: Path) -> Path:
    """One chunk's zstd payload has its frame header destroyed: it does not decompress."""
    p = _base_file(folder, "undecompressable.mcap")
    b = bytearray(p.read_bytes())
    ch = chunks(p)
    _, rec_at, rec_len = _chunk_fields(b, ch[len(ch) // 2][0])
    assert rec_len > 16
    b[rec_at: rec_at + 8] = b"\xde\xad\xbe\xef" * 2
    p.write_bytes(bytes(b))
    return p


# ------------------------------------------------------------------ channels
def _write_streams(path: Path, items: list[tuple[str, str, np.ndarray, dict]]) -> Path:
    """Write ``(msg_type, topic, t_ns, fields)`` streams with the project's column writer."""
    with McapColumnWriter(path, profile="ros2", chunk_size=CHUNK_SIZE) as w:
        for msg_type, topic, t, fields in items:
            name, s_enc, s_data, m_enc = messages.schema_for(msg_type)
            cid = w.add_channel(topic, m_enc, w.add_schema(name, s_enc, s_data))
            data, off = messages.encode(msg_type, t, fields, "mag")
            w.add_messages(cid, t + 2_000_000, data, off)
    return path


def missing_mag(folder: Path) -> Path:
    """Only an attitude channel."""
    s = streams()
    return _write_streams(folder / "no_mag.mcap", [
        ("sensor_msgs/msg/Imu", "/attitude", s.att_t_ns, {"q_xyzw": s.q_enu_body})])


def missing_attitude(folder: Path) -> Path:
    """Only a magnetometer channel."""
    s = streams()
    return write_recording(folder / "no_attitude.mcap", mag_t_ns=s.mag_t_ns, mag_nT=s.mag_nT,
                           chunk_size=CHUNK_SIZE)


def two_mags(folder: Path) -> Path:
    """Two magnetometer channels (``/mag_a``, ``/mag_b``) and one attitude channel."""
    s = streams()
    return _write_streams(folder / "two_mags.mcap", [
        ("sensor_msgs/msg/MagneticField", "/mag_a", s.mag_t_ns, {"mag_T": s.mag_nT * 1e-9}),
        ("sensor_msgs/msg/MagneticField", "/mag_b", s.mag_t_ns, {"mag_T": s.mag_nT * 1e-9}),
        ("sensor_msgs/msg/Imu", "/attitude", s.att_t_ns, {"q_xyzw": s.q_enu_body})])


#: The unknown message type of :func:`unknown_schema`.
UNKNOWN_TYPE = "acme_msgs/msg/Fluxgate3"


def unknown_schema(folder: Path) -> Path:
    """The magnetometer on ``/mag`` is an unknown vendor type; the attitude is a ROS Imu."""
    s = streams()
    p = folder / "unknown_schema.mcap"
    n = len(s.mag_t_ns)
    rows = np.zeros(n, dtype=[("hdr", "u1", 4), ("v", "<f8", 3)])
    rows["hdr"] = (0, 1, 0, 0)  # CDR little-endian encapsulation
    rows["v"] = s.mag_nT
    data = rows.view(np.uint8).reshape(-1)
    off = np.arange(n + 1, dtype=np.int64) * rows.dtype.itemsize
    with McapColumnWriter(p, profile="ros2", chunk_size=CHUNK_SIZE) as w:
        sid = w.add_schema(UNKNOWN_TYPE, "ros2msg", b"float64 x\nfloat64 y\nfloat64 z\n")
        w.add_messages(w.add_channel("/mag", "cdr", sid), s.mag_t_ns, data, off)
        name, s_enc, s_data, m_enc = messages.schema_for("sensor_msgs/msg/Imu")
        cid = w.add_channel("/attitude", m_enc, w.add_schema(name, s_enc, s_data))
        d, o = messages.encode("sensor_msgs/msg/Imu", s.att_t_ns, {"q_xyzw": s.q_enu_body})
        w.add_messages(cid, s.att_t_ns, d, o)
    return p


# ------------------------------------------------------------------ values
def nan_inf(folder: Path) -> Path:
    """5 NaN and 5 Inf magnetometer samples, 4 NaN attitude samples."""
    s = streams()
    s.mag_nT[[20, 60, 100, 140, 180], 0] = np.nan
    s.mag_nT[[30, 70, 110, 150, 190], 2] = np.inf
    s.q_enu_body[[25, 75, 125, 175], 3] = np.nan
    return s.write(folder / "nan_inf.mcap")


def bad_quaternions(folder: Path) -> Path:
    """3 zero quaternions and 10 of norm 1.02 in the attitude channel."""
    s = streams()
    s.q_enu_body[[40, 140, 240]] = 0.0
    s.q_enu_body[300:310] *= 1.02
    return s.write(folder / "bad_quaternions.mcap")


def stamps_backwards(folder: Path) -> Path:
    """Pairs of magnetometer stamps swapped (received in order, stamped out of order)."""
    s = streams()
    for k in range(50, 350, 50):
        s.mag_t_ns[[k, k + 1]] = s.mag_t_ns[[k + 1, k]]
        s.mag_nT[[k, k + 1]] = s.mag_nT[[k + 1, k]]
    return s.write(folder / "stamps_backwards.mcap")


def stamps_duplicated(folder: Path) -> Path:
    """Six magnetometer samples carry the stamp of the sample before them."""
    s = streams()
    for k in range(60, 360, 50):
        s.mag_t_ns[k] = s.mag_t_ns[k - 1]
    return s.write(folder / "stamps_duplicated.mcap")


def stamps_jump_hours(folder: Path) -> Path:
    """Four magnetometer stamps 3 h ahead of their receive time (a clock glitch)."""
    s = streams()
    s.mag_t_ns[[100, 101, 250, 251]] += 3 * 3600 * 10**9
    return s.write(folder / "stamps_jump.mcap")


def long_gap(folder: Path) -> Path:
    """Both streams stop for 7 s in the middle (a logger stall; 140 samples of each lost)."""
    s = streams()
    km = (s.mag_t_ns < s.mag_t_ns[100]) | (s.mag_t_ns >= s.mag_t_ns[240])
    ka = (s.att_t_ns < s.mag_t_ns[100]) | (s.att_t_ns >= s.mag_t_ns[240])
    s.mag_t_ns, s.mag_nT, s.mag_log_ns = s.mag_t_ns[km], s.mag_nT[km], s.mag_log_ns[km]
    s.att_t_ns, s.q_enu_body, s.att_log_ns = s.att_t_ns[ka], s.q_enu_body[ka], s.att_log_ns[ka]
    return s.write(folder / "long_gap.mcap")


def microtesla_as_tesla(folder: Path) -> Path:
    """A driver wrote microtesla numbers into the tesla field (REP-145): 1e6 x too large."""
    s = streams()
    s.mag_nT = s.mag_nT * 1e6  # 48 uT written as 48 T reads as 4.8e10 nT
    return s.write(folder / "microtesla.mcap")


def stuck(folder: Path) -> Path:
    """Every magnetometer sample identical (a stuck sensor or driver)."""
    s = streams()
    s.mag_nT[:] = s.mag_nT[0]
    return s.write(folder / "stuck.mcap")


def saturated(folder: Path) -> Path:
    """Axis y clipped at a rail below most of its values (60 % of samples on the rail)."""
    s = streams()
    rail = float(np.quantile(s.mag_nT[:, 1], 0.6))
    s.mag_nT[:, 1] = np.maximum(s.mag_nT[:, 1], rail)
    return s.write(folder / "saturated.mcap")


def partly_saturated(folder: Path) -> Path:
    """Axis y clipped at a rail for 30 % of the samples (an overrange during the turns)."""
    s = streams()
    rail = float(np.quantile(s.mag_nT[:, 1], 0.3))
    s.mag_nT[:, 1] = np.maximum(s.mag_nT[:, 1], rail)
    return s.write(folder / "partly_saturated.mcap")


def static(folder: Path) -> Path:
    """The platform never turns: constant attitude, constant field plus sensor noise."""
    s = streams()
    s.q_enu_body[:] = s.q_enu_body[0]
    rng = np.random.default_rng(1)
    s.mag_nT = base_sim().recording.mag.values[0] + rng.normal(0.0, 0.5, s.mag_nT.shape)
    return s.write(folder / "static.mcap")


def too_short(folder: Path) -> Path:
    """Five samples of each stream (a quarter of a second)."""
    s = streams()
    return write_recording(folder / "too_short.mcap", mag_t_ns=s.mag_t_ns[:5],
                           mag_nT=s.mag_nT[:5], attitude_t_ns=s.att_t_ns[:5],
                           q_enu_body=s.q_enu_body[:5])


# ------------------------------------------------------------------ configuration
def scenario_bad_key(folder: Path) -> Path:
    """A scenario whose [timing] table has a misspelt key (``mag_rate`` for ``mag_rate_hz``)."""
    p = folder / "bad_key.toml"
    p.write_text(SCENARIO_TOML.replace("mag_rate_hz = 20.0", "mag_rate = 20.0"))
    return p


def scenario_bad_value(folder: Path) -> Path:
    """A scenario whose ``timing.duration_s`` is a string."""
    p = folder / "bad_value.toml"
    p.write_text(SCENARIO_TOML.replace("duration_s = 20.0", 'duration_s = "twenty"'))
    return p


def scenario_not_toml(folder: Path) -> Path:
    """A scenario file that is Python, not TOML (configuration is data, never code)."""
    p = folder / "code.toml"
    p.write_text("import os\nos.system('echo owned')\n")
    return p


def calibration_other_format(folder: Path) -> Path:
    """A calibration JSON of another program (valid JSON, wrong format and keys)."""
    p = folder / "other_calibration.json"
    p.write_text('{"format": "acme.magcal/2", "hard_iron": [1, 2, 3], '
                 '"soft_iron": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}\n')
    return p


def calibration_not_json(folder: Path) -> Path:
    """A calibration file that is not JSON at all."""
    p = folder / "calibration_text.json"
    p.write_text("R = [[1,0,0],[0,1,0],[0,0,1]]\n")
    return p


#: Every generator, by case name.
CASES: dict[str, Callable[[Path], Path]] = {
    f.__name__: f
    for f in (
        empty, text_file, png_file, cut_in_header, cut_in_chunk, cut_before_footer,
        cut_at_data_end, bad_crc, undecompressable, missing_mag, missing_attitude, two_mags,
        unknown_schema, nan_inf, bad_quaternions, stamps_backwards, stamps_duplicated,
        stamps_jump_hours, long_gap, microtesla_as_tesla, stuck, saturated, partly_saturated,
        static, too_short,
        scenario_bad_key, scenario_bad_value, scenario_not_toml, calibration_other_format,
        calibration_not_json,
    )
}

"""READER: damaged files and bad data (issue 9 corpus), each with its intended answer."""

from __future__ import annotations

import hashlib
import warnings

import numpy as np
import pytest
from _reader_fixtures import DEFS, motion, write_ros2, write_ros2_raw
from mcap.reader import make_reader
from mcap.writer import CompressionType

from pipeline.app.cli import main
from pipeline.core.errors import (
    CorruptRecordingError,
    DataQualityError,
    NotMcapError,
    RecoveredDataWarning,
)
from pipeline.io.mcap_read import read_raw_channels, read_recording
from stages.context import Context
from stages.resample import Resample

MAG = "sensor_msgs/msg/MagneticField"
IMU = "sensor_msgs/msg/Imu"


def _file(tmp_path, n=300, compression=CompressionType.ZSTD, chunk_size=2048, name="r.mcap"):
    t, mag_T, q = motion(n)
    return write_ros2(tmp_path / name, [("/mag", MAG, DEFS[MAG], t, mag_T, ["imu"]),
                                        ("/att", IMU, DEFS[IMU], t + 2_000_000, q, ["b"])],
                      compression=compression, chunk_size=chunk_size)


def _codes(rec):
    return {p.code: p for p in rec.problems}


def _chunk_data_offsets(path):
    with open(path, "rb") as fh:
        idx = make_reader(fh).get_summary().chunk_indexes
    # chunk record: opcode, length, 3 x u64, u32 crc, compression string, u64 records length
    return [(c.chunk_start_offset + 9 + 28 + 4 + len(c.compression) + 8, c) for c in idx]


# ---------------------------------------------------------------- cut files
@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.NONE])
def test_cut_at_many_offsets(tmp_path, compression):
    p = _file(tmp_path, compression=compression)
    full = p.read_bytes()
    ref = {c.topic: c for c in read_raw_channels(p)}
    cut = tmp_path / "cut.mcap"
    last = -1
    offsets = np.unique(np.linspace(0, len(full) - 1, 50).astype(int))
    for off in offsets:
        cut.write_bytes(full[:off])
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            try:
                got = read_raw_channels(cut)
            except NotMcapError:
                assert off < 40  # only a file cut inside its header is refused
                continue
        assert any(issubclass(x.category, RecoveredDataWarning) for x in w), off
        total = 0
        for c in got:  # what is recovered is exactly the beginning of each channel
            r = ref[c.topic]
            k = len(c)
            total += k
            np.testing.assert_array_equal(c.log_time_ns, r.log_time_ns[:k])
            assert c.data.tobytes() == r.data[: r.offsets[k]].tobytes()
        assert total >= last, f"recovered count fell at offset {off}"
        last = total
    assert last > 0.8 * sum(len(c) for c in ref.values())


def test_cut_inside_chunk_reads_recording_up_to_the_cut(tmp_path):
    p = _file(tmp_path, n=400, chunk_size=1 << 20)  # one chunk: the cut tears it
    full_rec = read_recording(p)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(p.read_bytes()[: int(p.stat().st_size * 0.6)])
    with pytest.warns(RecoveredDataWarning, match="cut inside a chunk"):
        rec = read_recording(cut)
    k = len(rec.mag)
    assert 50 < k < 400
    np.testing.assert_array_equal(rec.mag.values, full_rec.mag.values[:k])
    assert {"truncated", "torn_chunk"} <= set(_codes(rec))


def test_cut_before_footer_keeps_everything(tmp_path):
    p = _file(tmp_path)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(p.read_bytes()[:-37])  # footer record and closing magic gone
    with pytest.warns(RecoveredDataWarning, match="before its footer"):
        rec = read_recording(cut)
    assert len(rec.mag) == 300 and len(rec.attitude) == 300
    assert _codes(rec)["truncated"].count == 0


@pytest.mark.parametrize("content,match", [(b"", "empty"), (b"hello world, not mcap" * 9,
                                                            "not an MCAP"),
                                           (None, "cut inside the MCAP header")])
def test_empty_not_mcap_cut_in_header(tmp_path, content, match):
    p = _file(tmp_path)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(p.read_bytes()[:20] if content is None else content)
    with pytest.raises(NotMcapError, match=match) as ei:
        read_recording(bad)
    assert str(bad) in ei.value.one_line() and ei.value.exit_code == 2


def test_cli_one_line_exit_2(tmp_path, capsys):
    bad = tmp_path / "notes.mcap"
    bad.write_text("not a recording")
    assert main(["info", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and "Traceback" not in err[0]


# ---------------------------------------------------------------- damaged chunks
def test_wrong_chunk_crc_skips_that_chunk(tmp_path):
    p = _file(tmp_path, compression=CompressionType.NONE)
    data = bytearray(p.read_bytes())
    start, c = _chunk_data_offsets(p)[2]
    data[start + 100] ^= 0xFF
    bad = tmp_path / "crc.mcap"
    bad.write_bytes(bytes(data))
    with pytest.warns(RecoveredDataWarning, match="CRC"):
        rec = read_recording(bad)
    pr = _codes(rec)["chunk_crc"]
    assert pr.count > 0 and len(rec.mag) + len(rec.attitude) == 600 - pr.count


def test_undecompressable_chunk_skipped(tmp_path):
    p = _file(tmp_path)
    data = bytearray(p.read_bytes())
    start, c = _chunk_data_offsets(p)[1]
    data[start : start + 4] = b"\x00\x00\x00\x00"  # zstd frame magic destroyed
    bad = tmp_path / "z.mcap"
    bad.write_bytes(bytes(data))
    with pytest.warns(RecoveredDataWarning, match="does not decompress"):
        rec = read_recording(bad)
    pr = _codes(rec)["chunk_undecompressable"]
    assert pr.count > 0 and len(rec.mag) + len(rec.attitude) == 600 - pr.count


def test_only_chunk_bad_is_an_error(tmp_path):
    p = _file(tmp_path, compression=CompressionType.NONE, chunk_size=1 << 20)
    data = bytearray(p.read_bytes())
    start, c = _chunk_data_offsets(p)[0]
    data[start + 500] ^= 0x55
    bad = tmp_path / "one.mcap"
    bad.write_bytes(bytes(data))
    with pytest.warns(RecoveredDataWarning), pytest.raises(CorruptRecordingError):
        read_recording(bad)


def test_input_never_modified(tmp_path):
    p = _file(tmp_path)
    h = hashlib.sha256(p.read_bytes()).hexdigest()
    read_recording(p)
    read_raw_channels(p)
    assert hashlib.sha256(p.read_bytes()).hexdigest() == h


def test_no_message_indexes_and_unchunked(tmp_path):
    t, mag_T, q = motion(200)
    for chunked in (True, False):
        p = write_ros2_raw(tmp_path / f"u{chunked}.mcap",
                           [("/mag", MAG, DEFS[MAG], t, mag_T, ["imu"]),
                            ("/att", IMU, DEFS[IMU], t, q, ["b"])], use_chunking=chunked)
        full = p.read_bytes()
        cut = tmp_path / "c.mcap"
        cut.write_bytes(full[: len(full) * 3 // 4])
        with pytest.warns(RecoveredDataWarning):
            rec = read_recording(cut)
        assert 10 < len(rec.mag) <= 200
        np.testing.assert_allclose(rec.mag.values, mag_T[: len(rec.mag)] * 1e9, rtol=1e-15)


# ---------------------------------------------------------------- bad values
def _write(tmp_path, t, mag_T, q, t_att=None, log_times=None, name="d.mcap"):
    return write_ros2(tmp_path / name, [("/mag", MAG, DEFS[MAG], t, mag_T, ["imu"]),
                                        ("/att", IMU, DEFS[IMU],
                                         t if t_att is None else t_att, q, ["b"])],
                      log_times=log_times)


def test_nan_inf_dropped(tmp_path):
    t, mag_T, q = motion(200)
    mag_T[[3, 50]] = np.nan
    mag_T[77, 1] = np.inf
    q[10] = np.nan
    rec = read_recording(_write(tmp_path, t, mag_T, q))
    assert len(rec.mag) == 197 and len(rec.attitude) == 199
    assert np.isfinite(rec.mag.values).all()
    assert [p.count for p in rec.problems if p.code == "nonfinite"] == [3, 1]


def test_zero_and_non_unit_quaternions(tmp_path):
    t, mag_T, q = motion(200)
    q[[5, 6]] = 0.0
    q[20:30] *= 1.7
    rec = read_recording(_write(tmp_path, t, mag_T, q))
    codes = _codes(rec)
    assert codes["zero_quaternion"].count == 2 and codes["non_unit_quaternion"].count == 10
    assert len(rec.attitude) == 198
    np.testing.assert_allclose(np.linalg.norm(rec.attitude.q_enu_body, axis=1), 1.0, atol=1e-12)


def test_stamps_backwards_duplicated_and_jumping(tmp_path):
    t, mag_T, q = motion(200)
    log = t + 400_000
    tm = t.copy()
    tm[[40, 41]] = tm[[41, 40]]  # backwards
    tm[90] = tm[89]  # duplicated
    tm[150] += 3 * 3600 * 10**9  # clock jump by hours; the logger's receive time is sane
    rec = read_recording(_write(tmp_path, tm, mag_T, q, log_times={0: log}))
    c = _codes(rec)
    assert c["out_of_order"].count == 1 and c["duplicate"].count == 1
    assert c["stamp_jump"].count == 1
    assert len(rec.mag) == 198 and np.all(np.diff(rec.mag.t_ns) > 0)
    assert rec.duration_s < 3


def test_long_attitude_gap_not_bridged(tmp_path):
    t, mag_T, q = motion(400)  # 100 Hz
    keep = (np.arange(400) < 150) | (np.arange(400) >= 250)  # 1 s without attitude
    rec = read_recording(_write(tmp_path, t, mag_T, q[keep], t_att=t[keep]))
    assert _codes(rec)["gap"].count == 1
    al = Resample().run(Context(recording=rec)).aligned
    assert len(al) == 400 - 100  # samples strictly inside the gap are dropped
    assert not np.isin(np.arange(150, 250), al.index).any()
    assert np.isin([149, 250], al.index).all()  # the gap's edges are attitude samples


def test_microtesla_written_as_tesla(tmp_path):
    t, mag_T, q = motion(100)
    p = _write(tmp_path, t, mag_T * 1e6, q)  # 20 uT stored as "20 T"
    with pytest.raises(DataQualityError, match="far outside") as ei:
        read_recording(p)
    assert "microtesla" in ei.value.hint and ei.value.exit_code == 2
    assert str(p) in ei.value.one_line()


def test_stuck_sensor(tmp_path):
    t, mag_T, q = motion(100)
    mag_T[:] = mag_T[0]
    with pytest.raises(DataQualityError, match="stuck"):
        read_recording(_write(tmp_path, t, mag_T, q))


def test_saturated_sensor(tmp_path):
    t, mag_T, q = motion(300)
    mag_T[:200, 0] = 30e-6  # clipped at the range limit
    with pytest.raises(DataQualityError, match="saturated"):
        read_recording(_write(tmp_path, t, mag_T, q))
    t, mag_T, q = motion(300)
    mag_T[:12, 0] = 30e-6
    rec = read_recording(_write(tmp_path, t, mag_T, q, name="s2.mcap"))
    assert _codes(rec)["saturated"].count == 12


def test_too_short(tmp_path):
    t, mag_T, q = motion(5)
    with pytest.raises(DataQualityError, match="too short"):
        read_recording(_write(tmp_path, t, mag_T, q))


# ---------------------------------------------------------------- records of newer versions
def _top_records(data: bytes) -> list[tuple[int, int, int]]:
    """``(offset, opcode, record length)`` of the top-level records after the magic."""
    import struct

    out, pos = [], 8
    while pos + 9 <= len(data):
        op, n = struct.unpack_from("<BQ", data, pos)
        out.append((pos, op, 9 + n))
        pos += 9 + n
    return out


def _with_reserved_record(data: bytes, opcode: int = 0x20) -> bytes:
    """``data`` with a record of a reserved opcode between two records of its data section."""
    import struct

    recs = [r for r in _top_records(data) if r[1] in (0x05, 0x06)]  # messages or chunks
    assert len(recs) >= 4
    at = recs[len(recs) // 2][0]
    payload = b"a record of a future MCAP version"
    return data[:at] + struct.pack("<BQ", opcode, len(payload)) + payload + data[at:]


@pytest.mark.parametrize("chunked", [True, False], ids=["chunked", "unchunked"])
def test_a_record_with_a_reserved_opcode_is_skipped(tmp_path, capsys, chunked):
    """MCAP reserves opcodes 0x10-0x7F for future versions; readers skip such records."""
    import json

    t, mag_T, q = motion(300)
    streams = [("/mag", MAG, DEFS[MAG], t, mag_T, ["imu"]),
               ("/att", IMU, DEFS[IMU], t + 2_000_000, q, ["b"])]
    if chunked:
        p = write_ros2(tmp_path / "r.mcap", streams, chunk_size=2048)
    else:
        p = write_ros2_raw(tmp_path / "r.mcap", streams, use_chunking=False)
    newer = tmp_path / "newer.mcap"
    newer.write_bytes(_with_reserved_record(p.read_bytes()))
    rec = read_recording(newer)  # no warning: nothing was lost (warnings fail the test)
    assert len(rec.mag) == 300 and len(rec.attitude) == 300
    np.testing.assert_allclose(rec.mag.values, mag_T * 1e9, rtol=1e-12)
    assert main(["info", "--json", str(newer)]) == 0
    counts = {c["topic"]: c["count"] for c in json.loads(capsys.readouterr().out)["channels"]}
    assert counts == {"/mag": 300, "/att": 300}


def test_the_damage_that_explains_a_failure_is_in_its_one_line(tmp_path, capsys):
    """A file cut off by damage before its channels: the one error line says why."""
    import struct

    t, mag_T, q = motion(300)
    p = write_ros2_raw(tmp_path / "r.mcap", [("/mag", MAG, DEFS[MAG], t, mag_T, ["imu"]),
                                            ("/att", IMU, DEFS[IMU], t, q, ["b"])],
                       use_chunking=False)
    data = p.read_bytes()
    # damage the first schema record's opcode: nothing after it can be trusted
    at = next(pos for pos, op, _ in _top_records(data) if op == 0x03)
    bad = tmp_path / "damaged.mcap"
    bad.write_bytes(data[:at] + struct.pack("<B", 0) + data[at + 1:])
    assert main(["info", str(bad)]) in (0, 2)
    capsys.readouterr()
    assert main(["calibrate", str(bad), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1, err
    assert "no magnetometer" in err[-1] and f"byte {at}" in err[-1], err
    # process says the same in its one line, and leaves no output folder behind
    out = tmp_path / "processed"
    assert main(["process", str(bad), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1, err
    assert "no magnetometer" in err[-1] and f"byte {at}" in err[-1], err
    assert not out.exists()

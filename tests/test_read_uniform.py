"""The reader's fast path for records of one shape (issue 18) against its general path.

``mcap_decode._batches`` gathers only the first bytes of records that share one layout and
reads each field with a strided copy; anything else (records of several lengths, strings
whose length varies, big-endian CDR, a damaged index) goes through ``select_messages`` and
``ChannelDecoder.decode``. Both must give the same arrays, bit for bit, the same frame ids and the
same problems.
"""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
from _reader_fixtures import DEFS, INSPVA_DEFS, motion, write_ros2

from pipeline.io import mcap_decode
from pipeline.io.mcap_decode import decode_channels
from pipeline.io.mcap_read import iter_recording_chunks, read_recording
from pipeline.io.mcap_scan import index_chunks, scan_file
from pipeline.io.mcap_write import write_recording

MAG = "sensor_msgs/msg/MagneticField"
IMU = "sensor_msgs/msg/Imu"
INSPVA = "novatel_oem7_msgs/msg/INSPVA"


def _decode_all(path: Path) -> tuple[dict, list]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scan = scan_file(path)
        index_chunks(scan)
        dec = decode_channels(scan, sorted(scan.channels))
    return dec, list(scan.problems)


def _same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for cid in a:
        x, y = a[cid], b[cid]
        assert (x.frame_id, x.position_kind) == (y.frame_id, y.position_kind)
        for name in ("t_ns", "values", "log_time_ns", "position"):
            u, v = getattr(x, name), getattr(y, name)
            if u is None or v is None:
                assert u is None and v is None
                continue
            assert u.dtype == v.dtype and u.shape == v.shape
            assert u.tobytes() == v.tobytes(), name


def _both_paths(path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[int, int]:
    """Decode with and without the fast path; return (fast batches, general batches)."""
    counts = [0, 0]
    orig = mcap_decode._batches

    def counting(*a, **k):  # type: ignore[no-untyped-def]
        for buf, sel, ends in orig(*a, **k):
            counts[buf is not None] += 1
            yield buf, sel, ends

    with monkeypatch.context() as m:
        m.setattr(mcap_decode, "_batches", counting)
        fast, fast_problems = _decode_all(path)
    with monkeypatch.context() as m:
        m.setattr(mcap_decode._Uniform, "rows", lambda self, buf, off: None)
        slow, slow_problems = _decode_all(path)
    _same(fast, slow)
    assert fast_problems == slow_problems
    return counts[0], counts[1]


@pytest.mark.parametrize("frames", [["imu"], ["a", "longer_frame_name", "", "abcd"]])
@pytest.mark.parametrize("att", [IMU, "geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry",
                                 "geometry_msgs/msg/QuaternionStamped", INSPVA])
def test_fast_path_equals_general_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                       att: str, frames: list[str]) -> None:
    t, mag_T, q = motion(600)
    att_def = INSPVA_DEFS["new"] if att == INSPVA else DEFS[att]
    vals = np.degrees(q[:, :3]) if att == INSPVA else q
    p = write_ros2(tmp_path / "r.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, frames),
        ("/att", att, att_def, t + 1_000_000, vals, frames),
        ("/turntable", "std_msgs/msg/Float64", DEFS["std_msgs/msg/Float64"], t,
         np.linspace(0, 90, len(t)), ["x"]),
    ], chunk_size=4096)
    fast, general = _both_paths(p, monkeypatch)
    if len(frames) == 1:
        assert fast and not general  # one shape per channel: all fast
    # shapes changing from chunk to chunk or inside one: equal either way


def test_bench_like_file_is_read_fast(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    t, mag_T, q = motion(3000)
    p = tmp_path / "w.mcap"
    write_recording(p, mag_t_ns=t, mag_nT=mag_T * 1e9, attitude_t_ns=t + 1_300_000,
                    q_enu_body=q, mag_log_delay_ns=200_000, attitude_log_delay_ns=900_000)
    fast, general = _both_paths(p, monkeypatch)
    assert fast and not general


def test_damaged_index_found_and_read_record_by_record(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    t, mag_T, q = motion(3000)
    p = tmp_path / "w.mcap"
    write_recording(p, mag_t_ns=t, mag_nT=mag_T * 1e9, attitude_t_ns=t + 1_300_000,
                    q_enu_body=q, mag_log_delay_ns=200_000, attitude_log_delay_ns=900_000)
    good = read_recording(p)
    scan = scan_file(p)
    ch = scan.chunks[len(scan.chunks) // 2]
    cid, mi = next(iter(ch.mi_pos.items()))
    data = bytearray(p.read_bytes())
    first_offset = mi + 9 + 2 + 4 + 8  # opcode, length, channel id, array length, log time
    (off,) = struct.unpack_from("<Q", data, first_offset)
    struct.pack_into("<Q", data, first_offset, off + 3)
    bad = tmp_path / "bad_index.mcap"
    bad.write_bytes(bytes(data))
    _both_paths(bad, monkeypatch)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = read_recording(bad)
    assert [pr.code for pr in rec.problems] == ["damaged_index"]
    for a, b in ((rec.mag.t_ns, good.mag.t_ns), (rec.mag.values, good.mag.values)):
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
    assert rec.attitude is not None and good.attitude is not None
    assert rec.attitude.q_enu_body.tobytes() == good.attitude.q_enu_body.tobytes()


@pytest.mark.parametrize("batch_bytes", [1 << 13, 1 << 23])
def test_shape_changing_between_chunks(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                       batch_bytes: int) -> None:
    t, mag_T, q = motion(1200)
    frames = ["a"] * 400 + ["longer_frame_name"] * 400 + [""] * 400
    p = write_ros2(tmp_path / "r.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, frames),
        ("/imu", IMU, DEFS[IMU], t + 1_000_000, q, frames[::-1]),
    ], chunk_size=4096)
    monkeypatch.setattr(mcap_decode, "BATCH_BYTES", batch_bytes)
    fast, general = _both_paths(p, monkeypatch)
    if batch_bytes < 1 << 20:
        assert fast and general  # chunks of one shape fast, those of two shapes not


def _chunk_arrays(path: Path, max_messages: int) -> list[list[np.ndarray]]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        chunks = list(iter_recording_chunks(path, max_messages=max_messages))
    out = []
    for c in chunks:
        assert c.attitude is not None and c.position is not None
        out.append([c.mag.t_ns, c.mag.values, c.attitude.t_ns, c.attitude.q_enu_body,
                    c.position.t_ns, c.position.p_m])
    return out


@pytest.mark.parametrize("max_messages", [150, 700, 100_000])
def test_chunked_reading_fast_and_general_give_the_same_ranges(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, max_messages: int) -> None:
    # records of one shape in the first and last thirds, of two in the middle (frame ids of
    # two lengths): ranges of chunks read the fast way, the general way and both
    t, mag_T, q = motion(1200)
    frames = ["a"] * 400 + ["a", "longer_frame_name"] * 200 + ["a"] * 400
    p = write_ros2(tmp_path / "r.mcap", [
        ("/mag", MAG, DEFS[MAG], t, mag_T, frames),
        ("/ins", INSPVA, INSPVA_DEFS["new"], t + 1_000_000, np.degrees(q[:, :3]), ["ins"]),
    ], chunk_size=4096)
    fast = _chunk_arrays(p, max_messages)
    monkeypatch.setattr(mcap_decode._Uniform, "rows", lambda self, buf, off: None)
    general = _chunk_arrays(p, max_messages)
    assert len(fast) == len(general) >= (2 if max_messages < 2400 else 1)
    for a, b in zip(fast, general, strict=True):
        for u, v in zip(a, b, strict=True):
            assert u.dtype == v.dtype and u.tobytes() == v.tobytes()
    rec = read_recording(p)
    whole = np.concatenate([c[1] for c in fast])
    assert whole.tobytes() == rec.mag.values.tobytes()
    # each range but the last reaches max_messages (both channels' messages)
    for c in fast[:-1]:
        assert len(c[0]) + len(c[2]) >= max_messages

"""Scale paths on small data: chunked reading and copying, memory-mapped files, byte masks,
streaming corrected MCAP, and process_recording's path for long recordings."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import pipeline.io.mcap_scan as mcap_scan
from pipeline.core.geometry import li2020_euler_to_quat, quat_conj, quat_rotate, so3_exp, so3_log
from pipeline.io.mcap_read import (
    iter_raw_channels,
    iter_recording_chunks,
    read_raw_channels,
    read_recording,
)
from pipeline.io.mcap_write import write_recording

B_ENU = np.array([12_000.0, 28_000.0, -25_000.0])
ROTVEC_DEG = np.array([-1.5, 0.5, 2.0])


def make(path, n=6_000, chunk_size=32 << 10, seed=0):
    rng = np.random.default_rng(seed)
    s = np.arange(n) / 50.0
    q = li2020_euler_to_quat(2 * np.pi * s / 30.0, np.radians(20) * np.sin(s / 3.0),
                             np.radians(20) * np.sin(s / 4.0))
    R = so3_exp(np.radians(ROTVEC_DEG))
    y = quat_rotate(quat_conj(q), np.broadcast_to(B_ENU, (n, 3))) @ R
    y = y + 0.5 * rng.standard_normal((n, 3))
    t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 20_000_000
    write_recording(path, mag_t_ns=t, mag_nT=y, attitude_t_ns=t + 2_000_000, q_enu_body=q,
                    mag_log_delay_ns=300_000, attitude_log_delay_ns=700_000,
                    chunk_size=chunk_size)
    return path, R


def test_chunks_concatenate_to_the_whole_recording(tmp_path):
    path, _ = make(tmp_path / "a.mcap")
    rec = read_recording(path)
    chunks = list(iter_recording_chunks(path, max_messages=1_500))
    assert len(chunks) >= 4 and [c.index for c in chunks] == list(range(len(chunks)))
    np.testing.assert_array_equal(np.concatenate([c.mag.t_ns for c in chunks]), rec.mag.t_ns)
    np.testing.assert_array_equal(np.concatenate([c.mag.values for c in chunks]),
                                  rec.mag.values)
    np.testing.assert_allclose(np.concatenate([c.attitude.q_enu_body for c in chunks]),
                               rec.attitude.q_enu_body, atol=1e-15)


def test_raw_ranges_concatenate_and_bound_later_log_times(tmp_path):
    path, _ = make(tmp_path / "b.mcap")
    whole = read_raw_channels(path)
    ranges = list(iter_raw_channels(path, max_messages=2_000))
    assert len(ranges) >= 3 and ranges[-1][1] is None
    for k, (raw, bound) in enumerate(ranges):
        assert [r.topic for r in raw] == [r.topic for r in whole]
        if bound is not None:
            later = [r.log_time_ns for rr, _b in ranges[k + 1:] for r in rr if len(r)]
            assert min(int(x.min()) for x in later) >= bound
    for i, w in enumerate(whole):
        parts = [raw[i] for raw, _ in ranges]
        np.testing.assert_array_equal(np.concatenate([p.log_time_ns for p in parts]),
                                      w.log_time_ns)
        np.testing.assert_array_equal(np.concatenate([p.sequence for p in parts]), w.sequence)
        np.testing.assert_array_equal(np.concatenate([p.data for p in parts]), w.data)


def test_memory_mapped_reading_equals_reading(tmp_path, monkeypatch):
    path, _ = make(tmp_path / "c.mcap", n=2_000)
    a = read_recording(path)
    monkeypatch.setattr(mcap_scan, "MMAP_MIN_BYTES", 0)
    b = read_recording(path)
    np.testing.assert_array_equal(a.mag.values, b.mag.values)
    np.testing.assert_array_equal(a.attitude.q_enu_body, b.attitude.q_enu_body)
    raw = read_raw_channels(path)
    assert sum(len(r) for r in raw) == 4_000


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 12), st.integers(0, 9)), min_size=1, max_size=30))
def test_copy_ranges_equals_slicing(spans):
    """Sorted disjoint ranges (with zero lengths and adjacency) and shuffled ones."""
    buf = np.arange(400, dtype=np.int64).astype(np.uint8)
    start, length, pos = [], [], 0
    for gap, ln in spans:
        pos += gap
        start.append(pos)
        length.append(ln)
        pos += ln
    start_a, length_a = np.array(start), np.array(length)
    want = np.concatenate([buf[a:a + n] for a, n in zip(start, length, strict=True)])
    np.testing.assert_array_equal(mcap_scan.copy_ranges(buf, start_a, length_a), want)
    rev = np.concatenate([buf[a:a + n] for a, n in zip(start[::-1], length[::-1], strict=True)])
    np.testing.assert_array_equal(
        mcap_scan.copy_ranges(buf, start_a[::-1].copy(), length_a[::-1].copy()), rev)


def test_corrected_mcap_written_range_by_range(tmp_path, monkeypatch):
    """Small copy ranges: every input message copied byte for byte, each channel's log
    times ordered in the file, readable by mcap's own reader with CRC checks; the new
    channels complete.

    Both copies: the input's chunks as they are (an intact input) and message by message
    (the path for damaged inputs). Chunks may overlap in time (input chunks beside the new
    channels' chunks), so the file order is in log-time order per channel, not across
    channels; a reader in log-time order goes by the indexes.
    """
    from mcap.reader import make_reader

    import stages.write_mcap as write_mcap
    from pipeline.run.runner import ProcessOptions, analyse

    path, _ = make(tmp_path / "d.mcap", n=5_000)
    rec = read_recording(path)
    cal = analyse(rec, ProcessOptions(diagnose=False)).need_calibration()
    monkeypatch.setattr(write_mcap, "COPY_RANGE_MESSAGES", 1_000)
    for copy in ("chunks", "messages"):
        if copy == "messages":
            monkeypatch.setattr(write_mcap, "pass_through", lambda path: None)
        out = write_mcap.write_corrected_mcap(rec, cal, tmp_path / copy / "d.corrected.mcap")
        got = {r.topic: r for r in read_raw_channels(out)}
        for r in read_raw_channels(path):
            np.testing.assert_array_equal(got[r.topic].data, r.data)
            np.testing.assert_array_equal(got[r.topic].log_time_ns, r.log_time_ns)
        for suffix in write_mcap.SUFFIXES:
            assert len(got[f"/mag/{suffix}"]) == len(rec.mag)
        with open(out, "rb") as fh:
            reader = make_reader(fh, validate_crcs=True)
            msgs = [(c.topic, m.log_time)
                    for _s, c, m in reader.iter_messages(log_time_order=False)]
            assert reader.get_summary().statistics.message_count == len(msgs) == (
                2 * 5_000 + 4 * 5_000 + 1)  # input; 4 new channels; one /tf_static
            ordered = [m.log_time for _s, _c, m in reader.iter_messages(log_time_order=True)]
        assert sorted(ordered) == ordered and len(ordered) == len(msgs)
        for topic in {t for t, _ in msgs}:
            logs = np.array([t for tp, t in msgs if tp == topic], dtype=np.int64)
            assert np.all(np.diff(logs) >= 0), topic


@pytest.mark.parametrize("chunked", [True, False], ids=["file", "in-memory"])
def test_process_scale_path_matches_the_normal_path(tmp_path, monkeypatch, chunked):
    """Both sources of a long recording give the whole recording's answer: the file read
    range by range (an intact file) and the recording read whole, then cut into chunks
    (what a damaged file takes: its corrected MCAP copied message by message)."""
    import pipeline.run.plan as plan
    import pipeline.run.source as source
    import stages.write_mcap as write_mcap
    from pipeline.run.runner import ProcessOptions, process_recording

    monkeypatch.setattr(plan, "DECIMATED_SAMPLES", 2_000)  # every 4th sample
    monkeypatch.setattr(plan, "CHUNK_SAMPLES", 1_500)
    if not chunked:
        monkeypatch.setattr(source, "pass_through", lambda path: None)
        monkeypatch.setattr(write_mcap, "pass_through", lambda path: None)

    path, R = make(tmp_path / "e.mcap", n=8_000)
    base = dict(diagnose=False, write_rerun=False, write_report=False)
    small = process_recording(path, tmp_path / "normal", options=ProcessOptions(**base))
    big = process_recording(path, tmp_path / "scale",
                            options=ProcessOptions(scale_samples=1_000, **base))
    steps = list(big["timings_s"])
    assert steps.index("SegmentMotion") < steps.index("Resample")  # windows analysed
    assert big["estimator"] == "ml-streaming"
    rv_small = np.array(small["rotvec_body_mag_deg"])
    rv_big = np.array(big["rotvec_body_mag_deg"])
    assert np.linalg.norm(rv_big - rv_small) < 0.02
    assert np.degrees(np.linalg.norm(so3_log(so3_exp(np.radians(rv_big)) @ R.T))) < 0.02
    for key in ("ratio_pct_x", "ratio_pct_y", "ratio_pct_z"):
        assert big[key] == pytest.approx(small[key], rel=0.05)
    assert set(big["paths"]) == set(small["paths"])

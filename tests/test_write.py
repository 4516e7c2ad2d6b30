"""MCAP writing (pipeline.io.mcap_write), checked with mcap's and mcap_ros2's own readers."""

from __future__ import annotations

import io
import json
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.records import Chunk, DataEnd, Footer, MessageIndex
from mcap.stream_reader import StreamReader, get_chunk_data_stream
from mcap_ros2.decoder import DecoderFactory

from pipeline.core import geometry
from pipeline.core.errors import OutputError
from pipeline.io.mcap_write import McapColumnWriter, copy_channels, write_recording
from pipeline.io.messages import encode, schema_for

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
T0 = 1_700_000_000_000_000_000


def _sim(n_mag=900, n_att=450, seed=0):
    rng = np.random.default_rng(seed)
    t_mag = T0 + np.arange(n_mag, dtype=np.int64) * 5_000_000 + 1_234
    t_att = T0 + np.arange(n_att, dtype=np.int64) * 10_000_000 + 777
    mag = rng.normal(size=(n_mag, 3)) * 2e4
    q = rng.normal(size=(n_att, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return t_mag, mag, t_att, q


def _decoded(path, topic):
    with open(path, "rb") as fh:
        r = make_reader(fh, decoder_factories=[DecoderFactory()], validate_crcs=True)
        return [(m.log_time, d) for _, _, m, d in r.iter_decoded_messages(topics=[topic])]


def _check_file_crcs(path: Path) -> None:
    """Data-section, summary, chunk and attachment CRCs, computed independently here."""
    buf = Path(path).read_bytes()
    assert buf[:8] == buf[-8:] == b"\x89MCAP0\r\n"
    footer_at = len(buf) - 8 - 29
    op, length, summary_start, so_start, summary_crc = struct.unpack_from("<BQQQI", buf, footer_at)
    assert (op, length) == (0x02, 20)
    assert summary_crc == zlib.crc32(buf[summary_start : footer_at + 1 + 8 + 16])
    n_chunks = n_att = 0
    for rec in StreamReader(io.BytesIO(buf), emit_chunks=True, validate_crcs=True).records:
        if isinstance(rec, DataEnd):
            data_end_at = summary_start - 13  # DataEnd: opcode, length, crc
            assert buf[data_end_at] == 0x0F
            assert rec.data_section_crc == zlib.crc32(buf[:data_end_at])
        elif isinstance(rec, Chunk):
            n_chunks += 1
            stream, _ = get_chunk_data_stream(rec, validate_crc=True)
            assert rec.uncompressed_crc != 0
        elif type(rec).__name__ == "Attachment":
            n_att += 1
            assert rec.data is not None
    # Attachment CRCs: mcap's reader does not check them; find each record by its index.
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    for idx in summary.attachment_indexes:
        rec = buf[idx.offset : idx.offset + idx.length]
        assert rec[0] == 0x09
        body, crc = rec[9:-4], struct.unpack("<I", rec[-4:])[0]
        assert crc == zlib.crc32(body)
    assert summary.statistics.chunk_count == n_chunks == len(summary.chunk_indexes)


CASES = [
    ("sensor_msgs/msg/MagneticField", "sensor_msgs/msg/Imu", "zstd"),
    ("sensor_msgs/msg/MagneticField", "geometry_msgs/msg/PoseStamped", "lz4"),
    ("sensor_msgs/msg/MagneticField", "geometry_msgs/msg/QuaternionStamped", "none"),
    ("sensor_msgs/msg/MagneticField", "novatel_oem7_msgs/msg/INSPVA", "zstd"),
    ("magalign.Magnetometer", "magalign.AttitudeQuaternion", "zstd"),
    ("magalign.Magnetometer", "magalign.AttitudeEuler", "lz4"),
]


@pytest.mark.parametrize(("mag_type", "att_type", "compression"), CASES)
def test_write_recording_reads_back(tmp_path, mag_type, att_type, compression):
    t_mag, mag, t_att, q = _sim()
    p = tmp_path / "rec.mcap"
    write_recording(
        p, mag_t_ns=t_mag, mag_nT=mag, attitude_t_ns=t_att, q_enu_body=q, mag_type=mag_type,
        attitude_type=att_type, compression=compression, mag_log_delay_ns=3_000_000,
        attitude_log_delay_ns=11_000_000, chunk_size=16_384,
        turntable_t_ns=t_att[::5], turntable_deg=np.linspace(0, 359, len(t_att[::5])),
        turntable_type="std_msgs/msg/Float64" if mag_type.startswith("sensor")
        else "magalign.Turntable",
    )
    _check_file_crcs(p)
    with open(p, "rb") as fh:
        r = make_reader(fh, validate_crcs=True)
        s = r.get_summary()
        header = r.get_header()
        msgs = [(c.topic, m) for _, c, m in r.iter_messages()]
    assert header.profile == ("ros2" if mag_type.startswith("sensor") else "")
    log = np.array([m.log_time for _, m in msgs])
    assert np.all(np.diff(log) >= 0), "messages interleaved by log time"
    topics = [t for t, _ in msgs]
    assert topics.count("/mag") == len(t_mag) and topics.count("/attitude") == len(t_att)
    # Summary statistics
    st_ = s.statistics
    ids = {c.topic: c.id for c in s.channels.values()}
    assert st_.message_count == len(msgs)
    assert st_.channel_message_counts == {ids["/mag"]: len(t_mag), ids["/attitude"]: len(t_att),
                                          ids["/turntable"]: len(t_att[::5])}
    assert st_.message_start_time == log[0] and st_.message_end_time == log[-1]
    assert st_.schema_count == len(s.schemas) == 3 and st_.channel_count == 3
    assert st_.chunk_count > 3
    assert sum(ci.uncompressed_size for ci in s.chunk_indexes) == sum(
        31 + len(m.data) for _, m in msgs)
    mag_log = np.array([m.log_time for t, m in msgs if t == "/mag"])
    np.testing.assert_array_equal(mag_log, t_mag + 3_000_000)

    if mag_type.startswith("sensor"):
        dec = _decoded(p, "/mag")
        got = np.array([[d.magnetic_field.x, d.magnetic_field.y, d.magnetic_field.z]
                        for _, d in dec])
        np.testing.assert_array_equal(got, mag * 1e-9)
        stamps = [d.header.stamp.sec * 10**9 + d.header.stamp.nanosec for _, d in dec]
        np.testing.assert_array_equal(stamps, t_mag)
        assert {d.header.frame_id for _, d in dec} == {"mag"}
        att = _decoded(p, "/attitude")
        if att_type == "novatel_oem7_msgs/msg/INSPVA":
            q_back = geometry.novatel_to_quat([d.roll for _, d in att], [d.pitch for _, d in att],
                                              [d.azimuth for _, d in att])
            sign = np.sign(np.sum(q_back * q, axis=1))[:, None]
            np.testing.assert_allclose(q_back * sign, q, atol=1e-12)
        else:
            o = [(d.orientation if hasattr(d, "orientation") else
                  d.pose.orientation if hasattr(d, "pose") else d.quaternion) for _, d in att]
            np.testing.assert_array_equal([[a.x, a.y, a.z, a.w] for a in o], q)
    else:
        mags = [json.loads(m.data) for t, m in msgs if t == "/mag"]
        np.testing.assert_array_equal([d["mag_nT"] for d in mags], mag)
        np.testing.assert_array_equal([d["t_ns"] for d in mags], t_mag)
        att = [json.loads(m.data) for t, m in msgs if t == "/attitude"]
        if att_type == "magalign.AttitudeEuler":
            q_back = geometry.li2020_euler_to_quat(
                np.radians([d["heading_deg"] for d in att]),
                np.radians([d["pitch_deg"] for d in att]),
                np.radians([d["roll_deg"] for d in att]))
            sign = np.sign(np.sum(q_back * q, axis=1))[:, None]
            np.testing.assert_allclose(q_back * sign, q, atol=1e-12)
        else:
            np.testing.assert_array_equal([d["q_enu_body"] for d in att], q)


def test_stream_reader_and_message_indexes(tmp_path):
    """Non-seeking read with CRCs; every MessageIndex entry points at its Message record."""
    t_mag, mag, t_att, q = _sim(700, 300, seed=2)
    p = tmp_path / "rec.mcap"
    write_recording(p, mag_t_ns=t_mag, mag_nT=mag, attitude_t_ns=t_att, q_enu_body=q,
                    chunk_size=5_000, attitude_log_delay_ns=4_000_000)
    buf = p.read_bytes()
    chunk = None
    n_entries = 0
    chunk_offsets = []
    for rec in StreamReader(io.BytesIO(buf), emit_chunks=True, validate_crcs=True).records:
        if isinstance(rec, Chunk):
            stream, _ = get_chunk_data_stream(rec, validate_crc=True)
            chunk = stream.read(rec.uncompressed_size)
            chunk_offsets.append(rec)
        elif isinstance(rec, MessageIndex):
            assert chunk is not None
            for log_time, off in rec.records:
                op, _, cid, _, lt = struct.unpack_from("<BQHIQ", chunk, off)
                assert (op, cid, lt) == (0x05, rec.channel_id, log_time)
                n_entries += 1
        elif isinstance(rec, Footer):
            assert rec.summary_start > 0
    assert n_entries == len(t_mag) + len(t_att)
    with open(p, "rb") as fh:
        s = make_reader(fh).get_summary()
    # Chunk indexes point at the chunks and at their message indexes.
    for ci in s.chunk_indexes:
        assert buf[ci.chunk_start_offset] == 0x06
        end = ci.chunk_start_offset + ci.chunk_length
        assert ci.message_index_length == sum(
            9 + struct.unpack_from("<Q", buf, o + 1)[0] for o in ci.message_index_offsets.values())
        assert min(ci.message_index_offsets.values()) == end
    # Time-windowed reading through the index (half-open window)
    with open(p, "rb") as fh:
        r = make_reader(fh)
        lo, hi = int(t_mag[100]), int(t_mag[200])
        got = [m.log_time for _, _, m in r.iter_messages(topics=["/mag"], starting_at=lo,
                                                         ending_before=hi)]
    np.testing.assert_array_equal(got, t_mag[100:200])


def test_metadata_and_attachment_round_trip(tmp_path):
    p = tmp_path / "meta.mcap"
    blob = bytes(range(256)) * 3
    with McapColumnWriter(p, profile="", compression="none") as w:
        w.add_metadata("magalign.calibration", {"json": '{"a": [1, 2]}', "k": "ü"})
        w.add_metadata("second", {})
        w.add_attachment("calibration.json", "application/json", blob, log_time_ns=42,
                         create_time_ns=7)
    _check_file_crcs(p)
    with open(p, "rb") as fh:
        r = make_reader(fh, validate_crcs=True)
        md = [(m.name, m.metadata) for m in r.iter_metadata()]
        att = list(r.iter_attachments())
        s = r.get_summary()
    assert md == [("magalign.calibration", {"json": '{"a": [1, 2]}', "k": "ü"}), ("second", {})]
    assert len(att) == 1
    a = att[0]
    assert (a.name, a.media_type, a.data, a.log_time, a.create_time) == (
        "calibration.json", "application/json", blob, 42, 7)
    assert s.statistics.attachment_count == 1 and s.statistics.metadata_count == 2
    assert s.statistics.message_count == 0 and s.statistics.chunk_count == 0


def test_no_output_when_exception_mid_write(tmp_path):
    p = tmp_path / "out.mcap"
    t_mag, mag, _, _ = _sim(50, 10)
    with pytest.raises(RuntimeError, match="boom"), McapColumnWriter(p) as w:
        sid = w.add_schema(*schema_for("sensor_msgs/msg/MagneticField")[:3])
        cid = w.add_channel("/mag", "cdr", sid)
        w.add_messages(cid, t_mag, *encode("sensor_msgs/msg/MagneticField", t_mag,
                                           {"mag_T": mag * 1e-9}))
        raise RuntimeError("boom")
    assert not p.exists()
    assert list(tmp_path.iterdir()) == [], "no temporary file left behind"


def test_no_output_when_writing_itself_fails(tmp_path):
    p = tmp_path / "out.mcap"
    w = McapColumnWriter(p)
    w.open()
    cid = w.add_channel("/x", "json", 0)
    w.add_messages(cid, [1, 2], np.frombuffer(b"{}{}", np.uint8), [0, 2, 4])
    w._blocks[0].rec_off = None  # corrupt internal state: writing raises mid-file
    with pytest.raises((TypeError, ValueError)):
        w.close()
    assert list(tmp_path.iterdir()) == []


def test_refuses_to_overwrite_an_input(tmp_path):
    t_mag, mag, _, _ = _sim(20, 5)
    src = tmp_path / "in.mcap"
    write_recording(src, mag_t_ns=t_mag, mag_nT=mag)
    before = src.read_bytes()
    with pytest.raises(OutputError, match="input"):
        write_recording(src, mag_t_ns=t_mag, mag_nT=mag * 2, inputs=(src,))
    with pytest.raises(OutputError, match="input"), McapColumnWriter(
            tmp_path / "." / "in.mcap", inputs=[str(src)]):
        pass
    assert src.read_bytes() == before


def test_bad_arguments_raise_output_error(tmp_path):
    with pytest.raises(OutputError):
        McapColumnWriter(tmp_path / "x.mcap", compression="bz2")
    with McapColumnWriter(tmp_path / "x.mcap") as w:
        with pytest.raises(OutputError):
            w.add_channel("/a", "cdr", 5)
        cid = w.add_channel("/a", "json", 0)
        with pytest.raises(OutputError):
            w.add_messages(cid, [1, 2], np.zeros(4, np.uint8), [0, 2])
        with pytest.raises(OutputError):
            w.add_messages(cid, [1, 2], np.zeros(4, np.uint8), [0, 2, 9])
        with pytest.raises(OutputError):
            w.add_messages(99, [1], np.zeros(1, np.uint8), [0, 1])


def test_merge_is_stable_by_log_time(tmp_path):
    """Blocks added out of order and with equal times come out sorted, ties in call order."""
    p = tmp_path / "m.mcap"
    with McapColumnWriter(p, profile="", chunk_size=64) as w:
        a = w.add_channel("/a", "json", 0)
        b = w.add_channel("/b", "json", 0)
        payload = [b'{"i": %d}' % i for i in range(6)]
        data = np.frombuffer(b"".join(payload), np.uint8)
        off = np.concatenate([[0], np.cumsum([len(x) for x in payload])])
        w.add_messages(a, [30, 10, 20, 10, 50, 40], data, off)  # unsorted within a block
        w.add_messages(b, [10, 10, 60], data[: off[3]], off[:4], sequence=[7, 8, 9])
        w.add_messages(a, [5], data[: off[1]], off[:2])
    with open(p, "rb") as fh:
        got = [(c.topic, m.log_time, m.data, m.sequence)
               for _, c, m in make_reader(fh, validate_crcs=True).iter_messages()]
    assert got == [
        ("/a", 5, payload[0], 6),
        ("/a", 10, payload[1], 1), ("/a", 10, payload[3], 3),
        ("/b", 10, payload[0], 7), ("/b", 10, payload[1], 8),
        ("/a", 20, payload[2], 2), ("/a", 30, payload[0], 0), ("/a", 40, payload[5], 5),
        ("/a", 50, payload[4], 4), ("/b", 60, payload[2], 9),
    ]


def test_flush_in_stretches_equals_one_shot(tmp_path):
    """Writing stretch by stretch with flush() gives the same messages and statistics."""
    t_mag, mag, t_att, q = _sim(600, 300, seed=7)
    d_mag, o_mag = encode("sensor_msgs/msg/MagneticField", t_mag, {"mag_T": mag * 1e-9}, "mag")
    d_att, o_att = encode("sensor_msgs/msg/Imu", t_att, {"q_xyzw": q}, "body")
    one, parts = tmp_path / "one.mcap", tmp_path / "parts.mcap"
    with McapColumnWriter(one, chunk_size=4096) as w:
        a = w.add_channel("/mag", "cdr", w.add_schema(*schema_for(
            "sensor_msgs/msg/MagneticField")[:3]))
        b = w.add_channel("/att", "cdr", w.add_schema(*schema_for("sensor_msgs/msg/Imu")[:3]))
        w.add_messages(a, t_mag, d_mag, o_mag)
        w.add_messages(b, t_att, d_att, o_att)
    with McapColumnWriter(parts, chunk_size=4096) as w:
        a = w.add_channel("/mag", "cdr", w.add_schema(*schema_for(
            "sensor_msgs/msg/MagneticField")[:3]))
        w.add_messages(a, t_mag[:250], d_mag[: o_mag[250]], o_mag[:251])
        w.flush(int(t_mag[250]))  # nothing of /att exists yet; its channel comes later
        b = w.add_channel("/att", "cdr", w.add_schema(*schema_for("sensor_msgs/msg/Imu")[:3]))
        k = int(np.searchsorted(t_att, t_mag[250]))
        w.add_messages(b, t_att[k:], d_att[o_att[k]:], o_att[k:] - o_att[k],
                       sequence=np.arange(k, len(t_att)))
        w.add_messages(a, t_mag[250:], d_mag[o_mag[250]:], o_mag[250:] - o_mag[250])
        w.flush(int(t_mag[400]))
        with pytest.raises(OutputError, match="flush"):
            w.add_messages(a, t_mag[:1], d_mag[: o_mag[1]], o_mag[:2])
    _check_file_crcs(parts)
    ma, sa = _all_messages(one)
    mb, sb = _all_messages(parts)
    # Everything of /att before the first flush point was never given to the second writer.
    ma = [m for m in ma if m[0] == "/mag" or m[5] >= t_mag[250]]
    assert [m[:1] + m[3:] for m in ma] == [m[:1] + m[3:] for m in mb]
    assert sb.statistics.message_count == len(mb)
    assert sb.statistics.message_start_time == t_mag[0] == mb[0][5]
    assert sb.statistics.message_end_time == sa.statistics.message_end_time


@dataclass(frozen=True)
class _Raw:
    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    metadata: dict = field(default_factory=dict)
    log_time_ns: np.ndarray = None
    publish_time_ns: np.ndarray = None
    sequence: np.ndarray = None
    data: np.ndarray = None
    offsets: np.ndarray = None


def _raw_channels_by_hand(path) -> list[_Raw]:
    with open(path, "rb") as fh:
        r = make_reader(fh)
        s = r.get_summary()
        per: dict[int, list] = {cid: [] for cid in s.channels}
        for _, c, m in r.iter_messages(log_time_order=False):
            per[c.id].append(m)
    out = []
    for cid, ms in per.items():
        c = s.channels[cid]
        sc = s.schemas.get(c.schema_id)
        lens = [len(m.data) for m in ms]
        out.append(_Raw(
            c.topic, sc.name if sc else "", sc.encoding if sc else "", sc.data if sc else b"",
            c.message_encoding, dict(c.metadata),
            np.array([m.log_time for m in ms], np.int64),
            np.array([m.publish_time for m in ms], np.int64),
            np.array([m.sequence for m in ms], np.uint32),
            np.frombuffer(b"".join(m.data for m in ms), np.uint8),
            np.concatenate([[0], np.cumsum(lens)]).astype(np.int64)))
    return out


def _all_messages(path):
    with open(path, "rb") as fh:
        r = make_reader(fh, validate_crcs=True)
        s = r.get_summary()
        msgs = [(c.topic, c.message_encoding, dict(c.metadata), sc.name if sc else "",
                 sc.data if sc else b"", m.log_time, m.publish_time, m.sequence, m.data)
                for sc, c, m in r.iter_messages()]
    return msgs, s


def test_copy_channels_unchanged(tmp_path):
    t_mag, mag, t_att, q = _sim(400, 200, seed=5)
    src = tmp_path / "src.mcap"
    with McapColumnWriter(src) as w:
        sid = w.add_schema(*schema_for("sensor_msgs/msg/MagneticField")[:3])
        cid = w.add_channel("/mag", "cdr", sid, {"sensor": "fluxgate"})
        d, o = encode("sensor_msgs/msg/MagneticField", t_mag, {"mag_T": mag * 1e-9}, "mag")
        w.add_messages(cid, t_mag + 9, d, o, publish_time_ns=t_mag + 3,
                       sequence=np.arange(len(t_mag)) * 2 + 5)
        sid = w.add_schema(*schema_for("geometry_msgs/msg/PoseStamped")[:3])
        cid = w.add_channel("/pose", "cdr", sid)
        d, o = encode("geometry_msgs/msg/PoseStamped", t_att, {"q_xyzw": q}, "world")
        w.add_messages(cid, t_att, d, o)
        cid = w.add_channel("/notes", "json", 0)
        w.add_messages(cid, [T0], np.frombuffer(b'{"note": 1}', np.uint8), [0, 11])
    dst = tmp_path / "dst.mcap"
    with McapColumnWriter(dst, inputs=[src]) as w:
        ids = copy_channels(w, _raw_channels_by_hand(src))
        assert set(ids) == {"/mag", "/pose", "/notes"}
    a, sa = _all_messages(src)
    b, sb = _all_messages(dst)
    assert a == b
    assert sa.statistics.channel_message_counts == sb.statistics.channel_message_counts


def test_copy_channels_with_reader_on_real_recording(tmp_path):
    lab = REAL / "lab_03.mcap"
    if not lab.exists():
        pytest.skip(f"real recordings not available ({REAL} is absent)")
    from pipeline.io import mcap_read
    before = lab.read_bytes()
    dst = tmp_path / "copy.mcap"
    raw = mcap_read.read_raw_channels(lab)
    with McapColumnWriter(dst, inputs=[lab]) as w:
        copy_channels(w, raw)
    # Every column identical (read back with the project's reader) ...
    for a, b in zip(raw, mcap_read.read_raw_channels(dst), strict=True):
        assert (a.topic, a.schema_name, a.schema_data, a.message_encoding, a.metadata) == (
            b.topic, b.schema_name, b.schema_data, b.message_encoding, b.metadata)
        for name in ("log_time_ns", "publish_time_ns", "sequence", "data", "offsets"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    # ... and, with mcap's own reader (CRCs validated), the first seconds message by message.
    with open(lab, "rb") as fh:
        t_end = make_reader(fh).get_summary().statistics.message_start_time + 3 * 10**9
    win = []
    for path in (lab, dst):
        with open(path, "rb") as fh:
            r = make_reader(fh, validate_crcs=True)
            win.append([(c.topic, m.log_time, m.publish_time, m.sequence, m.data)
                        for _, c, m in r.iter_messages(ending_before=t_end)])
            s = r.get_summary()
            win.append(s.statistics.channel_message_counts)
    assert win[0] == win[2] and len(win[0]) > 500
    assert win[1] == win[3]
    assert lab.read_bytes() == before


# ------------------------------------------------------------------ property test

@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                 HealthCheck.function_scoped_fixture])
@given(
    blocks=st.lists(
        st.tuples(st.integers(0, 2),  # channel
                  st.lists(st.tuples(st.integers(0, 40), st.binary(max_size=40)),
                           min_size=0, max_size=30)),
        min_size=1, max_size=5),
    chunk_size=st.sampled_from([1, 100, 1 << 20]),
    compression=st.sampled_from(["zstd", "lz4", "none"]),
)
def test_property_any_columns_round_trip(tmp_path_factory, blocks, chunk_size, compression):
    p = tmp_path_factory.mktemp("prop") / "p.mcap"
    expected = []
    with McapColumnWriter(p, profile="", chunk_size=chunk_size, compression=compression) as w:
        cids = [w.add_channel(f"/c{i}", "raw", 0) for i in range(3)]
        for k, (ch, msgs) in enumerate(blocks):
            if not msgs:
                continue
            log = np.array([m[0] for m in msgs], np.int64)
            payloads = [m[1] for m in msgs]
            off = np.concatenate([[0], np.cumsum([len(x) for x in payloads])]).astype(np.int64)
            w.add_messages(cids[ch], log, np.frombuffer(b"".join(payloads), np.uint8), off)
            expected += [(int(t), k, i, f"/c{ch}", pl) for i, (t, pl) in enumerate(msgs)]
    expected.sort(key=lambda e: (e[0], e[1], e[2]))
    _check_file_crcs(p)
    with open(p, "rb") as fh:
        got = [(m.log_time, c.topic, m.data)
               for _, c, m in make_reader(fh, validate_crcs=True).iter_messages()]
    assert got == [(e[0], e[3], e[4]) for e in expected]


# ------------------------------------------------------------------ pass-through copy

def test_corrected_mcap_pass_through_equals_message_copy(tmp_path, monkeypatch):
    """Input chunks copied as they are give the same messages as the message-by-message copy.

    Per channel: log and publish times, sequence numbers and payloads, in order; the same
    statistics; every CRC valid; and the input chunks' compressed bytes appear in the output.
    """
    import pipeline.io.mcap_read as mcap_read
    from pipeline.io.mcap_read import pass_through, read_recording
    from pipeline.model.calibration import Calibration
    from stages.write_mcap import write_corrected_mcap

    t_mag, mag, t_att, q = _sim(3000, 1500, seed=11)
    src = write_recording(tmp_path / "in.mcap", mag_t_ns=t_mag, mag_nT=mag, attitude_t_ns=t_att,
                          q_enu_body=q, mag_log_delay_ns=300_000, chunk_size=8192)
    rec = read_recording(src)
    cal = Calibration(R_body_mag=np.eye(3), sigma_rotvec_deg=[0.1] * 3,
                      B_enu_nT=[1e4, 2e4, -3e4], estimator="truth", residual_rms_nT=1.0,
                      n_samples=len(t_mag))
    pt = pass_through(src)
    assert pt is not None and len(pt.chunks) > 5
    fast = write_corrected_mcap(rec, cal, tmp_path / "fast.mcap")
    monkeypatch.setattr(mcap_read, "pass_through", lambda path: None)
    slow = write_corrected_mcap(rec, cal, tmp_path / "slow.mcap")
    for p in (fast, slow):
        _check_file_crcs(p)

    def per_channel(path):
        msgs, s = _all_messages(path)
        out: dict[str, list] = {}
        for m in msgs:
            out.setdefault(m[0], []).append(m[1:])
        counts = {s.channels[c].topic: k for c, k in s.statistics.channel_message_counts.items()}
        return out, counts, s.statistics.message_count

    assert per_channel(fast) == per_channel(slow)
    out = fast.read_bytes()
    assert all(bytes(c.record) in out for c in pt.chunks)


def test_pass_through_refuses_unchunked_and_cut_files(tmp_path):
    from pipeline.io.mcap_read import pass_through

    t_mag, mag, t_att, q = _sim(600, 300, seed=2)
    src = write_recording(tmp_path / "in.mcap", mag_t_ns=t_mag, mag_nT=mag, attitude_t_ns=t_att,
                          q_enu_body=q, chunk_size=4096)
    assert pass_through(src) is not None
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(src.read_bytes()[:-200])
    assert pass_through(cut) is None


def test_pass_through_chunk_times_are_the_chunk_indexes(tmp_path):
    """Each pass-through chunk's start and end times (kept by the scan from the chunk records)
    are those mcap's own reader gives for the chunk at the same offset."""
    from pipeline.io.mcap_read import pass_through
    from pipeline.io.mcap_scan import scan_file

    t_mag, mag, t_att, q = _sim(2000, 1000, seed=5)
    src = write_recording(tmp_path / "in.mcap", mag_t_ns=t_mag, mag_nT=mag, attitude_t_ns=t_att,
                          q_enu_body=q, mag_log_delay_ns=250_000, chunk_size=4096)
    with open(src, "rb") as fh:
        idx = {ci.chunk_start_offset: (ci.message_start_time, ci.message_end_time)
               for ci in make_reader(fh).get_summary().chunk_indexes}
    scan = scan_file(src)
    assert len(idx) > 5 and len(scan.chunks) == len(idx)
    assert {ch.offset: (ch.start_ns, ch.end_ns) for ch in scan.chunks} == idx
    pt = pass_through(src)
    assert pt is not None
    assert sorted((c.start_ns, c.end_ns) for c in pt.chunks) == sorted(idx.values())

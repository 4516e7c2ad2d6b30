"""Vectorised MCAP reading, the reader's API: chunks straight into numpy, recovery of damaged files.

More in docs/modules.md, ``pipeline.io.mcap_read``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.core.errors import (
    ChannelError,
    CorruptRecordingError,
    DataQualityError,
    InputError,
    RecoveredDataWarning,
)
from pipeline.core.recording import (
    AngleSeries,
    AttitudeSeries,
    ChannelInfo,
    EncodingFamily,
    Frame,
    GeodeticOrigin,
    PositionFrame,
    PositionSeries,
    Problem,
    Recording,
    Role,
    VectorSeries,
)
from pipeline.io.mcap_checks import (
    ABSURD_NT,
    MIN_ATTITUDE_SAMPLES,
    attitude_gap_problems,
    check_channel,
    finite_rows,
    gap_problems,
    quat_norm,
    value_problems,
)
from pipeline.io.mcap_decode import (
    DecodedColumns,
    decode_channels,
    decoded_batches,
    first_valid_fix,
    geodetic_to_local_enu,
    pick_channel,
    role_of,
    type_of,
)
from pipeline.io.mcap_scan import (
    ChunkRecord,
    Scan,
    SchemaRecord,
    copy_ranges,
    decompress_chunk,
    index_chunks,
    iter_blocks,
    record_columns,
    release_pages,
    scan_file,
    select_messages,
)


# --------------------------------------------------------------------------- data classes
@dataclass(frozen=True)
class RawChannel:
    """Every message of one channel as columns, for copying unchanged into another file.

    Attributes
    ----------
    topic, schema_name, schema_encoding : str
    schema_data : bytes
    message_encoding : str
    metadata : dict
    log_time_ns, publish_time_ns : ndarray of int64, shape (N,)
    sequence : ndarray of uint32, shape (N,)
    data : ndarray of uint8
        All payloads concatenated, in file order.
    offsets : ndarray of int64, shape (N + 1,)
        Message ``i`` is ``data[offsets[i]:offsets[i + 1]]``.

    """

    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    metadata: dict
    log_time_ns: NDArray[np.int64]
    publish_time_ns: NDArray[np.int64]
    sequence: NDArray[np.uint32]
    data: NDArray[np.uint8]
    offsets: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.log_time_ns.shape[0])


# --------------------------------------------------------------------------- raw channels
def _raw_from_parts(scan: Scan, parts: dict[int, list[dict[str, np.ndarray]]]
                    ) -> list[RawChannel]:
    out = []
    for cid in sorted(scan.channels):
        c = scan.channels[cid]
        s = scan.schemas.get(c.schema_id, SchemaRecord(0, "", "", b""))
        ps = parts[cid]

        def cat(key: str, dtype: Any, ps: list = ps) -> np.ndarray:
            if len(ps) == 1:
                return ps[0][key].astype(dtype, copy=False)
            return np.concatenate([p[key] for p in ps]).astype(dtype) if ps else np.zeros(
                0, dtype)

        lengths = cat("length", np.int64)
        out.append(RawChannel(
            topic=c.topic, schema_name=s.name, schema_encoding=s.encoding,
            schema_data=s.data, message_encoding=c.message_encoding,
            metadata=dict(c.metadata), log_time_ns=cat("log_time_ns", np.int64),
            publish_time_ns=cat("publish_time_ns", np.int64), sequence=cat("sequence",
                                                                           np.uint32),
            data=cat("data", np.uint8),
            offsets=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
        ))
    return out


def read_raw_channels(path: str | Path) -> list[RawChannel]:
    """Every channel's messages as columns, to copy them unchanged into another file.

    Parameters
    ----------
    path : path of an MCAP file (damaged files are read as far as they are intact, with a
        :class:`~pipeline.core.errors.RecoveredDataWarning`).

    Returns
    -------
    list of RawChannel
        One per channel, in channel id order; messages in file order.

    """
    scan = scan_file(path)
    index_chunks(scan)
    parts: dict[int, list[dict[str, np.ndarray]]] = {cid: [] for cid in scan.channels}
    for buf, sel in iter_blocks(scan, set(scan.channels)):
        for cid, rec in sel.items():
            cols = record_columns(buf, rec)
            cols["data"] = copy_ranges(buf, cols["start"], cols["length"])
            parts[cid].append(cols)
    return _raw_from_parts(scan, parts)


def _chunk_start_ns(scan: Scan, ch: ChunkRecord) -> int:
    """Return the chunk record's ``message_start_time`` (as the scan read it)."""
    return int(ch.start_ns)


def iter_raw_channels(
    path: str | Path, *, max_messages: int = 200_000
) -> Iterator[tuple[list[RawChannel], int | None]]:
    """:func:`read_raw_channels` range by range, in bounded memory (long recordings).

    Yields
    ------
    (raw_channels, later_min_log_ns)
        Every channel (in channel id order, possibly empty) with the messages of about
        ``max_messages`` messages' worth of MCAP chunks, in file order; and the smallest log
        time any later range can hold (``None`` for the last range), so that a writer can
        flush everything before it (:meth:`pipeline.io.mcap_write.McapColumnWriter.flush`).

    """
    scan = scan_file(path)
    index_chunks(scan)
    # smallest start time of the chunks after each chunk (suffix minimum)
    good = [ch for ch in scan.chunks if not ch.bad and ch.index]
    starts = np.array([_chunk_start_ns(scan, ch) for ch in good], dtype=np.uint64)
    later = np.minimum.accumulate(starts[::-1])[::-1] if len(starts) else starts
    next_of = {id(ch): (int(later[k + 1]) if k + 1 < len(good) else None)
               for k, ch in enumerate(good)}
    parts: dict[int, list[dict[str, np.ndarray]]] = {cid: [] for cid in scan.channels}

    def add(buf: NDArray[np.uint8], sel: dict[int, np.ndarray]) -> int:
        for cid, rec in sel.items():
            cols = record_columns(buf, rec)
            cols["data"] = copy_ranges(buf, cols["start"], cols["length"])
            parts[cid].append(cols)
        return sum(len(r) for r in sel.values())

    # top-level messages of an unchunked file: all in the first range
    count = 0
    for cid in sorted(scan.top_messages.keys() & scan.channels.keys()):
        count += add(scan.buf, {cid: np.asarray(scan.top_messages[cid], dtype=np.int64)})
    pending = count > 0
    for ch in good:
        # the same steps as iter_blocks, chunk by chunk, to know where each range ends
        b = decompress_chunk(scan, ch)
        if b is not None:
            buf = np.frombuffer(b, dtype=np.uint8)
            count += add(buf, select_messages(scan, ch, buf, set(scan.channels)))
            pending = True
        release_pages(scan, ch.data_start, ch.data_len)
        bound = next_of[id(ch)]
        if count >= max_messages and bound is not None and not scan.top_messages:
            yield _raw_from_parts(scan, parts), bound
            parts = {cid: [] for cid in scan.channels}
            count, pending = 0, False
    if pending or count == 0:
        yield _raw_from_parts(scan, parts), None


# --------------------------------------------------------------------------- public
# --------------------------------------------------------------------------- pass-through
@dataclass(frozen=True)
class PassThroughChunk:
    """One Chunk record of an intact input and the MessageIndex records after it, as bytes.

    ``record`` and ``message_indexes`` are views of the file's bytes (nothing decompressed);
    ``mi_offsets`` gives each channel's MessageIndex record as an offset from the start of
    ``record``.
    """

    record: NDArray[np.uint8]
    message_indexes: NDArray[np.uint8]
    start_ns: int
    end_ns: int
    compression: str
    compressed_size: int
    uncompressed_size: int
    mi_offsets: dict[int, int]
    counts: dict[int, int]
    release: Callable[[], None]


@dataclass(frozen=True)
class PassThrough:
    """An input whose chunks can be copied as they are (:func:`pass_through`)."""

    schemas: dict[int, tuple[str, str, bytes]]
    channels: dict[int, tuple[str, str, int, dict[str, str]]]
    chunks: list[PassThroughChunk]


#: chunk compressions another MCAP reader understands as they are
PASS_THROUGH_COMPRESSIONS = ("zstd", "lz4", "")


def pass_through(path: str | Path) -> PassThrough | None:
    """Return the input's chunks for copying without decompressing them, or None.

    Only for an intact, indexed file: a footer, no problem found while scanning it, no
    top-level messages, every chunk complete with its MessageIndex records right after it
    (one per channel it holds, all channels known) and a compression every reader knows.
    Anything else returns None and the caller copies message by message
    (:func:`iter_raw_channels`), which recovers what a damaged file still holds. The chunks'
    contents are not decompressed here: their CRCs are checked by whoever reads them.
    """
    with warnings.catch_warnings():  # a damaged file is reported by the other path
        warnings.simplefilter("ignore")
        scan = scan_file(path)
    if scan.problems or scan.top_messages or not scan.chunks:
        return None
    if 0 in scan.schemas or 0 in scan.channels:
        return None  # ids the writer does not give out (0 means "no schema")
    chunks = []
    for ch in scan.chunks:
        if (ch.bad or ch.torn or not ch.index_trusted or not ch.index or not ch.mi_pos
                or ch.compression not in PASS_THROUGH_COMPRESSIONS
                or set(ch.mi_pos) != set(ch.index)
                or any(c not in scan.channels for c in ch.index)):
            return None
        end = ch.data_start + ch.data_len
        if min(ch.mi_pos.values()) != end:
            return None  # something between the chunk and its indexes

        def release(ch: ChunkRecord = ch) -> None:
            release_pages(scan, ch.offset, ch.mi_end - ch.offset)

        chunks.append(PassThroughChunk(
            record=scan.buf[ch.offset:end], message_indexes=scan.buf[end:ch.mi_end],
            start_ns=_chunk_start_ns(scan, ch),
            end_ns=int(ch.end_ns),
            compression=ch.compression, compressed_size=ch.data_len,
            uncompressed_size=ch.uncompressed_size,
            mi_offsets={c: p - ch.offset for c, p in ch.mi_pos.items()},
            counts={c: len(v) for c, v in ch.index.items()}, release=release))
    # the chunks are copied from the file's bytes: the message offsets (8 bytes a message)
    # and the pages read to find the chunks are not needed any more
    for ch in scan.chunks:
        ch.index = None
    release_pages(scan, 0, len(scan.buf))
    return PassThrough(
        schemas={i: (x.name, x.encoding, bytes(x.data)) for i, x in scan.schemas.items()},
        channels={i: (c.topic, c.message_encoding, c.schema_id, dict(c.metadata))
                  for i, c in scan.channels.items()},
        chunks=chunks)


def read_recording(
    path: str | Path,
    *,
    mag_topic: str | None = None,
    attitude_topic: str | None = None,
    turntable_topic: str | None = None,
    position_topic: str | None = None,
) -> Recording:
    """Read a magnetometer and its attitude source from an MCAP file.

    Parameters
    ----------
    path : path
        MCAP file (never modified).
    mag_topic, attitude_topic, turntable_topic : str, optional
        Channels to use; by default the single channel of a supported type for each role.
    position_topic : str, optional
        The position channel (``sensor_msgs/msg/NavSatFix``); by default the recording's only
        one. With two or more and no choice, none is used and a ``position_ambiguous``
        problem names them.

    Returns
    -------
    Recording
        ``mag`` in nT, frame ``mag``; ``attitude`` as ``q_enu_body``; ``turntable`` as an
        unwrapped angle in rad. Samples sorted by header stamp; what was dropped or repaired
        is listed in ``problems``. ``position``: the position channel's fixes as local ENU
        metres about the first valid fix (``origin``), on its own stamps, NaN rows where a
        fix was lost; that channel wins over positions the attitude channel carries
        (``PoseStamped``, ``Odometry``, INSPVA), which are used only when there is no
        position channel chosen or it holds no valid fix.

    Raises
    ------
    NotMcapError, CorruptRecordingError, ChannelError, SchemaError, DataQualityError
        ``ChannelError`` also when ``position_topic`` names no channel, ``SchemaError`` when
        it names one that is not a position type (both name the file).

    Warns
    -----
    RecoveredDataWarning
        When a damaged file was read only in part (the message says what was lost).

    """
    scan = scan_file(path)
    index_chunks(scan)
    p = scan.path
    pos_id = pick_position(scan, position_topic, scan.problems)
    mag_id = pick_channel(scan, Role.MAGNETOMETER, mag_topic, True)
    att_id = pick_channel(scan, Role.ATTITUDE, attitude_topic, False)
    try:
        tt_id = pick_channel(scan, Role.TURNTABLE, turntable_topic, att_id is None)
    except ChannelError as exc:
        if att_id is not None:
            tt_id = None
            scan.problems.append(Problem("turntable_ambiguous", exc.message))
        elif "no turntable" in exc.message:
            raise ChannelError(exc.message.replace("turntable", "attitude (or turntable)"),
                               role=Role.ATTITUDE.value, path=p, hint=exc.hint) from None
        else:
            raise
    ids = [i for i in (mag_id, att_id, tt_id, pos_id) if i is not None]
    dec = decode_channels(scan, ids)
    counts = {cid: len(dec[cid].t_ns) for cid in ids}
    stamps = {cid: dec[cid].t_ns for cid in ids}
    # The body frame's name: an Imu message's frame_id is the IMU's own frame (REP-145); the
    # frame_id of a pose, a quaternion or an INS solution names the reference frame instead.
    att_frame = ("" if att_id is None
                 or type_of(scan, scan.channels[att_id]).replace("/msg/", "/") != "sensor_msgs/Imu"
                 else dec[att_id].frame_id)
    problems = scan.problems
    d_mag = dec.pop(mag_id)  # popped: checks that copy the columns free the originals
    if len(d_mag.t_ns) == 0:
        raise CorruptRecordingError(f"no readable magnetometer messages on "
                                    f"{scan.channels[mag_id].topic}", path=p,
                                    hint="the recording is damaged or empty")
    mag_name = scan.channels[mag_id].topic
    d_mag = check_channel(Role.MAGNETOMETER, mag_name, d_mag, problems, p)
    mag = VectorSeries(d_mag.t_ns, d_mag.values, Frame.MAG, "nT")
    gap_problems(mag_name, mag.t_ns, problems)
    attitude = None
    position = None
    if att_id is not None:
        name = scan.channels[att_id].topic
        d = check_channel(Role.ATTITUDE, name, dec.pop(att_id), problems, p)
        if len(d.t_ns) < MIN_ATTITUDE_SAMPLES:
            raise DataQualityError(f"{name}: only {len(d.t_ns)} usable attitude samples",
                                   path=p, hint="the recording is too short to calibrate")
        attitude = AttitudeSeries(d.t_ns, d.values)
        position = position_series(d)
        gap_problems(name, attitude.t_ns, problems, min_gap_s=0.1)
    turntable = None
    if tt_id is not None:
        name = scan.channels[tt_id].topic
        d = check_channel(Role.TURNTABLE, name, dec.pop(tt_id), problems, p)
        if attitude is None and len(d.t_ns) < MIN_ATTITUDE_SAMPLES:
            raise DataQualityError(f"{name}: only {len(d.t_ns)} usable turntable samples",
                                   path=p, hint="the recording is too short to calibrate")
        turntable = AngleSeries(d.t_ns, np.unwrap(np.radians(d.values)))
    if pos_id is not None:
        name = scan.channels[pos_id].topic
        d = check_channel(Role.POSITION, name, dec.pop(pos_id), problems, p)
        gap_problems(name, d.t_ns, problems)
        fixes = position_series(d, fixes=True)
        if fixes is not None:  # the position channel wins over the attitude's positions
            position = fixes
    mag_ch = scan.channels[mag_id]
    return Recording(
        path=p,
        channels=channel_infos(scan, counts, stamps),
        mag=mag,
        mag_topic=mag_ch.topic,
        attitude=attitude,
        attitude_topic=None if att_id is None else scan.channels[att_id].topic,
        encoding=EncodingFamily.JSON if mag_ch.message_encoding == "json"
        else EncodingFamily.ROS2,
        turntable=turntable,
        mag_frame_id=d_mag.frame_id,
        attitude_frame_id=att_frame,
        problems=tuple(problems),
        position=position,
    )


def pick_position(scan: Scan, topic: str | None, problems: list[Problem]) -> int | None:
    """Channel id of the position channel, or None.

    By ``topic`` (an error naming the file when it is absent or not a position type), else
    the single channel of a position type. Positions are optional: two or more candidates
    and no choice is a ``position_ambiguous`` problem, not an error (the command line has no
    option to choose one yet, and the recording calibrates without positions).
    """
    try:
        return pick_channel(scan, Role.POSITION, topic, False)
    except ChannelError as exc:
        if topic is not None:
            raise
        problems.append(Problem("position_ambiguous", f"{exc.message}: no position channel "
                                f"was used ({exc.hint})"))
        return None


def position_series(d: DecodedColumns, *, fixes: bool = False, keep_lost: bool = False
                     ) -> PositionSeries | None:
    """Return a channel's positions (NaN rows kept), or None without any.

    ``PoseStamped`` / ``Odometry`` positions are in the source's own frame: a local frame
    whose third axis is up but whose horizontal axes need not be east and north (a
    motion-capture room), frame ``attitude_source_local``, no origin. Geodetic fixes
    (``NavSatFix``, INSPVA) become WGS-84 local ENU metres about the first valid fix in stamp
    order, which is the series' ``origin`` (:func:`geodetic_to_local_enu`).

    An attitude channel whose position fields are all zero or all NaN carries none (a writer
    that fills the field with zeros); the fields as written are tested, not the local metres,
    which are zero wherever a platform stands at its first fix (a survey that starts with a
    calibration turn in place). A position channel (``fixes``: ``NavSatFix``) has positions
    as soon as one fix is valid (a receiver standing still reads zeros about its own first
    fix); with ``keep_lost`` even without a valid fix it gives its stamps with NaN rows and no
    origin (a receiver without a fix yet still says that the recording has positions).
    """
    if d.position is None or len(d.t_ns) == 0:
        return None
    origin = None
    if d.position_kind == "geodetic":
        lat, lon, h = d.position[:, 0], d.position[:, 1], d.position[:, 2]
        origin = first_valid_fix(lat, lon, h)
        p = geodetic_to_local_enu(lat, lon, h, origin=origin)
        frame = PositionFrame.ENU
    else:
        p = np.asarray(d.position, dtype=float)
        frame = PositionFrame.ATTITUDE_SOURCE_LOCAL
    fin = np.isfinite(p).all(axis=1)
    written = np.asarray(d.position, dtype=float)[fin]
    if not (fixes and keep_lost) and (not fin.any() or (not fixes and not np.any(written != 0.0))):
        return None
    return PositionSeries(d.t_ns, p, frame, origin)


def problem_warnings(path: str | Path, problems: tuple[Problem, ...] | list[Problem],
                     said: set[str] | frozenset[str] = frozenset()) -> list[str]:
    """Messages of the problems a user has not heard yet, each naming the file.

    Parameters
    ----------
    path : path
        The recording the problems are in.
    problems : sequence of Problem
        ``Recording.problems``.
    said : set of str
        Messages already issued as warnings (damage found while scanning the file is warned
        by the reader itself).

    Returns
    -------
    list of str
        One line per problem, in order, starting with ``path``.

    """
    out = []
    for pr in problems:
        if pr.message in said:
            continue
        out.append(pr.message if pr.message.startswith(str(path)) else f"{path}: {pr.message}")
    return out


def read_recording_warning(path: str | Path, **kw: Any) -> Recording:
    """:func:`read_recording`, with every problem it handled also issued as a warning.

    Damage found while scanning the file is warned by the reader itself; what it repaired in
    the data (dropped NaN or duplicated samples, sorted stamps, gaps) is only listed in
    ``Recording.problems``, and the user must still hear what was lost. Used by the
    ``calibrate`` and ``diagnose`` commands (``pipeline.run.runner.analyse_recording``);
    ``process`` collects the same messages in its worker processes
    (:func:`pipeline.run.runner.process_recording`).

    Warns
    -----
    RecoveredDataWarning
        Once per problem.

    """
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            rec = read_recording(path, **kw)
    finally:
        # also when the read fails: the damage met on the way may be why
        for w in caught:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    said = {str(w.message) for w in caught}
    for msg in problem_warnings(path, rec.problems, said):
        warnings.warn(msg, RecoveredDataWarning, stacklevel=2)
    return rec


def _rate_hz(t: np.ndarray) -> float | None:
    if len(t) < 2:
        return None
    dt = np.diff(t)
    if int(dt.min()) <= 0:  # (strictly increasing stamps need neither sort nor filter)
        if int(dt.min()) < 0:
            dt = np.diff(np.sort(t))
        dt = dt[dt > 0]
    if not len(dt):
        return None
    # dt is this function's own array: the median may partition it in place
    return float(1e9 / np.median(dt, overwrite_input=True))


def channel_infos(scan: Scan, counts: dict[int, int], stamps: dict[int, np.ndarray]
                   ) -> tuple[ChannelInfo, ...]:
    """Return what ``info`` lists of each channel: topic, type, role, count and rate."""
    out = []
    for cid in sorted(scan.channels):
        c = scan.channels[cid]
        out.append(ChannelInfo(c.topic, type_of(scan, c), c.message_encoding,
                               role_of(scan, c), counts.get(cid, -1) if cid in counts else -1,
                               _rate_hz(stamps[cid]) if cid in stamps else None))
    return tuple(out)


def inspect_recording(path: str | Path, mag_probe: Callable[[str, np.ndarray, np.ndarray],
                                                             dict[str, Any] | None] | None = None
                      ) -> dict:
    """Describe a recording for ``magalign info``: channels, counts, rates, problems.

    Stamps are header stamps for supported types and log times for other channels.
    Nothing is refused here except files that are not MCAP at all: problems are listed.
    They are the damage found in the file (cut, chunks failing their CRC or not
    decompressing), the stamp checks of every channel (backwards, duplicated, gaps) and, for
    magnetometer, attitude, turntable and position channels, the value checks of
    :func:`read_recording` (NaN/Inf, zero or non-unit quaternions, clock jumps, saturation,
    lost or missing position fixes; what it would refuse is listed with code ``unusable``).

    Returns
    -------
    dict
        ``{"path", "profile", "channels": [{topic, type, encoding, role, count, rate_hz,
        start_ns, end_ns}], "duration_s", "problems": [{code, message, count}],
        "sample_hold"}`` (``sample_hold``: what ``mag_probe(topic, t_ns, values)`` says of
        the magnetometer channel's decoded samples, None without a probe; the reader knows
        no model: ``magalign info`` passes the sample-and-hold detector).

    """
    scan = scan_file(path)
    index_chunks(scan)
    problems: list[Problem] = []  # per channel; scan.problems grows while chunks are decoded
    stamps: dict[int, np.ndarray] = {}
    chans: list[dict[str, Any]] = []
    held: dict[str, Any] | None = None
    for cid in sorted(scan.channels):
        c = scan.channels[cid]
        role = role_of(scan, c)
        t = None
        if role is not Role.OTHER:
            try:
                dec = decode_channels(scan, [cid])[cid]
            except InputError as exc:
                problems.append(Problem("undecodable", exc.message))
            else:
                t = dec.t_ns
                problems += value_problems(scan, role, c.topic, dec)
                if role is Role.MAGNETOMETER and held is None and mag_probe is not None:
                    held = mag_probe(c.topic, dec.t_ns, dec.values)
        if t is None:
            log = [record_columns(buf, sel[cid])["log_time_ns"]
                   for buf, sel in iter_blocks(scan, {cid})]
            t = np.concatenate(log) if log else np.zeros(0, np.int64)
        stamps[cid] = t
        back = int(np.count_nonzero(np.diff(t) < 0))
        if back:
            problems.append(Problem("out_of_order", f"{c.topic}: {back} stamps going "
                                    "backwards", back))
        ts = np.sort(t)
        dup = int(np.count_nonzero(np.diff(ts) == 0))
        if dup:
            problems.append(Problem("duplicate", f"{c.topic}: {dup} duplicated stamps", dup))
        gap_problems(c.topic, ts, problems, min_gap_s=1.0 if role is Role.MAGNETOMETER
                      else 0.1)
        chans.append({
            "topic": c.topic, "type": type_of(scan, c), "encoding": c.message_encoding,
            "role": role.value, "count": int(len(t)), "rate_hz": _rate_hz(t),
            "start_ns": int(ts[0]) if len(ts) else None,
            "end_ns": int(ts[-1]) if len(ts) else None,
        })
    starts = [c["start_ns"] for c in chans if c["start_ns"] is not None]
    ends = [c["end_ns"] for c in chans if c["end_ns"] is not None]
    mags = [c for c in chans if c["role"] == Role.MAGNETOMETER.value and c["count"] > 1]
    span = (mags[0]["start_ns"], mags[0]["end_ns"]) if mags else None
    for cid, row in zip(sorted(scan.channels), chans, strict=True):
        if row["role"] == Role.ATTITUDE.value:
            attitude_gap_problems(row["topic"], np.sort(stamps[cid]), problems, span)
    if mags:
        duration = (mags[0]["end_ns"] - mags[0]["start_ns"]) * 1e-9
    else:
        duration = (max(ends) - min(starts)) * 1e-9 if starts else 0.0
    return {
        "path": scan.path,
        "profile": scan.profile,
        "channels": chans,
        "duration_s": float(duration),
        "problems": [{"code": p.code, "message": p.message, "count": p.count}
                     for p in [*scan.problems, *problems]],
        "sample_hold": held,
    }


# --------------------------------------------------------------------------- chunked reading
@dataclass(frozen=True)
class RecordingChunk:
    """The samples of one range of MCAP chunks (see :func:`iter_recording_chunks`).

    Attributes
    ----------
    index : int
        0, 1, 2, ... in file order.
    mag : VectorSeries
        Magnetometer samples of the range, nT, frame ``mag``, sorted by stamp, non-finite
        samples dropped.
    attitude : AttitudeSeries or None
        Attitude samples of the range (unit quaternions ``q_enu_body``), sorted by stamp.
    turntable : AngleSeries or None
        Turntable angle samples of the range (rad, not unwrapped across chunks).
    position : PositionSeries or None
        Positions of the range: the position channel's (``NavSatFix``) when the recording has
        one, else those the attitude channel carries; geodetic fixes in local ENU about the
        recording's first valid fix (the same origin in every range). Rows without a valid
        position are left out. Whether the recording has positions at all is the header's
        to say (:func:`pipeline.io.mcap_header.read_recording_header`).

    """

    index: int
    mag: VectorSeries
    attitude: AttitudeSeries | None
    turntable: AngleSeries | None
    position: PositionSeries | None = None


def _chunk_part(dec: DecodedColumns | None, quat: bool) -> DecodedColumns | None:
    if dec is None:
        return None
    ok = finite_rows(dec.values)
    if not quat and dec.values.ndim == 2 and dec.position_kind != "geodetic":
        # damaged values (a flipped exponent bit) would overflow the streaming sums
        with np.errstate(over="ignore", invalid="ignore"):
            ok &= np.abs(dec.values).max(axis=1, initial=0.0) < ABSURD_NT
    if quat:
        norm = quat_norm(np.where(ok[:, None], dec.values, 0.0))
        ok &= norm > 1e-6
    kept = dec.take(ok)
    if quat:
        kept = DecodedColumns(kept.t_ns, kept.values / norm[ok][:, None], kept.log_time_ns,
                        kept.frame_id, kept.position, kept.position_kind)
    return kept.take(np.argsort(kept.t_ns, kind="stable"))


class _ChunkPositions:
    """Each range's positions, in one frame over the whole recording.

    Geodetic fixes become local ENU about the recording's first valid fix (the ranges come
    in time order, so the first range with a valid fix holds it), as :func:`read_recording`
    places them; metres in the attitude source's frame are taken as they are.
    """

    def __init__(self) -> None:
        self.origin: GeodeticOrigin | None = None

    def series(self, d: DecodedColumns | None) -> PositionSeries | None:
        if d is None or d.position is None or not len(d.t_ns):
            return None
        if d.position_kind != "geodetic":
            return PositionSeries(d.t_ns, np.asarray(d.position, float),
                                  PositionFrame.ATTITUDE_SOURCE_LOCAL)
        lat, lon, h = d.position[:, 0], d.position[:, 1], d.position[:, 2]
        if self.origin is None:
            self.origin = first_valid_fix(lat, lon, h)
        if self.origin is None:  # no valid fix yet: the rows are lost positions
            return PositionSeries(d.t_ns, np.full((len(d.t_ns), 3), np.nan), PositionFrame.ENU)
        return PositionSeries(d.t_ns, geodetic_to_local_enu(lat, lon, h, origin=self.origin),
                              PositionFrame.ENU, self.origin)


def iter_recording_chunks(
    path: str | Path,
    *,
    max_messages: int = 200_000,
    mag_topic: str | None = None,
    attitude_topic: str | None = None,
    turntable_topic: str | None = None,
    position_topic: str | None = None,
) -> Iterator[RecordingChunk]:
    """Read a recording range by range, in bounded memory, for files too large for memory.

    The file is memory-mapped (:data:`MMAP_MIN_BYTES`), and its MCAP chunks are decoded in
    file order, in groups of about ``max_messages`` messages (a whole number of MCAP chunks,
    decoded at once: :func:`pipeline.io.mcap_decode.decoded_batches`), each handed out as
    one range. Channels are chosen as by :func:`read_recording`. Only the
    per-sample checks are made (non-finite values dropped, quaternions normalised, zero
    quaternions dropped, each range sorted by stamp); whole-recording checks (duplicates,
    clock jumps, gaps, stuck sensor) need the whole recording: use :func:`read_recording`
    when it fits in memory.

    Parameters
    ----------
    path : path
        MCAP file (never modified).
    max_messages : int
        Messages of the chosen channels per yielded range (at least one MCAP chunk).
    mag_topic, attitude_topic, turntable_topic, position_topic : str, optional
        Channels to use.

    Yields
    ------
    RecordingChunk

    Raises
    ------
    NotMcapError, CorruptRecordingError, ChannelError, SchemaError

    """
    scan = scan_file(path)
    index_chunks(scan)
    mag_id = pick_channel(scan, Role.MAGNETOMETER, mag_topic, True)
    att_id = pick_channel(scan, Role.ATTITUDE, attitude_topic, False)
    tt_id = None
    if att_id is None or turntable_topic is not None:
        tt_id = pick_channel(scan, Role.TURNTABLE, turntable_topic, att_id is None)
    # positions are optional: an ambiguous choice is the header's problem to report
    pos_id = pick_position(scan, position_topic, [])
    ids = [i for i in (mag_id, att_id, tt_id, pos_id) if i is not None]
    parts: dict[int, list[DecodedColumns]] = {cid: [] for cid in ids}
    index = 0
    positions = _ChunkPositions()

    def emit() -> RecordingChunk:
        cat: dict[int, DecodedColumns | None] = {}
        for cid in ids:
            ps = parts[cid]
            if not ps:
                cat[cid] = None
                continue
            pos = (np.concatenate([p.position for p in ps])
                   if all(p.position is not None for p in ps) else None)
            cat[cid] = DecodedColumns(np.concatenate([p.t_ns for p in ps]),
                                np.concatenate([p.values for p in ps]),
                                np.concatenate([p.log_time_ns for p in ps]), ps[0].frame_id,
                                pos, ps[0].position_kind)
            parts[cid] = []
        m = _chunk_part(cat[mag_id], False)
        a = _chunk_part(cat.get(att_id) if att_id is not None else None, True)
        tt = _chunk_part(cat.get(tt_id) if tt_id is not None else None, False)
        fx = _chunk_part(cat.get(pos_id) if pos_id is not None else None, False)
        return RecordingChunk(
            index=index,
            mag=VectorSeries(m.t_ns, m.values, Frame.MAG, "nT") if m is not None
            else VectorSeries(np.zeros(0, np.int64), np.zeros((0, 3)), Frame.MAG, "nT"),
            attitude=None if a is None or not len(a.t_ns) else AttitudeSeries(a.t_ns, a.values),
            turntable=None if tt is None or not len(tt.t_ns)
            else AngleSeries(tt.t_ns, np.radians(tt.values)),
            position=positions.series(fx if pos_id is not None else a),
        )

    for batch, ends in decoded_batches(scan, ids, max_messages):
        for cid, ds in batch.items():
            parts[cid] += ds
        if ends:
            yield emit()
            index += 1
    if any(parts.values()):
        yield emit()

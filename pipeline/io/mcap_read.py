"""Vectorised MCAP reading: chunks straight into numpy, recovery of damaged files.

How a file is read
------------------
1. **Scan** the top-level records from the start (:func:`_scan`). The file is in memory and
   only record headers are touched (a chunk is skipped by its length), so this costs a few
   hundred Python steps for a file of millions of messages. It finds schemas and channels
   (in the data section or the summary), chunk records and the ``MessageIndex`` records
   that follow each chunk, and top-level messages of non-chunked files. The same scan serves
   an intact file and a damaged one: a file cut by a crash (no footer, no summary, a torn
   last record) is read up to its last complete record, a torn last chunk is decompressed as
   far as its bytes go (streaming zstd/lz4) and its complete records are kept.
2. **Decode** chunk by chunk (:func:`_iter_blocks`): decompress (zstd, lz4 or none), check
   the CRC, take message record offsets from the message indexes (``numpy.frombuffer`` of
   ``(u64 log_time, u64 offset)`` pairs) or, when the indexes are missing, walk the chunk's
   records; then gather the payload fields of all messages of a channel at once with
   fancy indexing (:class:`pipeline.io.cdr.CdrLayout`). No Python object is made per message
   for ROS 2 CDR channels; JSON channels are parsed with one ``json.loads`` per chunk.

Everything lost is listed as a :class:`~pipeline.core.recording.Problem` and announced with a
:class:`~pipeline.core.errors.RecoveredDataWarning`. Data that cannot be trusted raises an
:class:`~pipeline.core.errors.InputError` subclass (exit status 2 at the command line).

Stamps are header stamps (CONVENTIONS), ``log_time`` only for messages without a header.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import mmap
import struct
import warnings
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np
from numpy.typing import NDArray

from pipeline.core.errors import (
    ChannelError,
    CorruptRecordingError,
    DataQualityError,
    InputError,
    NotMcapError,
    RecoveredDataWarning,
    SchemaError,
)
from pipeline.core.geometry import li2020_euler_to_quat, novatel_to_quat
from pipeline.core.recording import (
    AngleSeries,
    AttitudeSeries,
    ChannelInfo,
    EncodingFamily,
    Frame,
    PositionFrame,
    PositionSeries,
    Problem,
    Recording,
    Role,
    VectorSeries,
)
from pipeline.io.cdr import CdrLayout, gather_le, normalise_type, stamp_ns
from pipeline.io.mcap_format import MAGIC, MAX_OPCODE, Opcode
from schemas import MESSAGE_TYPES, MessageRole, types_of

#: message types by role, as normalised schema names (``pkg/Type`` or magalign.*), from the one
#: table of supported types (``schemas.MESSAGE_TYPES``)
MAG_TYPES = tuple(MESSAGE_TYPES[n].short_name for n in types_of(MessageRole.MAGNETOMETER))
ATTITUDE_TYPES = tuple(MESSAGE_TYPES[n].short_name for n in types_of(MessageRole.ATTITUDE))
TURNTABLE_TYPES = tuple(MESSAGE_TYPES[n].short_name for n in types_of(MessageRole.TURNTABLE))

# CDR field paths of the orientation and of the position an attitude message carries (the
# position is read when the stored definition has it); INSPVA's geodetic fix is converted to
# local ENU after sorting (first fix origin)
_CDR_QUAT = {t.short_name: t.quaternion for t in MESSAGE_TYPES.values() if t.quaternion}
_CDR_POSITION = {t.short_name: t.position for t in MESSAGE_TYPES.values() if t.position}
_INSPVA_FIX = ("latitude", "longitude", "height")
#: WGS84 semi-major axis (m) and first eccentricity squared
_WGS84_A_M = 6378137.0
_WGS84_E2 = 6.69437999014e-3

#: Plausible range of the median field magnitude. The Earth's field is 20,000-70,000 nT; an
#: indoor MEMS sensor near steel reads somewhat off that (the lab data: ~43,800 nT), so only
#: values off by more than a factor of ~20 are refused: those are unit mistakes.
FIELD_MIN_NT = 1_000.0
FIELD_MAX_NT = 200_000.0
#: stamps that differ from the logger's receive time by more than this (beyond the median
#: difference) are taken as clock jumps and dropped
STAMP_JUMP_NS = 3600 * 1_000_000_000
MIN_MAG_SAMPLES = 10
#: magnetometer samples larger than this many times the median field magnitude are damaged
#: values, not readings (a sensor's range is at most some 30 times the Earth's field)
SPIKE_FACTOR = 100.0
#: no magnetometer reads this (1000 T): a value beyond it is damage (chunked reading, which
#: has no median to compare with, drops such samples)
ABSURD_NT = 1e12
MIN_ATTITUDE_SAMPLES = 2


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


@dataclass
class _Schema:
    id: int
    name: str
    encoding: str
    data: bytes


@dataclass
class _Channel:
    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict


@dataclass
class _Chunk:
    offset: int  # file offset of the chunk record
    compression: str
    data_start: int  # file offset of the (compressed) records
    data_len: int  # bytes of compressed records present in the file
    uncompressed_size: int
    crc: int
    torn: bool = False
    index: dict[int, np.ndarray] | None = None  # channel id -> message record offsets
    index_trusted: bool = False
    bad: bool = False


@dataclass
class _Scan:
    path: str
    buf: NDArray[np.uint8]
    profile: str = ""
    schemas: dict[int, _Schema] = field(default_factory=dict)
    channels: dict[int, _Channel] = field(default_factory=dict)
    chunks: list[_Chunk] = field(default_factory=list)
    top_messages: dict[int, list[int]] = field(default_factory=dict)
    problems: list[Problem] = field(default_factory=list)
    complete_bytes: int = 0  # bytes up to the end of the last complete record
    mapped: Any = None  # the mmap.mmap when the file is memory-mapped


def _release(scan: _Scan, start: int, length: int) -> None:
    """Drop the mapped pages of ``[start, start + length)`` from this process's memory.

    The file stays mapped (a later access reads the pages again, usually from the page
    cache); this keeps the resident size of a long recording to about one chunk.
    """
    if scan.mapped is None or not hasattr(mmap, "MADV_DONTNEED"):
        return
    page = mmap.PAGESIZE
    lo = (start // page) * page
    hi = start + length
    if hi > lo:
        try:
            scan.mapped.madvise(mmap.MADV_DONTNEED, lo, min(hi, len(scan.mapped)) - lo)
        except (OSError, ValueError):
            pass  # advice only


# --------------------------------------------------------------------------- helpers
def _u(buf: NDArray[np.uint8], pos: NDArray[np.int64], dtype: str) -> np.ndarray:
    """Vectorised little-endian read of ``dtype`` at byte positions ``pos``."""
    dt = np.dtype(dtype)
    if dt.itemsize == 1:
        return buf[pos]
    return gather_le(buf, pos, dt)


def _str(b: bytes | mmap.mmap, p: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", b, p)
    if p + 4 + n > len(b):
        raise ValueError("string runs past its record")
    return b[p + 4 : p + 4 + n].decode("utf-8", "replace"), p + 4 + n


def _parse_schema(b: bytes | mmap.mmap, p: int) -> _Schema:
    (sid,) = struct.unpack_from("<H", b, p)
    name, p = _str(b, p + 2)
    enc, p = _str(b, p)
    (n,) = struct.unpack_from("<I", b, p)
    return _Schema(sid, name, enc, bytes(b[p + 4 : p + 4 + n]))


def _parse_channel(b: bytes | mmap.mmap, p: int) -> _Channel:
    cid, sid = struct.unpack_from("<HH", b, p)
    topic, p = _str(b, p + 4)
    enc, p = _str(b, p)
    (n,) = struct.unpack_from("<I", b, p)
    end = p + 4 + n
    p += 4
    meta = {}
    while p < end:
        k, p = _str(b, p)
        v, p = _str(b, p)
        meta[k] = v
    return _Channel(cid, sid, topic, enc, meta)


def _problem(scan_problems: list[Problem], code: str, message: str, count: int = 0,
             warn: bool = True) -> None:
    scan_problems.append(Problem(code, message, count))
    if warn:
        warnings.warn(message, RecoveredDataWarning, stacklevel=4)


# --------------------------------------------------------------------------- scanning
#: files at least this large are memory-mapped instead of read: pages are then loaded as the
#: chunks are decoded and can be dropped by the OS again, so a recording larger than the
#: memory can be read chunk by chunk (:func:`iter_recording_chunks`)
MMAP_MIN_BYTES = 64 << 20


def _map_file(p: Path) -> bytes | mmap.mmap:
    """Return the file's bytes: read into memory, or memory-mapped read-only when large."""
    size = p.stat().st_size
    if size < MMAP_MIN_BYTES:
        return p.read_bytes()
    with open(p, "rb") as fh:
        return mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)


def open_error(path: str | Path, exc: OSError) -> InputError:
    """Return the one-line error of a file that cannot be opened (reader and CLI alike)."""
    p = Path(path)
    if isinstance(exc, FileNotFoundError):
        return InputError("no such file", path=p)
    if isinstance(exc, IsADirectoryError):
        return InputError("is a folder, not an MCAP file", path=p)
    return InputError(f"cannot read: {exc.strerror}", path=p)


def check_magic(head: bytes, path: str | Path) -> None:
    """Refuse a file whose first bytes (``head``, 8 or fewer) are not MCAP's magic.

    Raises
    ------
    NotMcapError
        Empty, not starting with the magic bytes, or cut inside them.

    """
    p = Path(path)
    head = bytes(head[: len(MAGIC)])
    if not head:
        raise NotMcapError("empty file (0 bytes)", path=p,
                           hint="the logger may have crashed before writing anything")
    if head != MAGIC[: len(head)]:
        raise NotMcapError("not an MCAP file (bad magic bytes)", path=p,
                           hint="pass a .mcap recording")
    if len(head) < len(MAGIC):
        raise NotMcapError(f"cut inside the MCAP header ({len(head)} bytes)", path=p,
                           hint="nothing can be recovered from this file")


def _scan(path: str | Path) -> _Scan:
    """Read the file and list its top-level records (see the module docstring)."""
    p = Path(path)
    try:
        raw = _map_file(p)
    except OSError as exc:
        raise open_error(p, exc) from None
    size = len(raw)
    check_magic(raw[: len(MAGIC)], p)
    scan = _Scan(str(p), np.frombuffer(raw, dtype=np.uint8),
                 mapped=raw if isinstance(raw, mmap.mmap) else None)
    pos = 8
    ended = False  # footer seen
    data_end = False
    last_chunk: _Chunk | None = None
    last_chunk_index: dict[int, np.ndarray] = {}
    saw_header = False
    while pos < size:
        if pos + 9 > size:
            break
        op = raw[pos]
        (length,) = struct.unpack_from("<Q", raw, pos + 1)
        body = pos + 9
        if op == 0 or (op > MAX_OPCODE and op < 0x80) or length > size:
            if pos + 9 + length <= size or op == 0:
                _problem(scan.problems, "corrupt_record",
                         f"{p}: unreadable record at byte {pos} (opcode {op:#x}); "
                         f"the {size - pos} bytes from there on were ignored", 0)
                scan.complete_bytes = pos
                return _finish_scan(scan, last_chunk, last_chunk_index, pos, size, True)
            break
        if body + length > size:
            break  # torn record: handled below
        if not saw_header:
            if op != Opcode.HEADER:
                raise NotMcapError("MCAP magic without a header record", path=p)
            saw_header = True
            scan.profile, _ = _str(raw, body)
        if op != Opcode.MESSAGE_INDEX and last_chunk is not None:
            last_chunk.index = last_chunk_index or None
            last_chunk.index_trusted = bool(last_chunk_index)
            last_chunk, last_chunk_index = None, {}
        try:
            if op == Opcode.SCHEMA:
                s = _parse_schema(raw, body)
                scan.schemas.setdefault(s.id, s)
            elif op == Opcode.CHANNEL:
                c = _parse_channel(raw, body)
                scan.channels.setdefault(c.id, c)
            elif op == Opcode.MESSAGE and not data_end:
                if length < 22:  # shorter than a message's fixed fields: not a message
                    _problem(scan.problems, "short_record",
                             f"{p}: message record at byte {pos} is too short ({length} "
                             "bytes); it was skipped", 1)
                else:
                    (cid,) = struct.unpack_from("<H", raw, body)
                    scan.top_messages.setdefault(cid, []).append(pos)
            elif op == Opcode.CHUNK and not data_end:
                last_chunk = _chunk_header(raw, pos, body, length, size)
                scan.chunks.append(last_chunk)
            elif op == Opcode.MESSAGE_INDEX and last_chunk is not None:
                (cid, n) = struct.unpack_from("<HI", raw, body)
                pairs = np.frombuffer(raw, dtype="<u8", count=n // 8, offset=body + 6)
                last_chunk_index[cid] = np.sort(pairs[1::2].astype(np.int64))
            elif op == Opcode.DATA_END:
                data_end = True
            elif op == Opcode.FOOTER:
                ended = True
                pos = body + length
                break
        except (struct.error, ValueError) as exc:
            _problem(scan.problems, "corrupt_record",
                     f"{p}: malformed record at byte {pos} ({exc}); the {size - pos} bytes "
                     "from there on were ignored")
            scan.complete_bytes = pos
            return _finish_scan(scan, last_chunk, last_chunk_index, pos, size, True)
        pos = body + length
    scan.complete_bytes = pos
    if not saw_header:
        raise NotMcapError(f"cut inside the MCAP header ({size} bytes)", path=p,
                           hint="nothing can be recovered from this file")
    if ended and raw[pos : pos + 8] != MAGIC:
        _problem(scan.problems, "truncated", f"{p}: the closing magic bytes after the footer "
                 "are missing or damaged; every record was read", 0)
    return _finish_scan(scan, last_chunk, last_chunk_index, pos, size, not ended,
                        data_end=data_end)


def _chunk_header(raw: bytes | mmap.mmap, pos: int, body: int, length: int, size: int) -> _Chunk:
    start_t, end_t, usize, crc = struct.unpack_from("<QQQI", raw, body)
    comp, p = _str(raw, body + 28)
    (rlen,) = struct.unpack_from("<Q", raw, p)
    avail = min(rlen, size - (p + 8))
    return _Chunk(pos, comp, p + 8, avail, usize, crc, torn=avail < rlen)


def _finish_scan(scan: _Scan, last_chunk: _Chunk | None, last_index: dict, pos: int,
                 size: int, truncated: bool, data_end: bool = False) -> _Scan:
    raw = scan.buf
    if last_chunk is not None:
        # a chunk whose index list may have been cut: walk the chunk instead
        last_chunk.index = last_index or None
        last_chunk.index_trusted = False
    if truncated and not any(pr.code == "corrupt_record" for pr in scan.problems):
        lost = size - pos
        torn_chunk = None
        if pos + 9 <= size and raw[pos] == Opcode.CHUNK:
            try:
                torn_chunk = _chunk_header(raw[pos : pos + 64 + 4096].tobytes(), 0, 9,
                                           0, size - pos)
            except (struct.error, ValueError):
                torn_chunk = None
            if torn_chunk is not None:
                torn_chunk.offset += pos
                torn_chunk.data_start += pos
                torn_chunk.torn = True
                scan.chunks.append(torn_chunk)
        if data_end:
            msg = (f"{scan.path}: file ends before its footer (cut after the data section); "
                   "all messages were read, the summary was lost")
        elif torn_chunk is not None:
            msg = (f"{scan.path}: file cut inside a chunk at byte {size}; read up to the last "
                   f"complete record of that chunk (the file's last {lost} bytes hold a torn "
                   "chunk; messages after the cut are lost)")
        else:
            msg = (f"{scan.path}: file cut at byte {size} (no footer); read the first {pos} "
                   f"bytes up to the last complete record, {lost} trailing bytes lost")
        _problem(scan.problems, "truncated", msg, lost)
    return scan


# --------------------------------------------------------------------------- chunks
def _inflate(scan: _Scan, ch: _Chunk) -> tuple[bytes | None, str, str]:
    """Decompress a chunk and check its CRC: ``(bytes or None, problem kind, detail)``.

    Touches nothing shared (it runs on worker threads, see :func:`_decompressed`); a torn
    chunk is decompressed as far as its bytes go.
    """
    comp = scan.buf[ch.data_start : ch.data_start + ch.data_len].tobytes()
    try:
        if ch.compression == "":
            out = comp
        elif ch.compression == "zstd":
            import zstandard

            if ch.torn:
                out = zstandard.ZstdDecompressor().decompressobj().decompress(comp)
            else:
                out = zstandard.ZstdDecompressor().decompress(
                    comp, max_output_size=ch.uncompressed_size)
        elif ch.compression == "lz4":
            import lz4.frame

            if ch.torn:
                out = lz4.frame.LZ4FrameDecompressor().decompress(comp)
            else:
                out = lz4.frame.decompress(comp)
        else:
            return None, "chunk_compression", ""
    except Exception as exc:  # zstd/lz4 raise their own error types  # noqa: BLE001
        if ch.torn:
            return b"", "", ""
        return None, "chunk_undecompressable", str(exc)
    if not ch.torn and (len(out) != ch.uncompressed_size
                        or (ch.crc and zlib.crc32(out) != ch.crc)):
        return None, "chunk_crc", ""
    return out, "", ""


def _report(scan: _Scan, ch: _Chunk, result: tuple[bytes | None, str, str]) -> bytes | None:
    """Note the problem of an inflated chunk (in file order, on the reading thread)."""
    out, kind, detail = result
    if out is not None:
        return out
    ch.bad = True
    what = {"chunk_compression": f"uses unknown compression {ch.compression!r}",
            "chunk_undecompressable": f"does not decompress ({detail})",
            "chunk_crc": "fails its CRC check"}[kind]
    n = _index_count(ch)
    _problem(scan.problems, kind, f"{scan.path}: chunk at byte {ch.offset} {what}; its "
             f"{n} messages were skipped", n if isinstance(n, int) else 0)
    return None


def _decompress(scan: _Scan, ch: _Chunk) -> bytes | None:
    """Decompress a chunk's records (None, with its problem noted, when it cannot be read)."""
    return _report(scan, ch, _inflate(scan, ch))


DECOMPRESS_THREADS = 2
"""Threads inflating chunks ahead of the decoding (zstd, lz4 and zlib's CRC release the GIL)."""

DECOMPRESS_AHEAD = 8
"""Chunks inflated ahead of the one being decoded (memory: that many chunks)."""


def _decompressed(scan: _Scan, chunks: list[_Chunk]) -> Iterator[tuple[_Chunk, bytes | None]]:
    """``(chunk, its records or None)`` in file order, inflated on threads ahead of use.

    Problems are noted here, in file order, so that messages come out the same whatever the
    threads' timing.
    """
    if len(chunks) < 3 or DECOMPRESS_THREADS < 2:
        for ch in chunks:
            yield ch, _decompress(scan, ch)
        return
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=DECOMPRESS_THREADS,
                            thread_name_prefix="magalign-inflate") as ex:
        it = iter(chunks)
        pending = deque((ch, ex.submit(_inflate, scan, ch))
                        for ch in itertools.islice(it, DECOMPRESS_AHEAD))
        while pending:
            ch, fut = pending.popleft()
            nxt = next(it, None)
            if nxt is not None:
                pending.append((nxt, ex.submit(_inflate, scan, nxt)))
            yield ch, _report(scan, ch, fut.result())


def _index_count(ch: _Chunk) -> int | str:
    if ch.index is None:
        return "(unknown number of)"
    return int(sum(len(v) for v in ch.index.values()))


def _walk(scan: _Scan, b: bytes) -> tuple[dict[int, np.ndarray], int]:
    """Walk the records of a decompressed chunk: schemas/channels and message offsets.

    Returns the message record offsets by channel and the end of the last complete record.
    """
    msgs: dict[int, list[int]] = {}
    pos, n = 0, len(b)
    while pos + 9 <= n:
        op = b[pos]
        (length,) = struct.unpack_from("<Q", b, pos + 1)
        body = pos + 9
        if body + length > n or op == 0:
            break
        try:
            if op == Opcode.MESSAGE:
                if length < 22:
                    break
                (cid,) = struct.unpack_from("<H", b, body)
                msgs.setdefault(cid, []).append(pos)
            elif op == Opcode.SCHEMA:
                s = _parse_schema(b, body)
                scan.schemas.setdefault(s.id, s)
            elif op == Opcode.CHANNEL:
                c = _parse_channel(b, body)
                scan.channels.setdefault(c.id, c)
        except (struct.error, ValueError):
            break
        pos = body + length
    return {k: np.asarray(v, dtype=np.int64) for k, v in msgs.items()}, pos


def _prepare(scan: _Scan) -> None:
    """Walk the chunks whose message indexes are missing, unsure, or name unknown channels.

    Fills ``chunk.index`` so that every chunk can then be decoded from offsets alone, and
    registers channels that live only inside chunks.
    """
    for ch in scan.chunks:
        if ch.bad:
            continue
        unknown = ch.index is not None and any(c not in scan.channels for c in ch.index)
        if ch.index_trusted and not unknown and not ch.torn:
            continue
        b = _decompress(scan, ch)
        if b is None:
            continue
        idx, end = _walk(scan, b)
        if ch.torn:
            got = sum(len(v) for v in idx.values())
            scan.problems.append(Problem(
                "torn_chunk", f"{scan.path}: {got} messages recovered from the torn last "
                f"chunk ({end} of its {ch.uncompressed_size} uncompressed bytes)", got))
        ch.index = idx
        ch.index_trusted = True


def _valid_records(buf: NDArray[np.uint8], off: np.ndarray, cid: int) -> np.ndarray:
    """Mask of the offsets ``off`` that hold a whole Message record of channel ``cid``.

    A record is whole when its opcode is Message, its length covers the fixed fields (22
    bytes) and it ends inside ``buf``; the channel id in the record must be ``cid``.
    """
    n = len(buf)
    inside = (off >= 0) & (off + 31 <= n)
    ok = np.zeros(len(off), dtype=bool)
    o = off[inside]
    if len(o):
        length = _u(buf, o + 1, "<u8")
        room = (n - 9 - o).astype(np.uint64)
        ok[inside] = ((buf[o] == Opcode.MESSAGE) & (length >= 22) & (length <= room)
                      & (_u(buf, o + 9, "<u2") == cid))
    return ok


def _select(scan: _Scan, ch: _Chunk, buf: NDArray[np.uint8], want: set[int]
            ) -> dict[int, np.ndarray]:
    """Message record offsets of the wanted channels in one decompressed chunk.

    The message indexes stored after a chunk are not covered by its CRC: an offset that does
    not point at a whole Message record of its channel means the index is damaged, and the
    chunk is then walked record by record instead (one problem noted, nothing lost).
    """
    assert ch.index is not None  # only chunks with an index are selected from
    sel = {}
    damaged = False
    for cid in want & ch.index.keys():
        off = ch.index[cid]
        ok = _valid_records(buf, off, cid)
        if not ok.all():
            damaged = True
            break
        if len(off):
            sel[cid] = off
    if not damaged:
        return sel
    idx, _ = _walk(scan, buf.tobytes())
    ch.index = idx
    _problem(scan.problems, "damaged_index",
             f"{scan.path}: the message index of the chunk at byte {ch.offset} does not match "
             "its records; the chunk was read record by record instead", 0)
    return {cid: idx[cid] for cid in want & idx.keys() if len(idx[cid])}


def _iter_blocks(scan: _Scan, want: set[int], batch_bytes: int = 0
                 ) -> Iterator[tuple[NDArray[np.uint8], dict[int, np.ndarray]]]:
    """Yield ``(buffer, {channel id: message record offsets})`` for the wanted channels.

    ``batch_bytes`` > 0 joins consecutive chunks into blocks of about that many decompressed
    bytes (whole-recording reads: a logger's chunks hold a few hundred kB, and decoding each
    on its own spent most of the time in per-call overhead, issue 18); 0 yields one block per
    chunk (the chunked readers, whose memory bound is a chunk).
    """
    for cid in sorted(want & scan.top_messages.keys()):
        yield scan.buf, {cid: np.asarray(scan.top_messages[cid], dtype=np.int64)}
    bufs: list[bytes] = []
    sels: list[dict[int, np.ndarray]] = []
    size = 0
    todo = [ch for ch in scan.chunks
            if not ch.bad and ch.index and (want & ch.index.keys())]
    for ch, b in _decompressed(scan, todo):
        if b is None:
            continue
        sel = _select(scan, ch, np.frombuffer(b, dtype=np.uint8), want)
        _release(scan, ch.data_start, ch.data_len)  # decompressed: the bytes are not needed
        if not sel:
            continue
        bufs.append(b)
        sels.append(sel)
        size += len(b)
        if size >= batch_bytes:
            yield _join_blocks(bufs, sels)
            bufs, sels, size = [], [], 0
    if bufs:
        yield _join_blocks(bufs, sels)


BATCH_BYTES = 8 << 20
"""Decompressed bytes decoded at once (memory: about twice this, whatever the file size)."""


def _join_blocks(bufs: list[bytes], sels: list[dict[int, np.ndarray]]
                 ) -> tuple[NDArray[np.uint8], dict[int, np.ndarray]]:
    """One buffer of several decompressed chunks, with their record offsets shifted into it."""
    if len(bufs) == 1:
        return np.frombuffer(bufs[0], dtype=np.uint8), sels[0]
    base = np.cumsum([0] + [len(b) for b in bufs[:-1]])
    joined: dict[int, list[np.ndarray]] = {}
    for b0, sel in zip(base.tolist(), sels, strict=True):
        for cid, off in sel.items():
            joined.setdefault(cid, []).append(off + b0)
    buf = np.frombuffer(b"".join(bufs), dtype=np.uint8)
    return buf, {cid: np.concatenate(v) for cid, v in joined.items()}


def _compact_records(buf: NDArray[np.uint8], rec: np.ndarray
                     ) -> tuple[NDArray[np.uint8], np.ndarray]:
    """Copy the records at ``rec`` side by side when they all have one length.

    A sensor's messages usually have one size. One gather of whole records (each a ``V{n}``
    value) then replaces a dozen field gathers scattered over a large buffer: the field reads
    that follow walk a compact array in order, which the CPU's caches serve (issue 18: 2-3x
    faster ingest). Records of several sizes are returned as they are.
    """
    if len(rec) < 2:
        return buf, rec
    reclen = _u(buf, rec + 1, "<u8")
    n = int(reclen[0]) + 9
    if n > 1 << 16 or not bool((reclen == reclen[0]).all()) or int(rec.max()) + n > len(buf):
        return buf, rec
    view: np.ndarray = np.ndarray(shape=(len(buf) - n + 1,), dtype=f"V{n}",
                                  buffer=np.ascontiguousarray(buf), strides=(1,))
    compact = view[rec].view(np.uint8).reshape(-1)
    return compact, np.arange(len(rec), dtype=np.int64) * n


def _record_columns(buf: NDArray[np.uint8], rec: np.ndarray) -> dict[str, np.ndarray]:
    """Message record fields at record offsets ``rec`` (opcode position), vectorised."""
    reclen = _u(buf, rec + 1, "<u8").astype(np.int64)
    return {
        "sequence": _u(buf, rec + 11, "<u4"),
        "log_time_ns": _u(buf, rec + 15, "<u8").astype(np.int64),
        "publish_time_ns": _u(buf, rec + 23, "<u8").astype(np.int64),
        "start": rec + 31,
        "length": reclen - 22,
    }


def ranges_mask(size: int, start: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Boolean mask of ``size`` bytes, True inside the sorted, disjoint ``[start, start+length)``.

    Built as alternating runs (gap, range, gap, ...) with one ``np.repeat``: about one byte
    of work per output byte, no per-byte index arithmetic.
    """
    end = start + length
    runs = np.empty(2 * len(start) + 1, dtype=np.int64)
    runs[0] = start[0]
    runs[2:-1:2] = start[1:] - end[:-1]
    runs[1:-1:2] = length
    runs[-1] = size - end[-1]
    pattern = np.zeros(len(runs), dtype=np.bool_)
    pattern[1::2] = True
    return np.repeat(pattern, runs)


def _copy_ranges(buf: NDArray[np.uint8], start: np.ndarray, length: np.ndarray,
                 sep: int | None = None) -> NDArray[np.uint8]:
    """Concatenate ``buf[start_i:start_i + length_i]``, each followed by ``sep`` if given."""
    n = len(start)
    if n == 0:
        return np.zeros(0, dtype=np.uint8)
    length = length.astype(np.int64)
    payload = int(length.sum())
    start = start.astype(np.int64)
    if sep is None and (n == 1 or bool(np.all(np.diff(start) >= length[:-1]))):
        # ranges in order and disjoint (message records of one chunk): select the bytes with a
        # mask; no index array of one int64 per byte
        return buf[ranges_mask(len(buf), start, length)]
    # offset of each byte within its own range, without a Python loop
    within = np.arange(payload, dtype=np.int64) - np.repeat(np.cumsum(length) - length, length)
    src = np.repeat(start.astype(np.int64), length) + within
    if sep is None:
        return buf[src]
    dest = np.zeros(n, dtype=np.int64)
    dest[1:] = np.cumsum(length + 1)[:-1]
    out = np.full(payload + n, sep, dtype=np.uint8)
    out[np.repeat(dest, length) + within] = buf[src]
    return out


# --------------------------------------------------------------------------- raw channels
def _raw_from_parts(scan: _Scan, parts: dict[int, list[dict[str, np.ndarray]]]
                    ) -> list[RawChannel]:
    out = []
    for cid in sorted(scan.channels):
        c = scan.channels[cid]
        s = scan.schemas.get(c.schema_id, _Schema(0, "", "", b""))
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
    scan = _scan(path)
    _prepare(scan)
    parts: dict[int, list[dict[str, np.ndarray]]] = {cid: [] for cid in scan.channels}
    for buf, sel in _iter_blocks(scan, set(scan.channels)):
        for cid, rec in sel.items():
            cols = _record_columns(buf, rec)
            cols["data"] = _copy_ranges(buf, cols["start"], cols["length"])
            parts[cid].append(cols)
    return _raw_from_parts(scan, parts)


def _chunk_start_ns(scan: _Scan, ch: _Chunk) -> int:
    """Return the chunk record's ``message_start_time``."""
    return int(scan.buf[ch.offset + 9 : ch.offset + 17].view("<u8")[0])


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
    scan = _scan(path)
    _prepare(scan)
    # smallest start time of the chunks after each chunk (suffix minimum)
    good = [ch for ch in scan.chunks if not ch.bad and ch.index]
    starts = np.array([_chunk_start_ns(scan, ch) for ch in good], dtype=np.uint64)
    later = np.minimum.accumulate(starts[::-1])[::-1] if len(starts) else starts
    next_of = {id(ch): (int(later[k + 1]) if k + 1 < len(good) else None)
               for k, ch in enumerate(good)}
    parts: dict[int, list[dict[str, np.ndarray]]] = {cid: [] for cid in scan.channels}

    def add(buf: NDArray[np.uint8], sel: dict[int, np.ndarray]) -> int:
        for cid, rec in sel.items():
            cols = _record_columns(buf, rec)
            cols["data"] = _copy_ranges(buf, cols["start"], cols["length"])
            parts[cid].append(cols)
        return sum(len(r) for r in sel.values())

    # top-level messages of an unchunked file: all in the first range
    count = 0
    for cid in sorted(scan.top_messages.keys() & scan.channels.keys()):
        count += add(scan.buf, {cid: np.asarray(scan.top_messages[cid], dtype=np.int64)})
    pending = count > 0
    for ch in good:
        # the same steps as _iter_blocks, chunk by chunk, to know where each range ends
        b = _decompress(scan, ch)
        if b is not None:
            buf = np.frombuffer(b, dtype=np.uint8)
            count += add(buf, _select(scan, ch, buf, set(scan.channels)))
            pending = True
        _release(scan, ch.data_start, ch.data_len)
        bound = next_of[id(ch)]
        if count >= max_messages and bound is not None and not scan.top_messages:
            yield _raw_from_parts(scan, parts), bound
            parts = {cid: [] for cid in scan.channels}
            count, pending = 0, False
    if pending or count == 0:
        yield _raw_from_parts(scan, parts), None


# --------------------------------------------------------------------------- decoding
@dataclass
class _Decoded:
    """Decoded columns of one channel (stamps in file order)."""

    t_ns: np.ndarray
    values: np.ndarray  # (N,3) nT | (N,4) q_enu_body | (N,) turntable deg
    log_time_ns: np.ndarray
    frame_id: str = ""
    position: np.ndarray | None = None  # (N, 3): metres, or lat deg, lon deg, height m
    position_kind: str = ""  # "local" (metres, the source's frame) or "geodetic"

    def take(self, idx: np.ndarray, values: np.ndarray | None = None) -> _Decoded:
        """Rows ``idx`` (mask or indices) of every column; ``values`` replaces the values."""
        v = self.values[idx] if values is None else values
        pos = None if self.position is None else self.position[idx]
        return _Decoded(self.t_ns[idx], v, self.log_time_ns[idx], self.frame_id, pos,
                        self.position_kind)


def geodetic_to_local_enu(lat_deg: np.ndarray, lon_deg: np.ndarray, h_m: np.ndarray
                          ) -> np.ndarray:
    """Local ENU positions (N, 3), m, of geodetic fixes: flat-earth tangent plane.

    The origin is the first finite fix; east and north are the longitude and latitude
    differences times the WGS84 prime-vertical and meridian radii of curvature at the origin
    (plus its height), up is the height difference. Over a survey of a few kilometres the
    error of the plane is below a metre per ten kilometres (curvature ``d^2 / (2 R)``), far
    below what a field gradient needs.
    """
    lat, lon, h = (np.asarray(a, dtype=float) for a in (lat_deg, lon_deg, h_m))
    out = np.full((lat.shape[0], 3), np.nan)
    ok = np.isfinite(lat) & np.isfinite(lon) & np.isfinite(h)
    if not ok.any():
        return out
    i0 = int(np.argmax(ok))
    phi0 = np.radians(lat[i0])
    w = np.sqrt(1.0 - _WGS84_E2 * np.sin(phi0) ** 2)
    r_n = _WGS84_A_M / w  # prime vertical
    r_m = _WGS84_A_M * (1.0 - _WGS84_E2) / w**3  # meridian
    dlon = (lon - lon[i0] + 180.0) % 360.0 - 180.0
    out[:, 0] = np.radians(dlon) * (r_n + h[i0]) * np.cos(phi0)
    out[:, 1] = np.radians(lat - lat[i0]) * (r_m + h[i0])
    out[:, 2] = h - h[i0]
    out[~ok] = np.nan
    return out


class _Decoder:
    """Decoder of one channel's payloads, built from the schema stored in the file."""

    def __init__(self, scan: _Scan, ch: _Channel):
        self.path = scan.path
        self.topic = ch.topic
        sch = scan.schemas.get(ch.schema_id)
        if sch is None:
            raise SchemaError(f"channel {ch.topic} refers to schema id {ch.schema_id}, which "
                              "the file does not define", path=scan.path)
        self.type = normalise_type(sch.name)
        self.encoding = ch.message_encoding
        self.layout: CdrLayout | None = None
        self.validator: Any = None
        if ch.message_encoding == "cdr":
            if sch.encoding != "ros2msg":
                raise SchemaError(f"channel {ch.topic}: schema encoding {sch.encoding!r} is "
                                  "not supported (only ros2msg)", path=scan.path)
            try:
                self.layout = CdrLayout(sch.name, sch.data.decode("utf-8"))
            except SchemaError as exc:
                raise SchemaError(exc.message, path=scan.path) from None
            except UnicodeDecodeError:
                raise SchemaError(f"channel {ch.topic}: schema text is not UTF-8",
                                  path=scan.path) from None
            self.paths = self._cdr_paths()
        elif ch.message_encoding == "json":
            if sch.encoding == "jsonschema" and sch.data:
                import jsonschema

                try:
                    schema_doc = json.loads(sch.data)
                    cls = jsonschema.validators.validator_for(schema_doc)
                    self.validator = cls(schema_doc)
                except (ValueError, jsonschema.SchemaError) as exc:
                    raise SchemaError(f"channel {ch.topic}: stored JSON Schema is invalid "
                                      f"({exc})", path=scan.path) from None
        else:
            raise SchemaError(f"channel {ch.topic}: message encoding {ch.message_encoding!r}"
                              " is not supported (cdr or json)", path=scan.path)

    def _cdr_paths(self) -> list[str]:
        assert self.layout is not None  # called for CDR channels, once the layout is built
        t = self.type
        if t == "sensor_msgs/MagneticField":
            return ["header.stamp.sec", "header.stamp.nanosec", "header.frame_id",
                    "magnetic_field.x", "magnetic_field.y", "magnetic_field.z"]
        if t == "sensor_msgs/Imu":
            return ["header.stamp.sec", "header.stamp.nanosec", "header.frame_id"] + [
                f"orientation.{k}" for k in "xyzw"]
        if t in _CDR_QUAT:
            q = _CDR_QUAT[t]
            out = ["header.stamp.sec", "header.stamp.nanosec"] + [f"{q}.{k}" for k in "xyzw"]
            pp = _CDR_POSITION.get(t)
            if pp is not None and self.layout.has_field(f"{pp}.x"):
                out += [f"{pp}.{k}" for k in "xyz"]
            return out
        if t == "novatel_oem7_msgs/INSPVA":
            out = ["header.stamp.sec", "header.stamp.nanosec", "roll", "pitch", "azimuth"]
            if all(self.layout.has_field(k) for k in _INSPVA_FIX):
                out += list(_INSPVA_FIX)
            return out
        if t == "std_msgs/Float64":
            return ["data"]
        raise SchemaError(f"channel {self.topic}: message type {self.type} is not supported",
                          path=self.path, hint=_SUPPORTED_HINT)

    def decode(self, buf: NDArray[np.uint8], rec: np.ndarray) -> _Decoded:
        buf, rec = _compact_records(buf, rec)
        cols = _record_columns(buf, rec)
        log = cols["log_time_ns"]
        if self.layout is not None:
            try:
                f = self.layout.decode(buf, cols["start"], cols["length"], self.paths)
            except SchemaError as exc:
                raise SchemaError(f"channel {self.topic}: {exc.message}",
                                  path=self.path) from None
            return self._from_cdr(f, log, buf)
        return self._from_json(buf, cols, log)

    def _from_cdr(self, f: dict[str, np.ndarray], log: np.ndarray, buf: np.ndarray
                  ) -> _Decoded:
        t = self.type
        if t == "std_msgs/Float64":
            return _Decoded(log, f["data"].astype(float), log)  # no header: log time
        t_ns = stamp_ns(f["header.stamp.sec"], f["header.stamp.nanosec"])
        if t == "sensor_msgs/MagneticField":
            v = np.stack([f[f"magnetic_field.{k}"] for k in "xyz"], axis=-1) * 1e9
            s0, n0 = f["header.frame_id"][0]
            frame = bytes(buf[s0 : s0 + max(n0 - 1, 0)]).decode("utf-8", "replace")
            return _Decoded(t_ns, v, log, frame)
        if t == "sensor_msgs/Imu":  # its frame_id names the IMU's own (body) frame
            s0, n0 = f["header.frame_id"][0]
            frame = bytes(buf[s0 : s0 + max(n0 - 1, 0)]).decode("utf-8", "replace")
            return _Decoded(t_ns, np.stack([f[f"orientation.{k}"] for k in "xyzw"], axis=-1),
                            log, frame)
        if t in _CDR_QUAT:
            qp = _CDR_QUAT[t]
            pp = _CDR_POSITION.get(t)
            pos = (np.stack([f[f"{pp}.{k}"] for k in "xyz"], axis=-1)
                   if pp is not None and f"{pp}.x" in f else None)
            return _Decoded(t_ns, np.stack([f[f"{qp}.{k}"] for k in "xyzw"], axis=-1), log,
                            position=pos, position_kind="local" if pos is not None else "")
        q = novatel_to_quat(f["roll"], f["pitch"], f["azimuth"])
        if "latitude" in f:
            fix = np.stack([f[k] for k in _INSPVA_FIX], axis=-1).astype(float)
            return _Decoded(t_ns, q, log, position=fix, position_kind="geodetic")
        return _Decoded(t_ns, q, log)

    def _from_json(self, buf: np.ndarray, cols: dict, log: np.ndarray) -> _Decoded:
        joined = _copy_ranges(buf, cols["start"], cols["length"], sep=ord(","))
        try:
            text = b"[" + joined[:-1].tobytes() + b"]"
            objs = json.loads(text)
        except ValueError as exc:
            raise SchemaError(f"channel {self.topic}: messages are not valid JSON ({exc})",
                              path=self.path) from None
        if self.validator is not None and objs:
            # a sample (first, middle, last) is validated: enough to catch a wrong layout
            for o in (objs[0], objs[len(objs) // 2], objs[-1]):
                err = next(iter(self.validator.iter_errors(o)), None)
                if err is not None:
                    raise SchemaError(f"channel {self.topic}: message does not match the "
                                      f"stored JSON Schema: {err.message}", path=self.path)
        t = self.type
        try:
            t_ns = (np.array([o["t_ns"] for o in objs], dtype=np.int64)
                    if objs and "t_ns" in objs[0] else log)
            if t == "magalign.Magnetometer":
                v = np.array([o["mag_nT"] for o in objs], dtype=float).reshape(-1, 3)
                frame = str(objs[0].get("frame_id", "")) if objs else ""
                return _Decoded(t_ns, v, log, frame)
            if t == "magalign.AttitudeQuaternion":
                q = np.array([o["q_enu_body"] for o in objs], dtype=float).reshape(-1, 4)
                return _Decoded(t_ns, q, log)
            if t == "magalign.AttitudeEuler":
                hpr = np.array([[o["heading_deg"], o["pitch_deg"], o["roll_deg"]]
                                for o in objs], dtype=float).reshape(-1, 3)
                r = np.radians(hpr)
                return _Decoded(t_ns, li2020_euler_to_quat(r[:, 0], r[:, 1], r[:, 2]), log)
            if t == "magalign.Turntable":
                return _Decoded(t_ns, np.array([o["angle_deg"] for o in objs], dtype=float),
                                log)
        except (KeyError, TypeError, ValueError) as exc:
            raise SchemaError(f"channel {self.topic}: message lacks field {exc}",
                              path=self.path) from None
        raise SchemaError(f"channel {self.topic}: message type {t} is not supported",
                          path=self.path, hint=_SUPPORTED_HINT)


_SUPPORTED_HINT = "supported: " + ", ".join(MAG_TYPES + ATTITUDE_TYPES + TURNTABLE_TYPES)


def _decode_channels(scan: _Scan, cids: list[int]) -> dict[int, _Decoded]:
    decoders = {cid: _Decoder(scan, scan.channels[cid]) for cid in cids}
    # Upper bound of each channel's message count, from the message indexes: the columns are
    # filled chunk by chunk into arrays of that size (one copy of the data, where collecting
    # the chunks' columns and concatenating them held two).
    cap = {cid: len(scan.top_messages.get(cid, ())) + sum(
        len(ch.index.get(cid, ())) for ch in scan.chunks if not ch.bad and ch.index)
        for cid in cids}
    cols: dict[int, list[np.ndarray]] = {}
    fill = dict.fromkeys(cids, 0)
    frames = dict.fromkeys(cids, "")
    kinds = dict.fromkeys(cids, "")
    for buf, sel in _iter_blocks(scan, set(cids), BATCH_BYTES):
        for cid, rec in sel.items():
            d = decoders[cid].decode(buf, rec)
            k, i = len(d.t_ns), fill[cid]
            parts: tuple[np.ndarray, ...] = (d.t_ns, d.values, d.log_time_ns)
            if d.position is not None:
                parts += (d.position,)
                kinds[cid] = d.position_kind
            if cid not in cols:
                cols[cid] = [np.empty((max(cap[cid], k),) + a.shape[1:], dtype=a.dtype)
                             for a in parts]
            elif i + k > cols[cid][0].shape[0]:  # more than indexed: grow
                cols[cid] = [np.concatenate([c[:i], np.empty((k,) + c.shape[1:], c.dtype)])
                             for c in cols[cid]]
            for c, a in zip(cols[cid], parts, strict=True):
                c[i : i + k] = a
            fill[cid] = i + k
            frames[cid] = frames[cid] or d.frame_id
    out = {}
    for cid in cids:
        if cid not in cols:
            width = {"sensor_msgs/MagneticField": 3, "magalign.Magnetometer": 3}.get(
                decoders[cid].type, 4)
            shape = (0,) if decoders[cid].type in TURNTABLE_TYPES else (0, width)
            out[cid] = _Decoded(np.zeros(0, np.int64), np.zeros(shape), np.zeros(0, np.int64))
            continue
        n = fill[cid]
        t, v, log, *pos = (c if n == c.shape[0] else c[:n].copy() for c in cols[cid])
        out[cid] = _Decoded(t, v, log, frames[cid], pos[0] if pos else None, kinds[cid])
    return out


# --------------------------------------------------------------------------- roles
def _role_of(scan: _Scan, ch: _Channel) -> Role:
    sch = scan.schemas.get(ch.schema_id)
    t = normalise_type(sch.name) if sch else ""
    if t in MAG_TYPES:
        return Role.MAGNETOMETER
    if t in ATTITUDE_TYPES:
        return Role.ATTITUDE
    if t in TURNTABLE_TYPES:
        return Role.TURNTABLE
    return Role.OTHER


def _type_of(scan: _Scan, ch: _Channel) -> str:
    sch = scan.schemas.get(ch.schema_id)
    return sch.name if sch else "?"


_OPTION = {Role.MAGNETOMETER: ("mag_topic", "--mag"),
           Role.ATTITUDE: ("attitude_topic", "--attitude"),
           Role.TURNTABLE: ("turntable_topic", "--turntable")}


@overload
def _pick(scan: _Scan, role: Role, topic: str | None, required: Literal[True]) -> int: ...


@overload
def _pick(scan: _Scan, role: Role, topic: str | None, required: bool) -> int | None: ...


def _pick(scan: _Scan, role: Role, topic: str | None, required: bool) -> int | None:
    """Channel id for a role: by explicit topic, else the single channel of a matching type."""
    opt, flag = _OPTION[role]
    if topic is not None:
        hits = [c for c in scan.channels.values() if c.topic == topic]
        if not hits:
            topics = ", ".join(sorted({c.topic for c in scan.channels.values()})) or "none"
            raise ChannelError(f"no channel with topic {topic} (topics: {topics})",
                               role=role.value, path=scan.path)
        c = hits[0]
        ok = (MAG_TYPES if role is Role.MAGNETOMETER else ATTITUDE_TYPES
              if role is Role.ATTITUDE else TURNTABLE_TYPES)
        if normalise_type(_type_of(scan, c)) not in ok:
            raise SchemaError(f"channel {topic} has type {_type_of(scan, c)}, which is not a "
                              f"supported {role.value} type", path=scan.path,
                              hint=_SUPPORTED_HINT)
        return c.id
    cands = [c for c in scan.channels.values() if _role_of(scan, c) is role]
    if len(cands) > 1:
        names = " and ".join(sorted(c.topic for c in cands))
        raise ChannelError(f"two or more candidate {role.value} channels: {names}",
                           role=role.value, path=scan.path,
                           hint=f"choose one with {flag} TOPIC ({opt}=...)")
    if not cands:
        if not required:
            return None
        listing = ", ".join(f"{c.topic} ({_type_of(scan, c)})"
                            for c in scan.channels.values()) or "no channels"
        raise ChannelError(f"no {role.value} channel found (channels: {listing})",
                           role=role.value, path=scan.path, hint=_SUPPORTED_HINT)
    return cands[0].id


# --------------------------------------------------------------------------- checks
def _sort_dedupe(name: str, dec: _Decoded, problems: list[Problem], path: str
                 ) -> _Decoded:
    """Drop clock jumps, sort by stamp, drop duplicated stamps; count all in problems."""
    t, log = dec.t_ns, dec.log_time_ns
    if len(t) > 2:
        d = t - log
        jump = np.abs(d - np.median(d)) > STAMP_JUMP_NS
        if jump.any() and not jump.all():
            k = int(jump.sum())
            problems.append(Problem("stamp_jump", f"{name}: {k} samples with stamps more than "
                                    "an hour away from their receive time were dropped", k))
            dec = dec.take(~jump)
            t = dec.t_ns
    back = int(np.count_nonzero(np.diff(t) < 0))
    if back:
        problems.append(Problem("out_of_order", f"{name}: {back} stamps going backwards; "
                                "samples were sorted by stamp", back))
        order = np.argsort(t, kind="stable")
        dec = dec.take(order)
        t = dec.t_ns
    dup = np.concatenate([[False], np.diff(t) == 0]) if len(t) else np.zeros(0, bool)
    if dup.any():
        k = int(dup.sum())
        problems.append(Problem("duplicate", f"{name}: {k} samples with a duplicated stamp "
                                "were dropped (first kept)", k))
        dec = dec.take(~dup)
    return dec


def _finite_rows(values: np.ndarray) -> np.ndarray:
    """Return True for each sample (row, or element of a 1-D column) with finite values.

    Also for a channel with no readable message (shape ``(0,)`` or ``(0, k)``), where a
    ``reshape(0, -1)`` would be ambiguous.
    """
    fin = np.isfinite(values)
    return fin if fin.ndim == 1 else fin.all(axis=tuple(range(1, fin.ndim)))


def _drop_nonfinite(name: str, dec: _Decoded, problems: list[Problem]) -> _Decoded:
    ok = _finite_rows(dec.values)
    if ok.all():
        return dec
    k = int((~ok).sum())
    problems.append(Problem("nonfinite", f"{name}: {k} samples with NaN or Inf values were "
                            "dropped", k))
    return dec.take(ok)


def _quat_norm(q: np.ndarray) -> np.ndarray:
    """Norm of each quaternion without overflow or underflow (damaged values reach 1e308)."""
    with np.errstate(over="ignore", invalid="ignore"):
        n = np.sqrt(np.einsum("ij,ij->i", q, q))
    if bool(((n > 1e-150) & (n < 1e150)).all()):
        return n  # the usual case: one pass, no scaling needed
    m = np.abs(q).max(axis=1) if len(q) else np.zeros(0)
    safe = np.where(m > 0, m, 1.0)
    return m * np.linalg.norm(q / safe[:, None], axis=1)


def _check_quaternions(name: str, dec: _Decoded, problems: list[Problem]) -> _Decoded:
    q = dec.values
    n = _quat_norm(q)
    zero = n < 1e-6
    if zero.any():
        k = int(zero.sum())
        problems.append(Problem("zero_quaternion", f"{name}: {k} zero quaternions were "
                                "dropped", k))
        q, n = q[~zero], n[~zero]
        dec = dec.take(~zero, q)
    off = np.abs(n - 1.0) > 1e-6
    if off.any():
        k = int(off.sum())
        problems.append(Problem("non_unit_quaternion", f"{name}: {k} quaternions were not of "
                                f"unit norm (up to {np.abs(n - 1).max():.3g} off) and were "
                                "normalised", k))
    if q.flags.writeable and q.flags.owndata:
        q /= n[:, None]  # the decoder's own array: normalise in place (no second copy)
    else:
        q = q / n[:, None]
    return dataclasses.replace(dec, values=q)


def _check_mag(path: str, name: str, dec: _Decoded, problems: list[Problem]) -> _Decoded:
    """Refuse unusable magnetometer data; return ``dec`` without samples pinned at a rail.

    A saturated axis reports its extreme value again and again while the true field is
    beyond it; those samples would bias the rotation by degrees, so they are dropped like
    NaN samples (and counted in ``problems``). More than half of the samples pinned is
    refused: what is left cannot be trusted to represent the motion.
    """
    v = dec.values
    if len(v) < MIN_MAG_SAMPLES:
        raise DataQualityError(f"{name}: only {len(v)} usable magnetometer samples",
                               path=path, hint="the recording is too short to calibrate "
                               f"anything (at least {MIN_MAG_SAMPLES} needed)")
    if np.all(v == v[0]):
        raise DataQualityError(f"{name}: every magnetometer sample is identical "
                               f"({v[0].tolist()} nT): the sensor is stuck", path=path,
                               hint="check the sensor and its driver")
    with np.errstate(over="ignore", invalid="ignore"):
        norm_nT = np.sqrt(np.einsum("ij,ij->i", v, v))
    mag_nT = float(np.median(norm_nT))
    if mag_nT > FIELD_MAX_NT or mag_nT < FIELD_MIN_NT:
        if mag_nT > FIELD_MAX_NT:
            hint = ("the values look like microtesla (or gauss) written into a tesla field; "
                    "sensor_msgs/MagneticField must carry tesla (REP-145): convert before "
                    "recording")
        else:
            hint = ("the values look too small for tesla (nanotesla written as tesla?); "
                    "sensor_msgs/MagneticField must carry tesla (REP-145)")
        raise DataQualityError(f"{name}: median field magnitude {mag_nT:.4g} nT is far "
                               "outside the Earth's 20,000-70,000 nT", path=path, hint=hint)
    # a few samples far beyond any field the sensor can see are damaged values (a flipped
    # exponent bit), not readings: dropped like NaN (their squares would overflow the fit)
    with np.errstate(over="ignore"):
        wild = ~(norm_nT <= SPIKE_FACTOR * mag_nT)
    if wild.any():
        k = int(np.count_nonzero(wild))
        problems.append(Problem("impossible_value", f"{name}: {k} samples more than "
                                f"{SPIKE_FACTOR:g} times the median field magnitude were "
                                "dropped (damaged values)", k))
        dec = _Decoded(dec.t_ns[~wild], v[~wild], dec.log_time_ns[~wild], dec.frame_id)
        v = dec.values
        if len(v) < MIN_MAG_SAMPLES:
            raise DataQualityError(f"{name}: only {len(v)} usable magnetometer samples",
                                   path=path, hint="the recording is too short to calibrate "
                                   f"anything (at least {MIN_MAG_SAMPLES} needed)")
    # saturation: many samples pinned at the extreme value of an axis (a rail)
    pinned = np.zeros(len(v), dtype=bool)
    rails: list[str] = []
    for ax in range(3):
        for ext in (v[:, ax].max(), v[:, ax].min()):
            at = v[:, ax] == ext
            k = int(np.count_nonzero(at))
            if k >= max(10, len(v) // 100):
                pinned |= at
                rails.append(f"{k} at {ext:.6g} nT on axis {'xyz'[ax]}")
    if not pinned.any():
        return dec
    k = int(np.count_nonzero(pinned))
    where = "; ".join(rails)
    if k > len(v) / 2:
        raise DataQualityError(
            f"{name}: {k / len(v):.0%} of the magnetometer samples sit at the extreme value "
            f"of an axis ({where}): the sensor is saturated", path=path,
            hint="reduce the sensor's range setting or move it from magnetic sources")
    problems.append(Problem(
        "saturated", f"{name}: {k} samples pinned at the rail of a saturated sensor ({where}) "
        "were dropped", k))
    keep = ~pinned
    return _Decoded(dec.t_ns[keep], v[keep], dec.log_time_ns[keep], dec.frame_id)


def _clean(role: Role, name: str, dec: _Decoded, problems: list[Problem], path: str
           ) -> _Decoded:
    """Run the reader's value checks of one channel, in the order :func:`read_recording` needs.

    Non-finite samples dropped; quaternions (attitude) checked and normalised; clock jumps
    dropped, stamps sorted, duplicates dropped; magnetometer data refused when unusable
    (too short, stuck, wrong unit, saturated) and samples pinned at a rail dropped. Every
    repair is appended to ``problems``. :func:`inspect_recording` runs the same checks.

    Raises
    ------
    DataQualityError
        Magnetometer data that cannot be used at all.

    """
    dec = _drop_nonfinite(name, dec, problems)
    if role is Role.ATTITUDE:
        dec = _check_quaternions(name, dec, problems)
    dec = _sort_dedupe(name, dec, problems, path)
    if role is Role.MAGNETOMETER:
        dec = _check_mag(path, name, dec, problems)
    return dec


def _gap_problems(name: str, t: np.ndarray, problems: list[Problem], min_gap_s: float = 1.0
                  ) -> None:
    if len(t) < 3:
        return
    dt = np.diff(t)
    med = float(np.median(dt))
    big = dt > max(min_gap_s * 1e9, 100 * med)
    if big.any():
        k = int(big.sum())
        longest = float(dt.max()) * 1e-9
        code = "time_jump" if longest > 3600 else "gap"
        limit_s = max(min_gap_s, 100 * med * 1e-9)
        gaps = "gaps" if k > 1 else "gap"
        problems.append(Problem(code, f"{name}: {k} {gaps} longer than {limit_s:.3g} s "
                                f"(longest {longest:.4g} s)", k))


#: an attitude stamp interval longer than this many median intervals has lost samples
ATTITUDE_GAP_FACTOR = 1.5


def attitude_gaps(t_ns: np.ndarray, span_ns: tuple[int, int] | None = None) -> dict | None:
    """Measure the attitude samples missing against the channel's own median rate.

    A gap is a stamp interval longer than :data:`ATTITUDE_GAP_FACTOR` median intervals (a
    motion-capture system losing its markers, an INS dropping messages); it holds
    ``round(interval / median) - 1`` missing samples. With ``span_ns`` (the magnetometer's
    first and last stamp) the stretches of it before the first and after the last attitude
    sample count as missing too: those magnetometer samples have no attitude either.

    Parameters
    ----------
    t_ns : ndarray of int64
        Stamps of the attitude channel, sorted.
    span_ns : (int, int), optional
        First and last magnetometer stamp.

    Returns
    -------
    dict or None
        ``{rate_hz, missing_samples, missing_s, n_gaps, longest_gap_s, gap_samples,
        gap_s, lead_samples, lead_s, trail_samples, trail_s}`` (times in s: ``gap_s`` is
        the time without attitude beyond one median interval per gap), or None when nothing
        is missing or there are fewer than three stamps.

    """
    if len(t_ns) < 3:
        return None
    t = np.asarray(t_ns, dtype=np.int64)
    dt = np.diff(t)
    pos = dt[dt > 0]
    if not len(pos):
        return None
    med = float(np.median(pos))
    g = dt[dt > ATTITUDE_GAP_FACTOR * med].astype(float)
    lead = trail = 0.0
    if span_ns is not None:
        lead = max(0.0, float(t[0] - span_ns[0]))
        trail = max(0.0, float(span_ns[1] - t[-1]))
    out = {
        "rate_hz": 1e9 / med,
        "n_gaps": int(len(g)),
        "longest_gap_s": float(g.max()) * 1e-9 if len(g) else 0.0,
        "gap_samples": int(np.maximum(np.rint(g / med) - 1, 1).sum()),
        "gap_s": float((g - med).sum()) * 1e-9,
        "lead_samples": int(np.rint(lead / med)),
        "lead_s": lead * 1e-9,
        "trail_samples": int(np.rint(trail / med)),
        "trail_s": trail * 1e-9,
    }
    out["missing_samples"] = out["gap_samples"] + out["lead_samples"] + out["trail_samples"]
    out["missing_s"] = out["gap_s"] + (out["lead_s"] if out["lead_samples"] else 0.0) + (
        out["trail_s"] if out["trail_samples"] else 0.0)
    return out if out["missing_samples"] else None


def _attitude_gap_problems(name: str, t_ns: np.ndarray, problems: list[Problem],
                           span_ns: tuple[int, int] | None = None) -> None:
    """Add an ``attitude_gaps`` problem when the attitude lost samples (:func:`attitude_gaps`)."""
    g = attitude_gaps(t_ns, span_ns)
    if g is None:
        return
    where = []
    if g["lead_samples"]:
        where.append(f"{g['lead_samples']:,} in the {g['lead_s']:.3f} s before the first "
                     "attitude sample")
    if g["trail_samples"]:
        where.append(f"{g['trail_samples']:,} in the {g['trail_s']:.3f} s after the last")
    if g["n_gaps"]:
        gaps = "gaps" if g["n_gaps"] > 1 else "gap"
        where.append(f"{g['gap_samples']:,} in {g['n_gaps']:,} {gaps} inside "
                     f"(longest {g['longest_gap_s']:.3g} s)")
    problems.append(Problem(
        "attitude_gaps",
        f"{name}: {g['missing_samples']:,} attitude samples missing against its median rate "
        f"{g['rate_hz']:.4g} Hz ({g['missing_s']:.3f} s of the magnetometer's span without "
        f"attitude): " + "; ".join(where), g["missing_samples"]))


# --------------------------------------------------------------------------- public
def read_recording(
    path: str | Path,
    *,
    mag_topic: str | None = None,
    attitude_topic: str | None = None,
    turntable_topic: str | None = None,
) -> Recording:
    """Read a magnetometer and its attitude source from an MCAP file.

    Parameters
    ----------
    path : path
        MCAP file (never modified).
    mag_topic, attitude_topic, turntable_topic : str, optional
        Channels to use; by default the single channel of a supported type for each role.

    Returns
    -------
    Recording
        ``mag`` in nT, frame ``mag``; ``attitude`` as ``q_enu_body``; ``turntable`` as an
        unwrapped angle in rad. Samples sorted by header stamp; what was dropped or repaired
        is listed in ``problems``.

    Raises
    ------
    NotMcapError, CorruptRecordingError, ChannelError, SchemaError, DataQualityError

    Warns
    -----
    RecoveredDataWarning
        When a damaged file was read only in part (the message says what was lost).

    """
    scan = _scan(path)
    _prepare(scan)
    p = scan.path
    mag_id = _pick(scan, Role.MAGNETOMETER, mag_topic, True)
    att_id = _pick(scan, Role.ATTITUDE, attitude_topic, False)
    try:
        tt_id = _pick(scan, Role.TURNTABLE, turntable_topic, att_id is None)
    except ChannelError as exc:
        if att_id is not None:
            tt_id = None
            scan.problems.append(Problem("turntable_ambiguous", exc.message))
        elif "no turntable" in exc.message:
            raise ChannelError(exc.message.replace("turntable", "attitude (or turntable)"),
                               role=Role.ATTITUDE.value, path=p, hint=exc.hint) from None
        else:
            raise
    ids = [i for i in (mag_id, att_id, tt_id) if i is not None]
    dec = _decode_channels(scan, ids)
    counts = {cid: len(dec[cid].t_ns) for cid in ids}
    stamps = {cid: dec[cid].t_ns for cid in ids}
    # The body frame's name: an Imu message's frame_id is the IMU's own frame (REP-145); the
    # frame_id of a pose, a quaternion or an INS solution names the reference frame instead.
    att_frame = ("" if att_id is None
                 or _type_of(scan, scan.channels[att_id]).replace("/msg/", "/") != "sensor_msgs/Imu"
                 else dec[att_id].frame_id)
    problems = scan.problems
    d_mag = dec.pop(mag_id)  # popped: checks that copy the columns free the originals
    if len(d_mag.t_ns) == 0:
        raise CorruptRecordingError(f"no readable magnetometer messages on "
                                    f"{scan.channels[mag_id].topic}", path=p,
                                    hint="the recording is damaged or empty")
    mag_name = scan.channels[mag_id].topic
    d_mag = _clean(Role.MAGNETOMETER, mag_name, d_mag, problems, p)
    mag = VectorSeries(d_mag.t_ns, d_mag.values, Frame.MAG, "nT")
    _gap_problems(mag_name, mag.t_ns, problems)
    attitude = None
    position = None
    if att_id is not None:
        name = scan.channels[att_id].topic
        d = _clean(Role.ATTITUDE, name, dec.pop(att_id), problems, p)
        if len(d.t_ns) < MIN_ATTITUDE_SAMPLES:
            raise DataQualityError(f"{name}: only {len(d.t_ns)} usable attitude samples",
                                   path=p, hint="the recording is too short to calibrate")
        attitude = AttitudeSeries(d.t_ns, d.values)
        position = _position_series(d)
        _gap_problems(name, attitude.t_ns, problems, min_gap_s=0.1)
    turntable = None
    if tt_id is not None:
        name = scan.channels[tt_id].topic
        d = _clean(Role.TURNTABLE, name, dec.pop(tt_id), problems, p)
        if attitude is None and len(d.t_ns) < MIN_ATTITUDE_SAMPLES:
            raise DataQualityError(f"{name}: only {len(d.t_ns)} usable turntable samples",
                                   path=p, hint="the recording is too short to calibrate")
        turntable = AngleSeries(d.t_ns, np.unwrap(np.radians(d.values)))
    mag_ch = scan.channels[mag_id]
    return Recording(
        path=p,
        channels=_channel_infos(scan, counts, stamps),
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


def _position_series(d: _Decoded) -> PositionSeries | None:
    """Return the attitude channel's positions (NaN rows kept), or None without any.

    ``PoseStamped`` / ``Odometry`` positions are in the source's own frame: a local frame
    whose third axis is up but whose horizontal axes need not be east and north (a
    motion-capture room), frame ``attitude_source_local``. INSPVA fixes become ENU metres on
    the tangent plane at the first fix (:func:`geodetic_to_local_enu`). A channel whose
    positions are all zero or all NaN carries none (a writer that fills the field with zeros).
    """
    if d.position is None or len(d.t_ns) == 0:
        return None
    if d.position_kind == "geodetic":
        p = geodetic_to_local_enu(d.position[:, 0], d.position[:, 1], d.position[:, 2])
        frame = PositionFrame.ENU
    else:
        p = np.asarray(d.position, dtype=float)
        frame = PositionFrame.ATTITUDE_SOURCE_LOCAL
    fin = np.isfinite(p).all(axis=1)
    if not fin.any() or not np.any(p[fin] != 0.0):
        return None
    return PositionSeries(d.t_ns, p, frame)


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
    ``calibrate`` command; ``process`` collects the same messages in its worker processes
    (:func:`pipeline.app.process_one.process_recording`).

    Warns
    -----
    RecoveredDataWarning
        Once per problem.

    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rec = read_recording(path, **kw)
    said = {str(w.message) for w in caught}
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    for msg in problem_warnings(path, rec.problems, said):
        warnings.warn(msg, RecoveredDataWarning, stacklevel=2)
    return rec


def _rate_hz(t: np.ndarray) -> float | None:
    if len(t) < 2:
        return None
    dt = np.diff(np.sort(t))
    dt = dt[dt > 0]
    if not len(dt):
        return None
    return float(1e9 / np.median(dt))


def _channel_infos(scan: _Scan, counts: dict[int, int], stamps: dict[int, np.ndarray]
                   ) -> tuple[ChannelInfo, ...]:
    out = []
    for cid in sorted(scan.channels):
        c = scan.channels[cid]
        out.append(ChannelInfo(c.topic, _type_of(scan, c), c.message_encoding,
                               _role_of(scan, c), counts.get(cid, -1) if cid in counts else -1,
                               _rate_hz(stamps[cid]) if cid in stamps else None))
    return tuple(out)


def inspect_recording(path: str | Path) -> dict:
    """Describe a recording for ``magalign info``: channels, counts, rates, problems.

    Stamps are header stamps for supported types and log times for other channels.
    Nothing is refused here except files that are not MCAP at all: problems are listed.
    They are the damage found in the file (cut, chunks failing their CRC or not
    decompressing), the stamp checks of every channel (backwards, duplicated, gaps) and, for
    magnetometer, attitude and turntable channels, the value checks of
    :func:`read_recording` (NaN/Inf, zero or non-unit quaternions, clock jumps, saturation;
    what it would refuse is listed with code ``unusable``).

    Returns
    -------
    dict
        ``{"path", "profile", "channels": [{topic, type, encoding, role, count, rate_hz,
        start_ns, end_ns}], "duration_s", "problems": [{code, message, count}]}``.

    """
    scan = _scan(path)
    _prepare(scan)
    problems: list[Problem] = []  # per channel; scan.problems grows while chunks are decoded
    stamps: dict[int, np.ndarray] = {}
    chans: list[dict[str, Any]] = []
    for cid in sorted(scan.channels):
        c = scan.channels[cid]
        role = _role_of(scan, c)
        t = None
        if role is not Role.OTHER:
            try:
                dec = _decode_channels(scan, [cid])[cid]
            except InputError as exc:
                problems.append(Problem("undecodable", exc.message))
            else:
                t = dec.t_ns
                problems += _value_problems(scan, role, c.topic, dec)
        if t is None:
            log = [_record_columns(buf, sel[cid])["log_time_ns"]
                   for buf, sel in _iter_blocks(scan, {cid})]
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
        _gap_problems(c.topic, ts, problems, min_gap_s=1.0 if role is Role.MAGNETOMETER
                      else 0.1)
        chans.append({
            "topic": c.topic, "type": _type_of(scan, c), "encoding": c.message_encoding,
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
            _attitude_gap_problems(row["topic"], np.sort(stamps[cid]), problems, span)
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
    }


#: problem codes of :func:`_clean` that :func:`inspect_recording` finds itself for every
#: channel (stamps backwards, duplicated), in words that describe the file, not the repair
_INFO_OWN_CODES = frozenset({"out_of_order", "duplicate"})


def _value_problems(scan: _Scan, role: Role, name: str, dec: _Decoded) -> list[Problem]:
    """List what :func:`read_recording` would repair or refuse in one decoded channel."""
    found: list[Problem] = []
    # _clean may normalise quaternions in place; the caller needs only the stamps, and
    # those are never modified
    try:
        _clean(role, name, dec, found, scan.path)
    except DataQualityError as exc:
        msg = exc.message + (f" ({exc.hint})" if exc.hint else "")
        found.append(Problem("unusable", msg))
    return [pr for pr in found if pr.code not in _INFO_OWN_CODES]


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

    """

    index: int
    mag: VectorSeries
    attitude: AttitudeSeries | None
    turntable: AngleSeries | None


def _chunk_part(dec: _Decoded | None, quat: bool) -> _Decoded | None:
    if dec is None:
        return None
    ok = _finite_rows(dec.values)
    if not quat and dec.values.ndim == 2:
        # damaged values (a flipped exponent bit) would overflow the streaming sums
        with np.errstate(over="ignore", invalid="ignore"):
            ok &= np.abs(dec.values).max(axis=1, initial=0.0) < ABSURD_NT
    if quat:
        norm = _quat_norm(np.where(ok[:, None], dec.values, 0.0))
        ok &= norm > 1e-6
    t, v = dec.t_ns[ok], dec.values[ok]
    if quat:
        v = v / norm[ok][:, None]
    order = np.argsort(t, kind="stable")
    return _Decoded(t[order], v[order], dec.log_time_ns[ok][order], dec.frame_id)


def iter_recording_chunks(
    path: str | Path,
    *,
    max_messages: int = 200_000,
    mag_topic: str | None = None,
    attitude_topic: str | None = None,
    turntable_topic: str | None = None,
) -> Iterator[RecordingChunk]:
    """Read a recording range by range, in bounded memory, for files too large for memory.

    The file is memory-mapped (:data:`MMAP_MIN_BYTES`), its MCAP chunks are decoded in file
    order, and their samples are handed out in groups of about ``max_messages`` messages (a
    whole number of MCAP chunks). Channels are chosen as by :func:`read_recording`. Only the
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
    mag_topic, attitude_topic, turntable_topic : str, optional
        Channels to use.

    Yields
    ------
    RecordingChunk

    Raises
    ------
    NotMcapError, CorruptRecordingError, ChannelError, SchemaError

    """
    scan = _scan(path)
    _prepare(scan)
    mag_id = _pick(scan, Role.MAGNETOMETER, mag_topic, True)
    att_id = _pick(scan, Role.ATTITUDE, attitude_topic, False)
    tt_id = None
    if att_id is None or turntable_topic is not None:
        tt_id = _pick(scan, Role.TURNTABLE, turntable_topic, att_id is None)
    ids = [i for i in (mag_id, att_id, tt_id) if i is not None]
    decoders = {cid: _Decoder(scan, scan.channels[cid]) for cid in ids}
    parts: dict[int, list[_Decoded]] = {cid: [] for cid in ids}
    count, index = 0, 0

    def emit() -> RecordingChunk:
        cat: dict[int, _Decoded | None] = {}
        for cid in ids:
            ps = parts[cid]
            if not ps:
                cat[cid] = None
                continue
            cat[cid] = _Decoded(np.concatenate([p.t_ns for p in ps]),
                                np.concatenate([p.values for p in ps]),
                                np.concatenate([p.log_time_ns for p in ps]), ps[0].frame_id)
            parts[cid] = []
        m = _chunk_part(cat[mag_id], False)
        a = _chunk_part(cat.get(att_id) if att_id is not None else None, True)
        tt = _chunk_part(cat.get(tt_id) if tt_id is not None else None, False)
        return RecordingChunk(
            index=index,
            mag=VectorSeries(m.t_ns, m.values, Frame.MAG, "nT") if m is not None
            else VectorSeries(np.zeros(0, np.int64), np.zeros((0, 3)), Frame.MAG, "nT"),
            attitude=None if a is None or not len(a.t_ns) else AttitudeSeries(a.t_ns, a.values),
            turntable=None if tt is None or not len(tt.t_ns)
            else AngleSeries(tt.t_ns, np.radians(tt.values)),
        )

    for buf, sel in _iter_blocks(scan, set(ids)):
        for cid, rec in sel.items():
            d = decoders[cid].decode(buf, rec)
            parts[cid].append(d)
            count += len(d.t_ns)
        if count >= max_messages:
            yield emit()
            index += 1
            count = 0
    if count:
        yield emit()

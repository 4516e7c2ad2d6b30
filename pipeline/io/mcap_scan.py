"""MCAP scanning and recovery.

The file mapped and walked record by record (``scan_file``): schemas, channels, chunks and their
message indexes; a cut or damaged file recovered up to its last readable record; chunks
inflated on two threads ahead of the decoding and their message records selected in batches.
"""

from __future__ import annotations

import itertools
import mmap
import struct
import threading
import warnings
import zlib
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lz4.frame
import numpy as np
import zstandard
from numpy.typing import NDArray

from pipeline.core.errors import (
    InputError,
    NotMcapError,
    RecoveredDataWarning,
)
from pipeline.core.recording import (
    Problem,
)
from pipeline.io.cdr import gather_le
from pipeline.io.mcap_format import MAGIC, MAX_OPCODE, Opcode


@dataclass
class SchemaRecord:
    """A Schema record of the file."""

    id: int
    name: str
    encoding: str
    data: bytes


@dataclass
class ChannelRecord:
    """A Channel record of the file."""

    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict


@dataclass
class ChunkRecord:
    """A Chunk record of the file: where its records lie and what its index says."""

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
    # MessageIndex records found right after the chunk: channel id -> file offset, and the
    # end of the last one (0: none)
    mi_pos: dict[int, int] = field(default_factory=dict)
    mi_end: int = 0
    # the chunk record's message_start_time and message_end_time, ns: kept from the scan,
    # since reading them again from the mapping maps the pages (with the kernel's large
    # folios, up to megabytes around each) that the scan released
    start_ns: int = 0
    end_ns: int = 0


@dataclass
class Scan:
    """The file mapped in memory and its top-level records, as :func:`scan_file` lists them."""

    path: str
    buf: NDArray[np.uint8]
    profile: str = ""
    schemas: dict[int, SchemaRecord] = field(default_factory=dict)
    channels: dict[int, ChannelRecord] = field(default_factory=dict)
    chunks: list[ChunkRecord] = field(default_factory=list)
    top_messages: dict[int, list[int]] = field(default_factory=dict)
    problems: list[Problem] = field(default_factory=list)
    complete_bytes: int = 0  # bytes up to the end of the last complete record
    mapped: Any = None  # the mmap.mmap when the file is memory-mapped


#: pages mapped around a faulting address that a release also drops (Linux maps up to 64 kB)
FAULT_AROUND_BYTES = 128 << 10


def release_pages(scan: Scan, start: int, length: int) -> None:
    """Drop the mapped pages of ``[start, start + length)`` from this process's memory.

    The file stays mapped (a later access reads the pages again, usually from the page
    cache); this keeps the resident size of a long recording to about one chunk.
    """
    if scan.mapped is None or not hasattr(mmap, "MADV_DONTNEED"):
        return
    page = mmap.PAGESIZE
    # a page fault maps its neighbours too (the kernel's fault-around, up to 64 kB), also
    # pages before ``start`` that an earlier release dropped: drop those again
    lo = (max(start - FAULT_AROUND_BYTES, 0) // page) * page
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


def _parse_schema(b: bytes | mmap.mmap, p: int) -> SchemaRecord:
    (sid,) = struct.unpack_from("<H", b, p)
    name, p = _str(b, p + 2)
    enc, p = _str(b, p)
    (n,) = struct.unpack_from("<I", b, p)
    return SchemaRecord(sid, name, enc, bytes(b[p + 4 : p + 4 + n]))


def _parse_channel(b: bytes | mmap.mmap, p: int) -> ChannelRecord:
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
    return ChannelRecord(cid, sid, topic, enc, meta)


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


#: bytes of a memory-mapped file walked between two releases of its pages while scanning
RELEASE_EVERY = 32 << 20


def scan_file(path: str | Path) -> Scan:
    """Read the file and list its top-level records (docs/modules.md)."""
    p = Path(path)
    try:
        raw = _map_file(p)
    except OSError as exc:
        raise open_error(p, exc) from None
    size = len(raw)
    check_magic(raw[: len(MAGIC)], p)
    scan = Scan(str(p), np.frombuffer(raw, dtype=np.uint8),
                 mapped=raw if isinstance(raw, mmap.mmap) else None)
    pos = 8
    ended = False  # footer seen
    data_end = False
    last_chunk: ChunkRecord | None = None
    last_chunk_index: dict[int, np.ndarray] = {}
    saw_header = False
    released = 0  # file pages before this offset were dropped
    while pos < size:
        if pos + 9 > size:
            break
        op = raw[pos]
        (length,) = struct.unpack_from("<Q", raw, pos + 1)
        body = pos + 9
        if MAX_OPCODE < op < 0x80 and _sound_record_at(raw, pos, size):
            # reserved for future versions of MCAP: readers skip such records (the
            # specification says so, and the official readers do)
            _problem(scan.problems, "reserved_record",
                     f"{p}: record with the reserved opcode {op:#x} at byte {pos} (a newer "
                     "MCAP version's) was skipped", 0, warn=False)
            pos = body + length
            continue
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
                if pos - released > RELEASE_EVERY:
                    # the message indexes read so far (16 bytes a message): drop their pages
                    release_pages(scan, released, pos - released)
                    released = pos
            elif op == Opcode.MESSAGE_INDEX and last_chunk is not None:
                (cid, n) = struct.unpack_from("<HI", raw, body)
                pairs = np.frombuffer(raw, dtype="<u8", count=n // 8, offset=body + 6)
                offsets = pairs[1::2].astype(np.int64)
                offsets.sort()  # in place: np.sort would copy it again
                last_chunk_index[cid] = offsets
                last_chunk.mi_pos[cid] = pos
                last_chunk.mi_end = body + length
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


def _sound_record_at(raw: bytes | mmap.mmap, pos: int, size: int) -> bool:
    """Tell whether the record at ``pos`` ends inside the file where another one can start.

    A reserved opcode is skipped only when its record is sound: its length keeps it inside
    the file and the bytes after it are the end of the file or the head of a record (a
    non-zero opcode and a length that fits). Anything else is damage, not a newer record.
    """
    (length,) = struct.unpack_from("<Q", raw, pos + 1)
    end = pos + 9 + length
    if end > size:
        return False
    if end == size:
        return True
    if end + 9 > size or raw[end] == 0:
        return False
    (nxt,) = struct.unpack_from("<Q", raw, end + 1)
    return end + 9 + nxt <= size


def _chunk_header(raw: bytes | mmap.mmap, pos: int, body: int, length: int, size: int
                  ) -> ChunkRecord:
    start_t, end_t, usize, crc = struct.unpack_from("<QQQI", raw, body)
    comp, p = _str(raw, body + 28)
    (rlen,) = struct.unpack_from("<Q", raw, p)
    avail = min(rlen, size - (p + 8))
    return ChunkRecord(pos, comp, p + 8, avail, usize, crc, torn=avail < rlen, start_ns=start_t,
                  end_ns=end_t)


def _finish_scan(scan: Scan, last_chunk: ChunkRecord | None, last_index: dict, pos: int,
                 size: int, truncated: bool, data_end: bool = False) -> Scan:
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
    # walking the records touched pages across the whole file: drop them (those a reader
    # needs come back from the page cache, one chunk at a time)
    release_pages(scan, 0, len(raw))
    return scan


# --------------------------------------------------------------------------- chunks
_local = threading.local()


def _zstd() -> Any:
    """Return this thread's ``zstandard.ZstdDecompressor``.

    One is not to be used by two threads at once; making one per chunk cost a context
    allocation each time.
    """
    d = getattr(_local, "zstd", None)
    if d is None:

        d = _local.zstd = zstandard.ZstdDecompressor()
    return d


def _inflate(scan: Scan, ch: ChunkRecord) -> tuple[bytes | None, str, str]:
    """Decompress a chunk and check its CRC: ``(bytes or None, problem kind, detail)``.

    Touches nothing shared (it runs on worker threads, see :func:`_decompressed`); a torn
    chunk is decompressed as far as its bytes go.
    """
    view = scan.buf[ch.data_start : ch.data_start + ch.data_len]
    try:
        if ch.compression == "":
            out = view.tobytes()
        elif ch.compression == "zstd":
            if ch.torn:

                out = zstandard.ZstdDecompressor().decompressobj().decompress(view.tobytes())
            else:
                # straight from the file's bytes (no copy), with this thread's decompressor
                out = _zstd().decompress(view, max_output_size=ch.uncompressed_size)
        elif ch.compression == "lz4":

            comp = view.tobytes()
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


def _report(scan: Scan, ch: ChunkRecord, result: tuple[bytes | None, str, str]) -> bytes | None:
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


def decompress_chunk(scan: Scan, ch: ChunkRecord) -> bytes | None:
    """Decompress a chunk's records (None, with its problem noted, when it cannot be read)."""
    return _report(scan, ch, _inflate(scan, ch))


DECOMPRESS_THREADS = 2
"""Threads inflating chunks ahead of the decoding (zstd, lz4 and zlib's CRC release the GIL)."""


DECOMPRESS_AHEAD = 8
"""Chunks inflated ahead of the one being decoded (memory: that many chunks)."""


def _decompressed(scan: Scan, chunks: list[ChunkRecord]
                  ) -> Iterator[tuple[ChunkRecord, bytes | None]]:
    """``(chunk, its records or None)`` in file order, inflated on threads ahead of use.

    Problems are noted here, in file order, so that messages come out the same whatever the
    threads' timing.
    """
    for ch, b, _ in decompressed_then(scan, chunks, None):
        yield ch, b


def _inflate_then(scan: Scan, ch: ChunkRecord, after: Callable[[ChunkRecord, bytes], Any] | None
                  ) -> tuple[tuple[bytes | None, str, str], Any]:
    result = _inflate(scan, ch)
    if after is None or result[0] is None:
        return result, None
    return result, after(ch, result[0])


def decompressed_then(scan: Scan, chunks: list[ChunkRecord],
                       after: Callable[[ChunkRecord, bytes], Any] | None
                       ) -> Iterator[tuple[ChunkRecord, bytes | None, Any]]:
    """:func:`_decompressed`, with ``after(chunk, records)`` run on the inflating thread.

    ``after`` must note nothing and change nothing shared that the reading thread uses (its
    result, or None for a chunk that could not be read, comes with the chunk).
    """
    if len(chunks) < 3 or DECOMPRESS_THREADS < 2:
        for ch in chunks:
            result, extra = _inflate_then(scan, ch, after)
            yield ch, _report(scan, ch, result), extra
        return

    with ThreadPoolExecutor(max_workers=DECOMPRESS_THREADS,
                            thread_name_prefix="magalign-inflate") as ex:
        it = iter(chunks)
        pending = deque((ch, ex.submit(_inflate_then, scan, ch, after))
                        for ch in itertools.islice(it, DECOMPRESS_AHEAD))
        while pending:
            ch, fut = pending.popleft()
            nxt = next(it, None)
            if nxt is not None:
                pending.append((nxt, ex.submit(_inflate_then, scan, nxt, after)))
            result, extra = fut.result()
            yield ch, _report(scan, ch, result), extra


def _index_count(ch: ChunkRecord) -> int | str:
    if ch.index is None:
        return "(unknown number of)"
    return int(sum(len(v) for v in ch.index.values()))


def _walk(scan: Scan, b: bytes) -> tuple[dict[int, np.ndarray], int]:
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


def index_chunks(scan: Scan) -> None:
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
        b = decompress_chunk(scan, ch)
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


def select_messages(scan: Scan, ch: ChunkRecord, buf: NDArray[np.uint8], want: set[int]
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


def iter_blocks(scan: Scan, want: set[int], batch_bytes: int = 0
                 ) -> Iterator[tuple[NDArray[np.uint8], dict[int, np.ndarray]]]:
    """Yield ``(buffer, {channel id: message record offsets})`` for the wanted channels.

    ``batch_bytes`` > 0 joins consecutive chunks into blocks of about that many decompressed
    bytes (whole-recording reads: a logger's chunks hold a few hundred kB, and decoding each
    on its own spends most of the time in per-call overhead); 0 yields one block per
    chunk, for readers that copy each chunk's records out as they go or stop at the first
    messages (the raw channels, the header's first messages).
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
        sel = select_messages(scan, ch, np.frombuffer(b, dtype=np.uint8), want)
        release_pages(scan, ch.data_start, ch.data_len)  # decompressed: the bytes are not needed
        if not sel:
            continue
        bufs.append(b)
        sels.append(sel)
        size += len(b)
        if size >= batch_bytes:
            yield join_blocks(bufs, sels)
            bufs, sels, size = [], [], 0
    if bufs:
        yield join_blocks(bufs, sels)


BATCH_BYTES = 8 << 20
"""Decompressed bytes decoded at once (memory: about twice this, whatever the file size)."""


def join_blocks(bufs: list[bytes], sels: list[dict[int, np.ndarray]]
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


def compact_records(buf: NDArray[np.uint8], rec: np.ndarray
                     ) -> tuple[NDArray[np.uint8], np.ndarray]:
    """Copy the records at ``rec`` side by side when they all have one length.

    A sensor's messages usually have one size. One gather of whole records (each a ``V{n}``
    value) then replaces a dozen field gathers scattered over a large buffer: the field reads
    that follow walk a compact array in order, which the CPU's caches serve. Records of
    several sizes are returned as they are.
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


def record_columns(buf: NDArray[np.uint8], rec: np.ndarray) -> dict[str, np.ndarray]:
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


def copy_ranges(buf: NDArray[np.uint8], start: np.ndarray, length: np.ndarray,
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

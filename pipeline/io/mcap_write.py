"""Vectorised MCAP writing: whole channels of messages in, a complete indexed MCAP file out.

More in docs/modules.md, ``pipeline.io.mcap_write``.
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import enum
import struct
import time
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Protocol, cast

import lz4.frame
import numpy as np
import zstandard
from numpy.typing import ArrayLike, NDArray

from pipeline.core import geometry
from pipeline.core.atomic import atomic_path
from pipeline.core.errors import OutputError, SchemaError
from pipeline.io import messages
from pipeline.io.mcap_format import MAGIC, Opcode
from schemas import MESSAGE_TYPES, MessageRole

if TYPE_CHECKING:
    # An ndarray is a buffer, but numpy's stubs declare ``__buffer__`` only for Python >= 3.12:
    # arrays handed to memoryview() are cast to this protocol.
    from typing_extensions import Buffer

__all__ = [
    "Compression",
    "McapColumnWriter",
    "RawChannelLike",
    "copy_channels",
    "write_recording",
]

LIBRARY = "magalign mcap_write"


class Compression(str, enum.Enum):
    """Chunk compression."""

    ZSTD = "zstd"
    LZ4 = "lz4"
    NONE = "none"

    @property
    def mcap_name(self) -> str:
        """The compression string stored in Chunk records (empty for none)."""
        return "" if self is Compression.NONE else self.value


# Message record header: opcode, record length, channel_id, sequence, log_time, publish_time.
_MSG_HDR = np.dtype(
    {
        "names": ["op", "len", "channel", "sequence", "log_time", "publish_time"],
        "formats": ["u1", "<u8", "<u2", "<u4", "<u8", "<u8"],
        "offsets": [0, 1, 9, 11, 15, 23],
        "itemsize": 31,
    }
)
_MSG_HDR_SIZE = 31
_MSG_FIXED = 2 + 4 + 8 + 8  # Message content before the payload
#: a chunk made of more runs of consecutive records than this is gathered (_write_chunk)
_MAX_RUNS = 256
#: chunks laid out ahead of the one being written (compressed on the helper thread)
_IN_FLIGHT = 2
_INDEX_ENTRY = np.dtype([("log_time", "<u8"), ("offset", "<u8")])


# --------------------------------------------------------------------------------------------
# record serialisation (few records: plain struct)


def _str(s: str) -> bytes:
    b = s.encode("utf-8")
    return struct.pack("<I", len(b)) + b


def _map_ss(m: Mapping[str, str]) -> bytes:
    body = b"".join(_str(str(k)) + _str(str(v)) for k, v in m.items())
    return struct.pack("<I", len(body)) + body


def _record(op: int, content: bytes) -> bytes:
    return struct.pack("<BQ", op, len(content)) + content


def _gather_segments(src: np.ndarray, start: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Concatenate ``src[start[k]:start[k] + length[k]]`` for all k, vectorised.

    Index arithmetic: byte j of the output belongs to segment k(j) and comes from
    ``start[k] + (j - dst_start[k])``; ``np.repeat`` spreads the per-segment shift.
    """
    length = length.astype(np.int64, copy=False)
    total = int(length.sum())
    if total == 0:
        return np.zeros(0, dtype=src.dtype)
    # int32 indexes when they fit: half the memory traffic of the index arrays.
    it = np.int32 if max(total, src.shape[0]) < 2**31 - 1 else np.int64
    dst_start = np.cumsum(length) - length
    idx = np.repeat((start.astype(np.int64) - dst_start).astype(it), length)
    idx += np.arange(total, dtype=it)
    return src[idx]


class _Sink:
    """File writer that tracks the position and the running CRC32 of the data section."""

    def __init__(self, fh: IO[bytes]):
        self.fh = fh
        self.pos = 0
        self.crc = 0
        self.track_crc = True

    def write(self, b: bytes | memoryview | np.ndarray) -> None:
        mv = memoryview(cast("Buffer", b)).cast("B") if not isinstance(b, bytes) else b
        self.fh.write(mv)
        if self.track_crc:
            self.crc = zlib.crc32(mv, self.crc)
        self.pos += len(mv)


@dataclass
class _Block:
    """One ``add_messages`` call: complete Message records, in the caller's order."""

    channel_id: int
    log_time: NDArray[np.uint64]
    records: NDArray[np.uint8]  # all Message records of the block, concatenated
    rec_off: NDArray[np.int64]  # (n + 1,) record offsets inside ``records``
    sorted: bool  # log times non-decreasing within the block


@dataclass
class _ChunkInfo:
    start_time: int
    end_time: int
    offset: int
    length: int
    mi_offsets: dict[int, int]
    mi_length: int
    compressed_size: int
    uncompressed_size: int
    compression: str | None = None  # another chunk's own (pass-through); None: the writer's


@dataclass
class _PreparedChunk:
    """A chunk laid out, not yet compressed: its records as slices, its index columns."""

    pieces: list[np.ndarray]
    total: int
    start_time: int
    end_time: int
    chan: np.ndarray  # channel of each record, in chunk order
    log: np.ndarray  # log time of each record, in chunk order
    rec_start: np.ndarray  # offset of each record in the uncompressed chunk


class PassThroughChunkLike(Protocol):
    """What :meth:`McapColumnWriter.add_chunk_record` needs (``mcap_read.PassThroughChunk``)."""

    @property
    def record(self) -> np.ndarray: ...

    @property
    def message_indexes(self) -> np.ndarray: ...

    @property
    def start_ns(self) -> int: ...

    @property
    def end_ns(self) -> int: ...

    @property
    def compression(self) -> str: ...

    @property
    def compressed_size(self) -> int: ...

    @property
    def uncompressed_size(self) -> int: ...

    @property
    def mi_offsets(self) -> dict[int, int]: ...

    @property
    def counts(self) -> dict[int, int]: ...


class RawChannelLike(Protocol):
    """What :func:`copy_channels` needs of a channel (``pipeline.io.mcap_read.RawChannel``)."""

    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    metadata: dict
    log_time_ns: np.ndarray
    publish_time_ns: np.ndarray
    sequence: np.ndarray
    data: np.ndarray
    offsets: np.ndarray


class McapColumnWriter:
    """Write an MCAP file from columns of messages.

    Use as a context manager; the file appears under ``path`` only when the block ends
    without an exception (it is written to a temporary name next to it and renamed).

    Parameters
    ----------
    path : str or Path
        Final output path.
    profile : str
        MCAP header profile (``"ros2"`` for ROS 2 CDR channels, ``""`` otherwise).
    compression : Compression or str
        ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
    chunk_size : int
        Target uncompressed chunk size, bytes (a chunk holds at least one message).
    inputs : sequence of path
        Input files; writing over one of them raises :class:`OutputError`.
    zstd_level : int
        zstd compression level (3 is zstd's and mcap's default).

    Examples
    --------
    >>> with McapColumnWriter("out.mcap") as w:  # doctest: +SKIP
    ...     sid = w.add_schema(*messages.schema_for("sensor_msgs/msg/MagneticField")[:3])
    ...     cid = w.add_channel("/mag", "cdr", sid)
    ...     data, off = messages.encode("sensor_msgs/msg/MagneticField", t_ns, {"mag_T": B})
    ...     w.add_messages(cid, t_ns, data, off)

    """

    def __init__(
        self,
        path: str | Path,
        *,
        profile: str = "ros2",
        compression: Compression | str = Compression.ZSTD,
        chunk_size: int = 1 << 20,
        inputs: Sequence[str | Path] = (),
        zstd_level: int = 3,
        library: str = LIBRARY,
    ):
        self.path = Path(path)
        self.profile = profile
        try:
            self.compression = Compression(compression)
        except ValueError as exc:
            raise OutputError(
                f"unknown MCAP compression {compression!r}", hint="use zstd, lz4 or none"
            ) from exc
        if chunk_size <= 0:
            raise OutputError(f"chunk_size must be positive, got {chunk_size}")
        self.chunk_size = int(chunk_size)
        self.inputs = tuple(inputs)
        self.zstd_level = zstd_level
        self.library = library
        self._schemas: dict[int, tuple[str, str, bytes]] = {}
        self._schema_ids: dict[tuple[str, str, bytes], int] = {}
        self._channels: dict[int, tuple[str, str, int, dict[str, str]]] = {}
        self._next_seq: dict[int, int] = {}
        self._blocks: list[_Block] = []
        self._metadata: list[tuple[str, dict[str, str]]] = []
        self._attachments: list[tuple[str, str, bytes, int, int]] = []
        self._stack: contextlib.ExitStack | None = None
        self._tmp: Path | None = None
        self._fh: IO[bytes] | None = None
        self._out: _Sink | None = None
        self._closed = False
        # What is already in the file (after flush): definitions, chunks, statistics.
        self._written_schemas: set[int] = set()
        self._written_channels: set[int] = set()
        self._chunks: list[_ChunkInfo] = []
        self._counts: dict[int, int] = {}
        self._t_min: int | None = None
        self._t_max: int | None = None
        self._flushed_before = 0
        self._zstd: Any = None
        self._pool: concurrent.futures.ThreadPoolExecutor | None = None

    # ---------------------------------------------------------------- context management

    def __enter__(self) -> McapColumnWriter:
        self.open()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort(exc_type, exc, tb)

    def open(self) -> None:
        """Open the temporary output file and write the MCAP header (done by ``with``)."""
        if self._stack is not None:
            return
        if self._closed:
            raise OutputError("MCAP writer already closed", path=self.path)
        stack = contextlib.ExitStack()
        self._tmp = stack.enter_context(atomic_path(self.path, inputs=tuple(self.inputs)))
        self._stack = stack
        try:
            self._fh = open(self._tmp, "wb")  # closed in close() or abort()
            self._out = _Sink(self._fh)
            self._out.write(MAGIC)
            self._out.write(_record(Opcode.HEADER, _str(self.profile) + _str(self.library)))
        except BaseException as exc:
            self.abort(type(exc), exc, exc.__traceback__)
            raise

    def abort(self, exc_type=None, exc=None, tb=None) -> None:
        """Drop everything; nothing appears under the final name."""
        self._stop_packer()
        if self._fh is not None:
            with contextlib.suppress(OSError):
                self._fh.close()
            self._fh = None
        if self._stack is not None:
            stack, self._stack = self._stack, None
            err = exc if exc is not None else OutputError("MCAP writing aborted", path=self.path)
            stack.__exit__(type(err), err, tb)
        self._closed = True

    def close(self) -> Path:
        """Write the whole file and rename it to its final name; returns the final path."""
        if self._closed:
            return self.path
        self.open()
        assert self._stack is not None and self._fh is not None
        try:
            self.flush()
            self._stop_packer()
            self._finish()
            self._fh.close()
            self._fh = None
        except BaseException as exc:
            self.abort(type(exc), exc, exc.__traceback__)
            raise
        stack, self._stack = self._stack, None
        stack.close()  # fsync and rename
        self._closed = True
        return self.path

    # ---------------------------------------------------------------- content

    def add_schema(self, name: str, encoding: str, data: bytes,
                   schema_id: int | None = None) -> int:
        """Register a schema; returns its id (>= 1).

        Without ``schema_id``, identical schemas share one id and a new one gets the next
        free id; with it (copying another file's records as they are), the schema gets that
        id.
        """
        key = (str(name), str(encoding), bytes(data))
        if schema_id is not None:
            sid = int(schema_id)
            if sid < 1 or sid > 0xFFFF or self._schemas.get(sid, key) != key:
                raise OutputError(f"schema id {sid} unusable or taken", path=self.path)
            self._schemas[sid] = key
            self._schema_ids.setdefault(key, sid)
            return sid
        known = self._schema_ids.get(key)
        if known is not None:
            return known
        sid = max(self._schemas, default=0) + 1
        self._schemas[sid] = key
        self._schema_ids[key] = sid
        return sid

    def add_channel(
        self,
        topic: str,
        message_encoding: str,
        schema_id: int,
        metadata: Mapping[str, str] | None = None,
        channel_id: int | None = None,
    ) -> int:
        """Register a channel; returns its id (>= 1). ``schema_id`` 0 means no schema.

        ``channel_id``: the id to use (copying another file's records as they are); by
        default the next free id.
        """
        if schema_id != 0 and schema_id not in self._schemas:
            raise OutputError(f"channel {topic}: unknown schema id {schema_id}", path=self.path)
        cid = max(self._channels, default=0) + 1 if channel_id is None else int(channel_id)
        if cid > 0xFFFF:
            raise OutputError("more than 65535 channels", path=self.path)
        if cid < 1 or cid in self._channels:
            raise OutputError(f"channel id {cid} unusable or taken", path=self.path)
        md = {str(k): str(v) for k, v in (metadata or {}).items()}
        self._channels[cid] = (str(topic), str(message_encoding), int(schema_id), md)
        self._next_seq[cid] = 0
        return cid

    def add_messages(
        self,
        channel_id: int,
        log_time_ns: ArrayLike,
        data: np.ndarray,
        offsets: ArrayLike,
        publish_time_ns: ArrayLike | None = None,
        sequence: ArrayLike | None = None,
    ) -> None:
        """Add N messages of one channel.

        Parameters
        ----------
        channel_id : int
            From :meth:`add_channel`.
        log_time_ns : array_like of int64, shape (N,)
            MCAP log times, ns since the Unix epoch (>= 0). Need not be sorted.
        data : ndarray of uint8
            All payloads concatenated.
        offsets : array_like of int64, shape (N + 1,)
            Message i is ``data[offsets[i]:offsets[i + 1]]``.
        publish_time_ns : array_like of int64, shape (N,), optional
            Defaults to the log times.
        sequence : array_like of uint32, shape (N,), optional
            Defaults to a per-channel counter continuing over calls.

        """
        if channel_id not in self._channels:
            raise OutputError(f"unknown channel id {channel_id}", path=self.path)
        log = np.asarray(log_time_ns)
        n = log.shape[0] if log.ndim == 1 else -1
        off = np.asarray(offsets, dtype=np.int64)
        buf = np.ascontiguousarray(data).reshape(-1).view(np.uint8)
        if log.ndim != 1 or off.shape != (n + 1,):
            raise OutputError(
                f"channel {channel_id}: log_time_ns must be (N,) and offsets (N+1,), got "
                f"{log.shape} and {off.shape}",
                path=self.path,
            )
        if n == 0:
            return
        lens = np.diff(off)
        if lens.min() < 0 or off[0] < 0 or off[-1] > buf.shape[0]:
            raise OutputError(f"channel {channel_id}: offsets out of range", path=self.path)
        if log.min() < 0:
            raise OutputError(f"channel {channel_id}: negative log times", path=self.path)
        if log.min() < self._flushed_before:
            raise OutputError(
                f"channel {channel_id}: log time {int(log.min())} before the last flush point "
                f"{self._flushed_before}",
                path=self.path,
                hint="add messages in log-time order across flush() calls",
            )
        log_u = log.astype(np.uint64)
        pub = log_u if publish_time_ns is None else np.asarray(publish_time_ns).astype(np.uint64)
        if sequence is None:
            s0 = self._next_seq[channel_id]
            seq = (np.arange(s0, s0 + n, dtype=np.int64) & 0xFFFFFFFF).astype(np.uint32)
        else:
            seq = np.asarray(sequence).astype(np.uint32)
        if pub.shape != (n,) or seq.shape != (n,):
            raise OutputError(
                f"channel {channel_id}: publish_time_ns and sequence must have shape ({n},)",
                path=self.path,
            )
        self._next_seq[channel_id] += n

        hdr = np.empty(n, dtype=_MSG_HDR)
        hdr["op"] = Opcode.MESSAGE
        hdr["len"] = lens + _MSG_FIXED
        hdr["channel"] = channel_id
        hdr["sequence"] = seq
        hdr["log_time"] = log_u
        hdr["publish_time"] = pub
        hdr_u8 = hdr.view(np.uint8).reshape(n, _MSG_HDR_SIZE)
        rec_len = lens + _MSG_HDR_SIZE
        rec_off = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(rec_len, out=rec_off[1:])
        width = int(lens[0])
        if np.all(lens == width):
            # Fixed-length payloads (CDR with a fixed frame_id): rows of one 2-D array.
            rows = np.empty((n, _MSG_HDR_SIZE + width), dtype=np.uint8)
            rows[:, :_MSG_HDR_SIZE] = hdr_u8
            if off[-1] - off[0] == n * width:  # payloads back to back (lengths all equal)
                rows[:, _MSG_HDR_SIZE:] = buf[off[0] : off[-1]].reshape(n, width)
            else:
                rows[:, _MSG_HDR_SIZE:] = _gather_segments(buf, off[:-1], lens).reshape(n, width)
            records = rows.reshape(-1)
        else:
            records = np.empty(int(rec_off[-1]), dtype=np.uint8)
            # Header bytes: 31 per record at each record start.
            records[(rec_off[:-1, None] + np.arange(_MSG_HDR_SIZE)).reshape(-1)] = hdr_u8.reshape(
                -1
            )
            # Payload bytes, gathered in one step and scattered after each header.
            total = int(lens.sum())
            dst = np.repeat(rec_off[:-1] + _MSG_HDR_SIZE - (np.cumsum(lens) - lens), lens)
            dst += np.arange(total, dtype=np.int64)
            records[dst] = _gather_segments(buf, off[:-1], lens)
        self._blocks.append(
            _Block(
                channel_id=channel_id,
                log_time=log_u,
                records=records,
                rec_off=rec_off,
                sorted=bool(np.all(log_u[1:] >= log_u[:-1])),
            )
        )

    def add_chunk_record(self, chunk: PassThroughChunkLike) -> None:
        """Write another file's Chunk record and its MessageIndex records as they are.

        The chunk's channel (and schema) ids must have been registered with the same ids
        (``add_channel(..., channel_id=...)``). The bytes are written at once, not merged
        with the messages added by :meth:`add_messages`: chunks may overlap in time (readers
        in log-time order go by the chunk and message indexes).
        """
        self.open()
        unknown = set(chunk.counts) - set(self._channels)
        if unknown:
            raise OutputError(f"chunk of unregistered channels {sorted(unknown)}", path=self.path)
        self._write_definitions()
        out = self._out
        assert out is not None
        offset = out.pos
        out.write(chunk.record)
        mi_start = out.pos
        out.write(chunk.message_indexes)
        self._chunks.append(_ChunkInfo(
            start_time=chunk.start_ns, end_time=chunk.end_ns, offset=offset,
            length=mi_start - offset,
            mi_offsets={c: offset + o for c, o in sorted(chunk.mi_offsets.items())},
            mi_length=out.pos - mi_start, compressed_size=chunk.compressed_size,
            uncompressed_size=chunk.uncompressed_size, compression=chunk.compression))
        for c, k in chunk.counts.items():
            self._counts[c] = self._counts.get(c, 0) + int(k)
        if sum(chunk.counts.values()):
            self._t_min = chunk.start_ns if self._t_min is None else min(self._t_min,
                                                                         chunk.start_ns)
            self._t_max = chunk.end_ns if self._t_max is None else max(self._t_max,
                                                                       chunk.end_ns)

    def add_metadata(self, name: str, metadata: Mapping[str, str]) -> None:
        """Add a Metadata record ``name`` with string keys and values."""
        self._metadata.append((str(name), {str(k): str(v) for k, v in metadata.items()}))

    def add_attachment(
        self,
        name: str,
        media_type: str,
        data: bytes,
        log_time_ns: int = 0,
        create_time_ns: int | None = None,
    ) -> None:
        """Add an Attachment record (its CRC is written)."""
        ct = time.time_ns() if create_time_ns is None else int(create_time_ns)
        self._attachments.append((str(name), str(media_type), bytes(data), int(log_time_ns), ct))

    # ---------------------------------------------------------------- writing

    def _compress_pieces(self, pieces: list[np.ndarray], total: int) -> bytes | memoryview:
        """Compress the concatenation of ``pieces`` (``total`` bytes) as one frame."""
        if self.compression is Compression.ZSTD:

            if self._zstd is None:  # one compressor for all chunks (its context is reused)
                self._zstd = zstandard.ZstdCompressor(level=self.zstd_level)
            if len(pieces) == 1:
                return self._zstd.compress(pieces[0])
            # one frame with its content size, fed slice by slice (no joined copy)
            cobj = self._zstd.compressobj(size=total)
            parts = [cobj.compress(p) for p in pieces]
            parts.append(cobj.flush())
            return b"".join(parts)
        joined = pieces[0] if len(pieces) == 1 else np.concatenate(pieces)
        if self.compression is Compression.LZ4:

            return lz4.frame.compress(joined)
        return memoryview(cast("Buffer", joined)).cast("B")

    def _write_definitions(self) -> None:
        """Write Schema and Channel records not yet in the file (before any message uses them)."""
        assert self._out is not None
        for sid in sorted(set(self._schemas) - self._written_schemas):
            self._out.write(_schema_record(sid, *self._schemas[sid]))
            self._written_schemas.add(sid)
        for cid in sorted(set(self._channels) - self._written_channels):
            self._out.write(_channel_record(cid, *self._channels[cid]))
            self._written_channels.add(cid)

    def flush(self, before_ns: int | None = None) -> None:
        """Write every message with log time ``< before_ns`` (all if None) as chunks now.

        Bounds memory on long recordings: add a stretch of messages, flush up to its end,
        and continue. Messages added later must not have log times before ``before_ns``.
        """
        self.open()
        self._write_definitions()
        keep: list[_Block]
        if before_ns is None:
            todo, keep = self._blocks, []
        else:
            todo, keep = [], []
            for b in self._blocks:
                m = b.log_time < np.uint64(max(int(before_ns), 0))
                if m.all():
                    todo.append(b)
                elif m.any():
                    todo.append(_sub_block(b, m))
                    keep.append(_sub_block(b, ~m))
                else:
                    keep.append(b)
            self._flushed_before = max(self._flushed_before, int(before_ns))
        self._blocks = keep
        if todo:
            self._write_chunks(todo)

    def _finish(self) -> None:
        out = self._out
        assert out is not None
        chunks, counts = self._chunks, self._counts
        t_min = 0 if self._t_min is None else self._t_min
        t_max = 0 if self._t_max is None else self._t_max
        schema_recs = [_schema_record(sid, *v) for sid, v in self._schemas.items()]
        channel_recs = [_channel_record(cid, *v) for cid, v in self._channels.items()]

        metadata_index = []
        for name, md in self._metadata:
            rec = _record(Opcode.METADATA, _str(name) + _map_ss(md))
            metadata_index.append(_record(Opcode.METADATA_INDEX,
                                          struct.pack("<QQ", out.pos, len(rec)) + _str(name)))
            out.write(rec)
        attachment_index = []
        for name, media, data, log_t, create_t in self._attachments:
            body = (struct.pack("<QQ", log_t, create_t) + _str(name) + _str(media)
                    + struct.pack("<Q", len(data)) + data)
            rec = _record(Opcode.ATTACHMENT, body + struct.pack("<I", zlib.crc32(body)))
            attachment_index.append(_record(
                Opcode.ATTACHMENT_INDEX,
                struct.pack("<QQQQQ", out.pos, len(rec), log_t, create_t, len(data))
                + _str(name) + _str(media),
            ))
            out.write(rec)

        out.write(_record(Opcode.DATA_END, struct.pack("<I", out.crc)))

        # Summary section.
        summary_start = out.pos
        out.crc = 0  # from here the running CRC is the summary CRC
        stats = (
            struct.pack(
                "<QHIIIIQQ", int(sum(counts.values())), len(self._schemas), len(self._channels),
                len(self._attachments), len(self._metadata), len(chunks), t_min, t_max,
            )
            + _map_bytes_u16_u64(counts)
        )
        groups: list[tuple[int, list[bytes]]] = [
            (Opcode.SCHEMA, schema_recs),
            (Opcode.CHANNEL, channel_recs),
            (Opcode.STATISTICS, [_record(Opcode.STATISTICS, stats)]),
            (Opcode.CHUNK_INDEX, [_chunk_index(c, self.compression.mcap_name) for c in chunks]),
            (Opcode.ATTACHMENT_INDEX, attachment_index),
            (Opcode.METADATA_INDEX, metadata_index),
        ]
        offsets = []
        for op, recs in groups:
            if not recs:
                continue
            start = out.pos
            blob = b"".join(recs)
            out.write(blob)
            offsets.append(_record(Opcode.SUMMARY_OFFSET,
                                   struct.pack("<BQQ", op, start, len(blob))))
        summary_offset_start = out.pos
        out.write(b"".join(offsets))
        footer_head = struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start)
        out.write(footer_head)
        out.write(struct.pack("<I", out.crc))
        out.write(MAGIC)

    def _write_chunks(self, blocks: list[_Block]) -> None:
        sizes = np.array([b.log_time.shape[0] for b in blocks], dtype=np.int64)
        blk = np.repeat(np.arange(len(blocks), dtype=np.int64), sizes)
        local = np.arange(int(sizes.sum()), dtype=np.int64) - np.repeat(np.cumsum(sizes) - sizes,
                                                                         sizes)
        log = np.concatenate([b.log_time for b in blocks])
        chan = np.repeat(np.array([b.channel_id for b in blocks], dtype=np.uint16), sizes)
        rec_len = np.concatenate([np.diff(b.rec_off) for b in blocks])
        for b, n in zip(blocks, sizes, strict=True):
            self._counts[b.channel_id] = self._counts.get(b.channel_id, 0) + int(n)
        # Merge every channel by log time; stable, so equal times keep the order of the calls.
        order = np.argsort(log, kind="stable")
        log_s, blk_s, loc_s = log[order], blk[order], local[order]
        chan_s, len_s = chan[order], rec_len[order]
        del blk, local, chan, rec_len
        t0, t1 = int(log_s[0]), int(log_s[-1])
        self._t_min = t0 if self._t_min is None else min(self._t_min, t0)
        self._t_max = t1 if self._t_max is None else max(self._t_max, t1)
        cs = np.zeros(len(order) + 1, dtype=np.int64)
        np.cumsum(len_s, out=cs[1:])
        n_total = len(order)
        # Chunk k is checksummed and compressed on a helper thread (zlib and zstd release the
        # GIL) while this thread lays out chunk k + 1 and writes chunk k - 1: at most
        # _IN_FLIGHT chunks of slices wait, so memory stays a few chunks.
        pending: collections.deque[tuple[concurrent.futures.Future, _PreparedChunk]] = (
            collections.deque())
        pool = self._packer()
        i = 0
        while i < n_total:
            j = int(np.searchsorted(cs, cs[i] + self.chunk_size, side="right")) - 1
            j = min(max(j, i + 1), n_total)
            prep = self._prepare_chunk(blocks, log_s[i:j], blk_s[i:j], loc_s[i:j],
                                       chan_s[i:j], len_s[i:j])
            pending.append((pool.submit(self._pack, prep.pieces, prep.total), prep))
            if len(pending) > _IN_FLIGHT:
                fut, done = pending.popleft()
                self._chunks.append(self._emit_chunk(done, *fut.result()))
            i = j
        while pending:
            fut, done = pending.popleft()
            self._chunks.append(self._emit_chunk(done, *fut.result()))

    def _prepare_chunk(
        self,
        blocks: list[_Block],
        log: np.ndarray,
        blk: np.ndarray,
        loc: np.ndarray,
        chan: np.ndarray,
        rec_len: np.ndarray,
    ) -> _PreparedChunk:
        """Lay out one chunk of the messages ``log``/``blk``/``loc`` (merged log-time order).

        Inside the chunk the records are grouped by block (``add_messages`` call, in call
        order), each block's records in log-time order: a group is one run of consecutive
        records of a block (a sorted block), so the chunk is a short list of slices of the
        blocks, checksummed and compressed piece by piece without being copied together.
        Equal log times keep the call order and each channel's records stay in log-time
        order; when grouping would break the latter (two blocks of one channel overlapping
        in time within the chunk), the chunk keeps the merged log-time order instead.
        """
        n = log.shape[0]
        order = np.argsort(blk, kind="stable")  # stable: log-time order within each block
        if not _channels_sorted(chan[order], log[order]):
            order = np.arange(n)
        blk_g, loc_g, len_g = blk[order], loc[order], rec_len[order]
        # runs of consecutive records of one block: one slice each
        brk = np.flatnonzero((blk_g[1:] != blk_g[:-1]) | (loc_g[1:] != loc_g[:-1] + 1)) + 1
        run_start = np.concatenate([[0], brk])
        run_end = np.concatenate([brk, [n]])
        pieces: list[np.ndarray] = []
        if len(run_start) <= _MAX_RUNS:
            for a, e in zip(run_start.tolist(), run_end.tolist(), strict=True):
                b = blocks[int(blk_g[a])]
                pieces.append(b.records[b.rec_off[loc_g[a]] : b.rec_off[loc_g[e - 1] + 1]])
        else:  # many short runs (an unsorted block): copy each block's span, gather once
            spans, src_start, base = [], np.empty(n, dtype=np.int64), 0
            for bid in np.unique(blk_g):
                m = blk_g == bid
                b = blocks[int(bid)]
                lo, hi = int(loc_g[m].min()), int(loc_g[m].max()) + 1
                s0 = int(b.rec_off[lo])
                spans.append(b.records[s0 : b.rec_off[hi]])
                src_start[m] = base + b.rec_off[loc_g[m]] - s0
                base += int(b.rec_off[hi]) - s0
            pieces.append(_gather_segments(np.concatenate(spans), src_start, len_g))
        rec_start = np.zeros(n, dtype=np.uint64)
        np.cumsum(len_g[:-1], out=rec_start[1:])
        return _PreparedChunk(pieces=pieces, total=int(len_g.sum()), start_time=int(log[0]),
                              end_time=int(log[-1]), chan=chan[order], log=log[order],
                              rec_start=rec_start)

    def _packer(self) -> concurrent.futures.ThreadPoolExecutor:
        """Return the helper thread that checksums and compresses chunks (created once)."""
        if self._pool is None:
            self._pool = concurrent.futures.ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="mcap-pack")
        return self._pool

    def _stop_packer(self) -> None:
        """Stop the helper thread (after its queued chunks)."""
        if self._pool is not None:
            pool, self._pool = self._pool, None
            pool.shutdown(wait=True, cancel_futures=True)

    def _pack(self, pieces: list[np.ndarray], total: int) -> tuple[int, bytes | memoryview]:
        """CRC-32 and compressed bytes of one chunk's records (runs on the helper thread)."""
        crc = 0
        for piece in pieces:
            crc = zlib.crc32(memoryview(cast("Buffer", piece)).cast("B"), crc)
        return crc, self._compress_pieces(pieces, total)

    def _emit_chunk(self, prep: _PreparedChunk, crc: int, comp: bytes | memoryview
                    ) -> _ChunkInfo:
        """Write a packed chunk and its MessageIndex records (one per channel)."""
        out = self._out
        assert out is not None
        comp_name = self.compression.mcap_name
        head = struct.pack("<QQQI", prep.start_time, prep.end_time, prep.total, crc)
        head += _str(comp_name) + struct.pack("<Q", len(comp))
        chunk_offset = out.pos
        out.write(struct.pack("<BQ", Opcode.CHUNK, len(head) + len(comp)) + head)
        out.write(comp)
        chunk_length = out.pos - chunk_offset
        chan_g = prep.chan
        mi_offsets: dict[int, int] = {}
        mi_start = out.pos
        for cid in np.flatnonzero(np.bincount(chan_g)).tolist():
            m = chan_g == cid
            entries = np.empty(int(np.count_nonzero(m)), dtype=_INDEX_ENTRY)
            entries["log_time"] = prep.log[m]
            entries["offset"] = prep.rec_start[m]
            body = entries.tobytes()
            mi_offsets[cid] = out.pos
            out.write(struct.pack("<BQHI", Opcode.MESSAGE_INDEX, 2 + 4 + len(body), cid,
                                  len(body)))
            out.write(body)
        return _ChunkInfo(
            start_time=prep.start_time, end_time=prep.end_time, offset=chunk_offset,
            length=chunk_length, mi_offsets=mi_offsets, mi_length=out.pos - mi_start,
            compressed_size=len(comp), uncompressed_size=prep.total,
        )


def _channels_sorted(chan: np.ndarray, log: np.ndarray) -> bool:
    """Whether each channel's log times are non-decreasing in the order given."""
    by_chan = np.argsort(chan, kind="stable")
    c, t = chan[by_chan], log[by_chan]
    return not bool(np.any((c[1:] == c[:-1]) & (t[1:] < t[:-1])))


def _schema_record(sid: int, name: str, encoding: str, data: bytes) -> bytes:
    return _record(Opcode.SCHEMA, struct.pack("<H", sid) + _str(name) + _str(encoding)
                   + struct.pack("<I", len(data)) + data)


def _channel_record(cid: int, topic: str, message_encoding: str, schema_id: int,
                    metadata: Mapping[str, str]) -> bytes:
    return _record(Opcode.CHANNEL, struct.pack("<HH", cid, schema_id) + _str(topic)
                   + _str(message_encoding) + _map_ss(metadata))


def _sub_block(b: _Block, mask: np.ndarray) -> _Block:
    """Return the messages of ``b`` selected by ``mask`` as a new block (own record copy)."""
    idx = np.flatnonzero(mask)
    lens = np.diff(b.rec_off)[idx]
    rec_off = np.zeros(idx.shape[0] + 1, dtype=np.int64)
    np.cumsum(lens, out=rec_off[1:])
    if idx[-1] - idx[0] == idx.shape[0] - 1:  # a contiguous run (sorted block): one slice
        records = b.records[b.rec_off[idx[0]] : b.rec_off[idx[-1] + 1]].copy()
    else:
        records = _gather_segments(b.records, b.rec_off[idx], lens)
    log = b.log_time[idx]
    return _Block(b.channel_id, log, records, rec_off, bool(np.all(log[1:] >= log[:-1])))


def _map_bytes_u16_u64(m: Mapping[int, int]) -> bytes:
    body = b"".join(struct.pack("<HQ", k, v) for k, v in m.items())
    return struct.pack("<I", len(body)) + body


def _chunk_index(c: _ChunkInfo, compression: str) -> bytes:
    """ChunkIndex record of ``c`` (``compression``: the writer's, unless the chunk has its own)."""
    compression = compression if c.compression is None else c.compression
    mi = _map_bytes_u16_u64(c.mi_offsets)
    body = (
        struct.pack("<QQQQ", c.start_time, c.end_time, c.offset, c.length)
        + mi
        + struct.pack("<Q", c.mi_length)
        + _str(compression)
        + struct.pack("<QQ", c.compressed_size, c.uncompressed_size)
    )
    return _record(Opcode.CHUNK_INDEX, body)


# --------------------------------------------------------------------------------------------


def copy_channels(
    writer: McapColumnWriter, raw_channels: Iterable[RawChannelLike]
) -> dict[str, int]:
    """Add channels read by ``pipeline.io.mcap_read.read_raw_channels`` to ``writer`` unchanged.

    Schemas, channel metadata, log and publish times, sequence numbers and payload bytes are
    copied as they are. Returns ``{topic: new channel id}``.
    """
    ids: dict[str, int] = {}
    for rc in raw_channels:
        if rc.schema_name == "" and rc.schema_encoding == "" and len(rc.schema_data) == 0:
            sid = 0  # schemaless channel
        else:
            sid = writer.add_schema(rc.schema_name, rc.schema_encoding, bytes(rc.schema_data))
        cid = writer.add_channel(rc.topic, rc.message_encoding, sid, dict(rc.metadata))
        writer.add_messages(cid, rc.log_time_ns, rc.data, rc.offsets,
                            publish_time_ns=rc.publish_time_ns, sequence=rc.sequence)
        ids[rc.topic] = cid
    return ids


_ATTITUDE_FIELDS = {t.name for t in MESSAGE_TYPES.values()
                    if t.role is MessageRole.ATTITUDE and t.columns == ("q_xyzw",)}


def _attitude_fields(msg_type: str, q_enu_body: np.ndarray) -> dict[str, np.ndarray]:
    if msg_type in _ATTITUDE_FIELDS:
        return {"q_xyzw": q_enu_body}
    if msg_type == "novatel_oem7_msgs/msg/INSPVA":
        roll, pitch, az = geometry.quat_to_novatel(q_enu_body)
        return {"roll_deg": roll, "pitch_deg": pitch, "azimuth_deg": az}
    if msg_type == "magalign.AttitudeEuler":
        h, p, r = geometry.quat_to_li2020_euler(q_enu_body)
        return {"heading_deg": np.degrees(h), "pitch_deg": np.degrees(p),
                "roll_deg": np.degrees(r)}
    raise SchemaError(f"{msg_type} is not an attitude message type")


def _mag_fields(msg_type: str, mag_nT: np.ndarray) -> dict[str, np.ndarray]:
    if msg_type == "sensor_msgs/msg/MagneticField":
        return {"mag_T": mag_nT * 1e-9}  # REP-145: tesla on the wire
    if msg_type == "magalign.Magnetometer":
        return {"mag_nT": mag_nT}
    raise SchemaError(f"{msg_type} is not a magnetometer message type")


def _turntable_fields(msg_type: str, angle_deg: np.ndarray) -> dict[str, np.ndarray]:
    if msg_type == "std_msgs/msg/Float64":
        return {"value": angle_deg}
    if msg_type == "magalign.Turntable":
        return {"angle_deg": angle_deg}
    raise SchemaError(f"{msg_type} is not a turntable message type")


def _position_fields(msg_type: str, fix: np.ndarray) -> dict[str, np.ndarray]:
    if msg_type == "sensor_msgs/msg/NavSatFix":
        return {"latitude_deg": fix[:, 0], "longitude_deg": fix[:, 1], "height_m": fix[:, 2]}
    raise SchemaError(f"{msg_type} is not a position message type")


def write_recording(
    path: str | Path,
    *,
    mag_t_ns: ArrayLike,
    mag_nT: ArrayLike,
    attitude_t_ns: ArrayLike | None = None,
    q_enu_body: ArrayLike | None = None,
    turntable_t_ns: ArrayLike | None = None,
    turntable_deg: ArrayLike | None = None,
    mag_type: str = "sensor_msgs/msg/MagneticField",
    attitude_type: str = "sensor_msgs/msg/Imu",
    turntable_type: str = "std_msgs/msg/Float64",
    mag_topic: str = "/mag",
    attitude_topic: str = "/attitude",
    turntable_topic: str = "/turntable",
    mag_frame_id: str = "mag",
    mag_log_delay_ns: int | ArrayLike = 0,
    attitude_log_delay_ns: int | ArrayLike = 0,
    compression: Compression | str = Compression.ZSTD,
    attitude_frame_id: str = "body",
    attitude_variant: str | None = None,
    turntable_log_delay_ns: int | ArrayLike = 0,
    metadata: Mapping[str, Mapping[str, str]] | None = None,
    inputs: Sequence[str | Path] = (),
    chunk_size: int = 1 << 20,
    attitude_extra: Mapping[str, ArrayLike] | None = None,
    position_t_ns: ArrayLike | None = None,
    position_fix: ArrayLike | None = None,
    position_type: str = "sensor_msgs/msg/NavSatFix",
    position_topic: str = "/fix",
    position_frame_id: str = "gnss",
    position_log_delay_ns: int | ArrayLike = 0,
    position_extra: Mapping[str, ArrayLike] | None = None,
) -> Path:
    """Write a recording as a real logger would: each stream's messages stamped, logged late.

    Each message's header stamp is its sample time; its MCAP log time (and publish time) is
    the stamp plus the stream's log delay (a scalar or one value per sample), and all streams
    are interleaved by log time in the file.

    Parameters
    ----------
    path : path
        Output MCAP file (written atomically).
    mag_t_ns, mag_nT : ndarray, shapes (N,) int64 and (N, 3) float64
        Magnetometer stamps and field in nT, mag frame (tesla on the wire for ROS 2).
    attitude_t_ns, q_enu_body : ndarray, shapes (M,) and (M, 4), optional
        Attitude stamps and quaternions (scalar-last). Converted to the type's angles for
        INSPVA (roll, pitch, azimuth clockwise from north) and ``magalign.AttitudeEuler``.
    turntable_t_ns, turntable_deg : ndarray, shapes (K,), optional
        Turntable angle channel, degrees.
    mag_type, attitude_type, turntable_type : str
        Message types (see :data:`pipeline.messages.WRITTEN_TYPES`).
    mag_topic, attitude_topic, turntable_topic : str
        Channel topics.
    mag_frame_id, attitude_frame_id : str
        ``frame_id`` written in the messages' headers.
    mag_log_delay_ns, attitude_log_delay_ns, turntable_log_delay_ns : int or ndarray
        Log time minus stamp, ns.
    compression : Compression or str
        Chunk compression.
    attitude_variant : str, optional
        Layout variant of the attitude type (INSPVA header layouts).
    metadata : mapping of str to mapping, optional
        Metadata records to add, by name.
    inputs : sequence of path
        Files that must not be overwritten.
    chunk_size : int
        Target uncompressed chunk size, bytes.
    attitude_extra : mapping of str to ndarray, optional
        Further columns of the attitude messages (see :func:`pipeline.messages.encode`),
        e.g. ``position_m`` (M, 3) for ``PoseStamped`` or ``latitude_deg``,
        ``longitude_deg``, ``height_m`` (M,) for INSPVA.
    position_t_ns, position_fix : ndarray, shapes (P,) int64 and (P, 3), optional
        A position channel: stamps and WGS-84 fixes, columns latitude (deg), longitude (deg),
        height above the ellipsoid (m); a NaN row is written as NaN values (give
        ``position_extra={"status": ...}`` with -1 to flag a fix as none).
    position_type, position_topic, position_frame_id : str
        Its message type (``sensor_msgs/msg/NavSatFix``), topic and ``header.frame_id`` (the
        antenna's frame).
    position_log_delay_ns : int or ndarray
        Log time minus stamp, ns.
    position_extra : mapping of str to ndarray, optional
        Further columns of the position messages (:func:`pipeline.messages.encode`):
        ``status`` (P,) (NavSatStatus, -1 no fix), ``position_covariance`` (P, 9), ...

    Returns
    -------
    Path
        ``path``.

    """
    types = [mag_type]
    if q_enu_body is not None:
        types.append(attitude_type)
    if turntable_deg is not None:
        types.append(turntable_type)
    if position_fix is not None:
        types.append(position_type)
    profile = "ros2" if all(t not in messages.JSON_TYPES for t in types) else ""
    streams: list[tuple[str, str, np.ndarray, dict[str, np.ndarray], str, Any, str | None]] = []
    # Columns are converted per stream up front (cheap); payloads are encoded one stream at a
    # time inside the writer so that only one stream's encoded bytes exist besides the records.
    mag_t = np.asarray(mag_t_ns, dtype=np.int64)
    streams.append((mag_type, mag_topic, mag_t,
                    _mag_fields(mag_type, np.asarray(mag_nT, dtype=np.float64).reshape(-1, 3)),
                    mag_frame_id, mag_log_delay_ns, None))
    if q_enu_body is not None:
        if attitude_t_ns is None:
            raise OutputError("q_enu_body given without attitude_t_ns", path=path)
        q = np.asarray(q_enu_body, dtype=np.float64).reshape(-1, 4)
        att_fields = _attitude_fields(attitude_type, q)
        att_fields.update({k: np.asarray(v, dtype=np.float64)
                           for k, v in (attitude_extra or {}).items()})
        streams.append((attitude_type, attitude_topic, np.asarray(attitude_t_ns, dtype=np.int64),
                        att_fields, attitude_frame_id,
                        attitude_log_delay_ns, attitude_variant))
    if turntable_deg is not None:
        if turntable_t_ns is None:
            raise OutputError("turntable_deg given without turntable_t_ns", path=path)
        streams.append((turntable_type, turntable_topic,
                        np.asarray(turntable_t_ns, dtype=np.int64),
                        _turntable_fields(turntable_type,
                                          np.asarray(turntable_deg, dtype=np.float64)),
                        "", turntable_log_delay_ns, None))
    if position_fix is not None:
        if position_t_ns is None:
            raise OutputError("position_fix given without position_t_ns", path=path)
        fix = np.asarray(position_fix, dtype=np.float64).reshape(-1, 3)
        pos_fields = _position_fields(position_type, fix)
        # as given: the status is an integer column of the message (int8), not a float
        pos_fields.update({k: np.asarray(v) for k, v in (position_extra or {}).items()})
        streams.append((position_type, position_topic,
                        np.asarray(position_t_ns, dtype=np.int64), pos_fields,
                        position_frame_id, position_log_delay_ns, None))
    with McapColumnWriter(path, profile=profile, compression=compression, inputs=inputs,
                          chunk_size=chunk_size) as w:
        for msg_type, topic, t, fields, frame_id, delay, variant in streams:
            name, s_enc, s_data, m_enc = messages.schema_for(msg_type, variant)
            sid = w.add_schema(name, s_enc, s_data)
            cid = w.add_channel(topic, m_enc, sid)
            data, off = messages.encode(msg_type, t, fields, frame_id, variant=variant)
            log_t = t + np.asarray(delay, dtype=np.int64)
            w.add_messages(cid, log_t, data, off)
            del data, off  # the writer holds its own copy of the records
        for name, md in (metadata or {}).items():
            w.add_metadata(name, md)
    return Path(path)

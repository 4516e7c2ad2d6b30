"""Where a run's chunks come from: a recording held in memory, or a long file read in ranges.

A recording held in memory is one chunk (a long one, such as a damaged file's recovered
samples, is cut into chunks of its own). A long intact indexed file is never held whole:
its ranges are decoded once, in the first pass, and spilled to an anonymous file beside the
outputs (72 bytes a sample pair) that the second pass replays.
"""

from __future__ import annotations

import dataclasses
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TypeVar

import numpy as np

from pipeline.core.errors import MagalignError, OutputError
from pipeline.core.recording import AttitudeSeries, PositionSeries, Recording, VectorSeries
from pipeline.io.mcap_header import read_recording_header
from pipeline.io.mcap_read import (
    PassThrough,
    RecordingChunk,
    iter_recording_chunks,
    pass_through,
    read_recording,
    read_recording_warning,
)
from pipeline.run.options import ProcessOptions

#: messages per range read from a long file (memory: about 100 bytes a message)
RANGE_MESSAGES = 200_000


class MemorySource:
    """A recording held in memory: one chunk, or chunks of ``chunk_samples`` samples.

    Parameters
    ----------
    recording : Recording
        With its attitude (a turntable's made first).
    chunk_samples : int or None
        Magnetometer samples per chunk; None: the recording is one chunk.

    """

    def __init__(self, recording: Recording, chunk_samples: int | None = None) -> None:
        self.header = recording
        self.recording = recording
        self.chunk_samples = chunk_samples
        t = recording.mag.t_ns
        self.n_mag = len(t)
        self.start_ns = int(t[0]) if len(t) else 0
        self.end_ns = int(t[-1]) + 1 if len(t) else 0

    @property
    def one_chunk(self) -> bool:
        """Whether the recording is one chunk."""
        return self.chunk_samples is None or self.n_mag <= self.chunk_samples

    def chunks(self) -> Iterator[RecordingChunk]:
        """Yield the chunks in time order (the first pass)."""
        rec = self.recording
        if self.one_chunk:
            yield RecordingChunk(0, rec.mag, rec.attitude, rec.turntable, rec.position)
            return
        assert self.chunk_samples is not None
        t = rec.mag.t_ns
        cuts = np.arange(self.chunk_samples, self.n_mag, self.chunk_samples)
        # chunk j holds the samples of every channel stamped in [t[cut_j], t[cut_j+1])
        bounds = [None, *(int(t[c]) for c in cuts), None]
        for j in range(len(bounds) - 1):
            lo, hi = bounds[j], bounds[j + 1]
            yield RecordingChunk(j, _span(rec.mag, lo, hi),
                                 None if rec.attitude is None else _span(rec.attitude, lo, hi),
                                 None,
                                 None if rec.position is None else _span(rec.position, lo, hi))

    def replay(self) -> Iterator[RecordingChunk]:
        """Yield the chunks again (the second pass)."""
        return self.chunks()

    def again(self) -> Iterator[RecordingChunk]:
        """Yield the chunks again within the first pass (windows found at its end)."""
        return self.chunks()

    def passthrough(self) -> PassThrough | None:
        """Return the input's chunks to copy as they are, when the file is intact and indexed."""
        return None if self.recording.problems else pass_through(self.recording.path)


S = TypeVar("S", VectorSeries, AttitudeSeries, PositionSeries)


def _span(series: S, lo: int | None, hi: int | None) -> S:
    """Return the rows of a sorted series with ``lo <= t < hi`` (None: unbounded)."""
    t = series.t_ns
    i0 = 0 if lo is None else int(np.searchsorted(t, lo, "left"))
    i1 = len(t) if hi is None else int(np.searchsorted(t, hi, "left"))
    return _rows(series, i0, max(i0, i1))


def _rows(series: S, i0: int, i1: int) -> S:
    if isinstance(series, VectorSeries):
        return dataclasses.replace(series, t_ns=series.t_ns[i0:i1], values=series.values[i0:i1])
    if isinstance(series, AttitudeSeries):
        return dataclasses.replace(series, t_ns=series.t_ns[i0:i1],
                                   q_enu_body=series.q_enu_body[i0:i1])
    return dataclasses.replace(series, t_ns=series.t_ns[i0:i1], p_m=series.p_m[i0:i1])


class FileSource:
    """A long intact indexed file: decoded range by range once, then replayed.

    Parameters
    ----------
    path : path
        The recording (never modified).
    header : Recording
        Its channels, topics, encoding and frame names
        (:func:`pipeline.io.mcap_header.read_recording_header`).
    passthrough : PassThrough
        Its chunks, copied as they are into the corrected MCAP.
    n_mag : int
        Its magnetometer messages.
    options : ProcessOptions
        The channels to read.

    """

    one_chunk = False

    def __init__(self, path: str | Path, header: Recording, passthrough: PassThrough,
                 n_mag: int, options: ProcessOptions) -> None:
        self.path = Path(path)
        self.header = header
        self._passthrough = passthrough
        self.n_mag = n_mag
        self.start_ns = min(c.start_ns for c in passthrough.chunks)
        self.end_ns = max(c.end_ns for c in passthrough.chunks)
        self.options = options
        self._spill: _Spill | None = None

    def spill_to(self, folder: Path) -> None:
        """Keep the decoded samples of the first pass in ``folder`` for the second."""
        self._spill = _Spill(folder)

    def chunks(self) -> Iterator[RecordingChunk]:
        """Decode the file range by range (the first pass)."""
        for ch in iter_recording_chunks(self.path, max_messages=RANGE_MESSAGES,
                                        mag_topic=self.options.mag_topic,
                                        attitude_topic=self.options.attitude_topic):
            if self._spill is not None:
                self._spill.write(ch)
            yield ch

    def replay(self) -> Iterator[RecordingChunk]:
        """Yield the first pass's chunks again from the spill file (the second pass)."""
        assert self._spill is not None, "the first pass was not spilled"
        return self._spill.chunks(last=True)

    def again(self) -> Iterator[RecordingChunk]:
        """Yield the chunks again within the first pass (windows found at its end).

        From the spill file when there is one (it stays for the second pass), else decoded
        from the file again.
        """
        if self._spill is not None:
            return self._spill.chunks(last=False)
        return iter_recording_chunks(self.path, max_messages=RANGE_MESSAGES,
                                     mag_topic=self.options.mag_topic,
                                     attitude_topic=self.options.attitude_topic)

    def passthrough(self) -> PassThrough | None:
        """Return the input's chunks, copied as they are."""
        return self._passthrough


Source = MemorySource | FileSource


class _Spill:
    """The decoded samples of the first pass, in an anonymous file, for the second.

    Reading them back is a copy of 72 bytes a sample pair; decoding the MCAP again (CDR,
    zstd) costs ten times more. The file (next to the outputs) goes away with the object.
    """

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        try:
            self._fh = tempfile.TemporaryFile(dir=str(folder))
        except OSError as exc:
            raise self._error(exc) from exc
        self.n_chunks = 0
        self.position: PositionSeries | None = None  # frame and origin of the positions

    def _error(self, exc: OSError) -> OutputError:
        return OutputError(f"cannot keep the decoded samples for the second pass: "
                           f"{exc.strerror or exc}", path=self.folder,
                           hint="a long recording needs about 72 bytes a sample pair of free "
                           "space beside the outputs while it is processed")

    def write(self, ch: RecordingChunk) -> None:
        att, pos = ch.attitude, ch.position
        m = 0 if att is None else len(att.t_ns)
        k = 0 if pos is None else len(pos.t_ns)
        try:
            np.array([len(ch.mag.t_ns), m, k], dtype=np.int64).tofile(self._fh)
            np.ascontiguousarray(ch.mag.t_ns, dtype=np.int64).tofile(self._fh)
            np.ascontiguousarray(ch.mag.values, dtype=np.float64).tofile(self._fh)
            if att is not None and m:
                np.ascontiguousarray(att.t_ns, dtype=np.int64).tofile(self._fh)
                np.ascontiguousarray(att.q_enu_body, dtype=np.float64).tofile(self._fh)
            if pos is not None and k:
                np.ascontiguousarray(pos.t_ns, dtype=np.int64).tofile(self._fh)
                np.ascontiguousarray(pos.p_m, dtype=np.float64).tofile(self._fh)
                if self.position is None:  # frame and origin: the same in every chunk
                    self.position = dataclasses.replace(pos, t_ns=pos.t_ns[:0],
                                                        p_m=pos.p_m[:0])
        except OSError as exc:
            raise self._error(exc) from exc
        self.n_chunks += 1

    def chunks(self, last: bool) -> Iterator[RecordingChunk]:
        """Yield the chunks written; ``last``: the file goes away after them."""
        fh = self._fh
        fh.flush()
        fh.seek(0)
        mag_like = VectorSeries(np.zeros(0, np.int64), np.zeros((0, 3)))
        for j in range(self.n_chunks):
            n, m, k = (int(x) for x in np.fromfile(fh, np.int64, 3))
            mt = np.fromfile(fh, np.int64, n)
            mv = np.fromfile(fh, np.float64, 3 * n).reshape(n, 3)
            att = None
            if m:
                at = np.fromfile(fh, np.int64, m)
                aq = np.fromfile(fh, np.float64, 4 * m).reshape(m, 4)
                att = AttitudeSeries(at, aq)
            pos = None
            if k:
                pt = np.fromfile(fh, np.int64, k)
                pp = np.fromfile(fh, np.float64, 3 * k).reshape(k, 3)
                assert self.position is not None  # set with the first positions written
                pos = dataclasses.replace(self.position, t_ns=pt, p_m=pp)
            yield RecordingChunk(j, dataclasses.replace(mag_like, t_ns=mt, values=mv), att,
                                 None, pos)
        if last:
            fh.close()


def open_source(path: str | Path, options: ProcessOptions, *, warn: bool = False) -> Source:
    """Return the source of ``path``: a long intact indexed file, or the recording in memory.

    A file is read range by range when the options allow it (``scale_samples``), it holds
    more magnetometer messages than that, is intact and indexed (its chunks can be copied
    as they are), and its attitude is not a turntable's (the axis-tilt fit needs the whole
    rotation). Otherwise the recording is read whole (a damaged file: what the reader
    recovers). ``warn``: what the reader repaired is also warned (``RecoveredDataWarning``).
    """
    if options.scale_samples is not None and options.turntable_topic is None:
        # a look at the file's indexes; what it finds wrong the reader says once, below (a
        # file read in ranges is intact)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                header = read_recording_header(path, mag_topic=options.mag_topic,
                                               attitude_topic=options.attitude_topic)
        except MagalignError:
            # the whole read below fails the same way, and warns first what damage it met
            # (the reason a channel may be missing)
            header = None
        mag = None if header is None else next(
            (c for c in header.channels if c.topic == header.mag_topic), None)
        if (header is not None and mag is not None and mag.count > options.scale_samples
                and header.attitude is not None):
            pt = pass_through(path)
            if pt is not None and pt.chunks:
                return FileSource(path, header, pt, int(mag.count), options)
    read = read_recording_warning if warn else read_recording
    rec = read(path, mag_topic=options.mag_topic, attitude_topic=options.attitude_topic,
               turntable_topic=options.turntable_topic)
    return MemorySource(rec)

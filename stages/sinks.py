"""The outputs of a run as sinks: each takes the restored chunks of a recording and closes.

The runner (:mod:`pipeline.run`) opens every sink with what the analysis found
(:class:`RunStart`), hands it every chunk's :class:`~stages.restore.RestoreResult` in time
order, lets it prepare what needs no other output (:meth:`Sink.prepare`, on the runner's
helper thread, while the others close) and closes it with what the run ends with
(:class:`RunEnd`). The metrics close first: the report quotes them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from pipeline.core.recording import Recording, Segment
from pipeline.io.mcap_read import PassThrough
from pipeline.model.calibration import Calibration
from stages.diagnose.result import Diagnosis
from stages.metrics import MetricsAccumulator, MetricsResult
from stages.report import make_figures, write_report
from stages.restore import RestoreResult, RestoreTotals
from stages.write_mcap import CorrectedMcapStream, corrected_path
from stages.write_rerun import RrdStream, rrd_path
from stages.write_results import write_results
from stages.write_survey import write_survey

Outputs = tuple[tuple[str, str], ...]


@dataclass(frozen=True)
class RunStart:
    """What the sinks open with.

    Attributes
    ----------
    recording : Recording
        The recording's channels, encoding, frame names and path (its series need not be
        there: a long recording is never held whole).
    calibration : Calibration
        The final model, restoring every chunk.
    segments : tuple of Segment or None
        The motion's segments over the whole recording.
    t0_ns : int
        The recording's first magnetometer stamp.
    passthrough : PassThrough or None
        The input's chunks, to be copied as they are (an intact indexed file).

    """

    recording: Recording
    calibration: Calibration
    segments: tuple[Segment, ...] | None
    t0_ns: int
    passthrough: PassThrough | None = None


@dataclass(frozen=True)
class RunEnd:
    """What the sinks close with.

    Attributes
    ----------
    recording : Recording
        The recording as the outputs show it: its channels, the kept rows' readings and the
        positions (every k-th of a long recording, all of a short one).
    calibration : Calibration
        The final model, with what the restore of every sample added (an applied
        calibration's verdict, a warning about the samples the analysis did not see).
    diagnosis : Diagnosis or None
    segments : tuple of Segment or None
    sample : RestoreResult
        The kept rows: every row, or every k-th of a long recording.
    totals : RestoreTotals
        Counts and residual of every sample.
    metrics : MetricsResult or None
        Set once the metrics sink has closed.

    """

    recording: Recording
    calibration: Calibration
    diagnosis: Diagnosis | None
    segments: tuple[Segment, ...] | None
    sample: RestoreResult
    totals: RestoreTotals
    metrics: MetricsResult | None = None


class Sink:
    """An output: opened once, given every restored chunk in time order, closed once.

    The methods a sink does not need do nothing.
    """

    #: the step name of its closing (progress line and timings)
    name: ClassVar[str] = "Output"

    def open(self, start: RunStart) -> None:
        """Start the output (nothing is written in place before :meth:`close`)."""

    def add(self, chunk: RestoreResult) -> None:
        """Take the next restored rows."""

    def prepare(self, end: RunEnd) -> None:
        """Do what needs none of the other outputs (runs while they close)."""

    def close(self, end: RunEnd) -> Outputs:
        """Finish the output; return ``(name, path)`` of each file written."""
        raise NotImplementedError

    def discard(self, exc: BaseException) -> None:
        """Drop a run that failed with ``exc``: no output file appears.

        Raises the error the output makes of ``exc`` (a full disk is an ``OutputError``).
        """


class MetricsSink(Sink):
    """``metrics.json`` and ``metrics.parquet`` (:mod:`stages.metrics`)."""

    name: ClassVar[str] = "Metrics"

    def __init__(self, out_dir: str | Path) -> None:
        self.out_dir = Path(out_dir)
        self.result: MetricsResult | None = None
        self._acc: MetricsAccumulator | None = None
        self._input = ""

    def open(self, start: RunStart) -> None:
        """Start the accumulator (Tang's heading errors for a turntable recording)."""
        turntable = start.recording.turntable is not None
        self._input = start.recording.path
        self._acc = MetricsAccumulator(
            start.segments, start.t0_ns, spill_dir=self.out_dir,
            heading_reference_enu_nT=start.calibration.B_enu_nT if turntable else None)

    def add(self, chunk: RestoreResult) -> None:
        """Merge the chunk's moments."""
        assert self._acc is not None
        self._acc.add(chunk)

    def close(self, end: RunEnd) -> Outputs:
        """Write the metrics; :attr:`result` holds them."""
        assert self._acc is not None
        self.result = self._acc.finish()
        j, pq = self.result.write(self.out_dir, (self._input,))
        return (("metrics.json", str(j)), ("metrics.parquet", str(pq)))

    def discard(self, exc: BaseException) -> None:
        """Drop the accumulator's temporary file."""
        self._acc = None


class ResultsSink(Sink):
    """``calibration.json`` and ``diagnosis.json`` (:mod:`stages.write_results`)."""

    name: ClassVar[str] = "WriteResults"

    def __init__(self, out_dir: str | Path) -> None:
        self.out_dir = Path(out_dir)

    def close(self, end: RunEnd) -> Outputs:
        """Write the final calibration and the diagnosis."""
        return write_results(self.out_dir, end.calibration, end.diagnosis)


class CorrectedMcapSink(Sink):
    """``<stem>.corrected.mcap`` (:mod:`stages.write_mcap`).

    An intact indexed input is copied chunk by chunk as the rows come; a damaged one is
    copied range by range at the end (its readable messages, with the rows kept until then).
    """

    name: ClassVar[str] = "WriteCorrectedMcap"

    def __init__(self, out_dir: str | Path) -> None:
        self.out_dir = Path(out_dir)
        self._stream: CorrectedMcapStream | None = None
        self._held: list[RestoreResult] | None = None
        self._dest = Path()

    def open(self, start: RunStart) -> None:
        """Open the file (under a temporary name) with the input's channels."""
        self._dest = corrected_path(self.out_dir, start.recording.path)
        self._stream = CorrectedMcapStream(start.recording, start.calibration, self._dest,
                                           start.passthrough)
        self._stream.__enter__()
        self._held = [] if start.passthrough is None else None

    def add(self, chunk: RestoreResult) -> None:
        """Write the chunk's new messages after the input chunks before them."""
        assert self._stream is not None
        if self._held is not None:
            self._held.append(chunk)
        else:
            self._stream.add_ranges(chunk)

    def close(self, end: RunEnd) -> Outputs:
        """Write the rest of the input, the final calibration and the summary."""
        assert self._stream is not None
        self._stream.cal_text = end.calibration.to_json()
        if self._held is not None and self._held:
            self._stream.copy_input_around(RestoreResult.concat(self._held))
        self._held = None
        self._stream.__exit__(None, None, None)
        return (("corrected_mcap", str(self._dest)),)

    def discard(self, exc: BaseException) -> None:
        """Drop the temporary file."""
        if self._stream is not None:
            stream, self._stream = self._stream, None
            stream.__exit__(type(exc), exc, exc.__traceback__)


class RerunSink(Sink):
    """``<stem>.rrd`` (:mod:`stages.write_rerun`).

    Parameters
    ----------
    out_dir : path
    max_points : int
        Most points per static 3D view.

    """

    name: ClassVar[str] = "WriteRerun"

    def __init__(self, out_dir: str | Path, max_points: int = 20000) -> None:
        self.out_dir = Path(out_dir)
        self.max_points = max_points
        self._stream: RrdStream | None = None
        self._start: RunStart | None = None
        self._dest = Path()

    def open(self, start: RunStart) -> None:
        """Name the file; rerun opens it with the first rows (after the other outputs')."""
        self._dest = rrd_path(self.out_dir, start.recording.path)
        self._start = start

    def _opened(self) -> RrdStream:
        if self._stream is None:
            assert self._start is not None, "open() first"
            stream = RrdStream(self._start.recording, self._start.calibration, self._dest)
            stream.__enter__()
            self._stream = stream
        return self._stream

    def add(self, chunk: RestoreResult) -> None:
        """Send the chunk's time series."""
        self._opened().add(chunk)

    def close(self, end: RunEnd) -> Outputs:
        """Send the 3D views, segments and diagnosis; flush and rename the file."""
        stream = self._opened()
        stream.recording, stream.calibration = end.recording, end.calibration
        stream.finish(end.sample, segments=end.segments, diagnosis=end.diagnosis,
                      max_points=self.max_points)
        stream.__exit__(None, None, None)
        return (("rrd", str(self._dest)),)

    def discard(self, exc: BaseException) -> None:
        """Drop the temporary file."""
        if self._stream is not None:
            stream, self._stream = self._stream, None
            stream.__exit__(type(exc), exc, exc.__traceback__)


class ReportSink(Sink):
    """``report.html`` and its figures (:mod:`stages.report`).

    Parameters
    ----------
    out_dir : path
    estimator : str or None
        The estimator asked for (None: the default), named in the report.
    calibration_path : str or None
        The calibration file applied instead of estimating, named in the report.

    """

    name: ClassVar[str] = "Report"

    def __init__(self, out_dir: str | Path, *, estimator: str | None = None,
                 calibration_path: str | None = None) -> None:
        self.out_dir = Path(out_dir)
        self.estimator = estimator
        self.calibration_path = calibration_path
        self._figures: dict[str, bytes] | None = None

    def prepare(self, end: RunEnd) -> None:
        """Draw the figures (they need neither the metrics nor the other outputs)."""
        self._figures = make_figures(end.recording, end.calibration, end.segments,
                                     restored=end.sample, diagnosis=end.diagnosis)

    def close(self, end: RunEnd) -> Outputs:
        """Write the figures and the report."""
        path = write_report(self.out_dir, end.recording, end.calibration, end.metrics,
                            end.diagnosis, end.segments, restored=end.sample,
                            totals=end.totals, estimator=self.estimator,
                            calibration_path=self.calibration_path, figures=self._figures)
        return (("report.html", str(path)),)


class SurveySink(Sink):
    """``targets.csv`` and ``anomaly.nc`` of a recording with positions (:mod:`.write_survey`).

    Closes before the rerun recording and the report, which show the grid it wrote.
    """

    name: ClassVar[str] = "WriteSurvey"

    def __init__(self, out_dir: str | Path) -> None:
        self.out_dir = Path(out_dir)
        self._t0_ns = 0

    def open(self, start: RunStart) -> None:
        """Keep the first magnetometer stamp (the closest approach counts from it)."""
        self._t0_ns = start.t0_ns

    def close(self, end: RunEnd) -> Outputs:
        """Write both files; nothing for a recording without positions."""
        return write_survey(self.out_dir, end.recording, end.sample, end.calibration,
                            end.diagnosis, self._t0_ns)

"""The plan of a run: the options turned into the analysis' stages and the output sinks.

A recording with at most ``scale_samples`` magnetometer samples is analysed whole. A longer
one is analysed on what the runner's first pass keeps of it (:mod:`pipeline.run.runner`):
:data:`DIAGNOSIS_WINDOWS` windows at the full rate of both sensors, about
:data:`DECIMATED_SAMPLES` magnetometer samples in all, for the estimators that need the
samples and for the diagnosis (its effects live at the sensors' own rates, which a
decimated series would hide; windows spread over the recording keep its slow terms
interpolated, never extrapolated); every k-th aligned sample for the segmentation; and the
sums of every sample for the ML estimate (:class:`stages.estimate_sums.EstimateFromSums`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.recording import Recording
from pipeline.core.stage import Stage, stage_name
from pipeline.core.vocabulary import EstimateTerm, EstimatorKind, RobustLoss
from pipeline.run.options import ProcessOptions
from stages.check_applied import CheckApplied, calibration_source
from stages.context import Context
from stages.diagnose.stage import Diagnose
from stages.estimate import Estimate, Judge
from stages.estimate_sums import EstimateFromSums
from stages.exclude import Exclude, NoteExclusions
from stages.load_calibration import LoadCalibration
from stages.require_observable import RequireObservable
from stages.resample import Resample
from stages.segment import SegmentMotion
from stages.sinks import (
    CorrectedMcapSink,
    MetricsSink,
    ReportSink,
    RerunSink,
    ResultsSink,
    Sink,
    SurveySink,
)
from stages.turntable import AxisTiltNote, plan_turntable

#: a long recording's analysis sees at most this many magnetometer samples (segmentation:
#: every k-th; diagnosis: this many in whole windows)
DECIMATED_SAMPLES = 150_000
#: windows of full-rate data the analysis of a long recording sees, spread evenly over it
DIAGNOSIS_WINDOWS = 12
#: magnetometer samples per chunk of a long recording held in memory (a damaged file's
#: recovered samples, a turntable's): about one range of the file's
CHUNK_SAMPLES = 100_000


@dataclass(frozen=True)
class FirstPass:
    """What the analysis stages of a long recording take from the runner's first pass.

    Attributes
    ----------
    max_gap_s : float
        The recording's gap rule (its first range's, when the options give none).
    n_excluded : int
        Magnetometer samples inside the ``--exclude`` windows.

    """

    max_gap_s: float
    n_excluded: int = 0


@dataclass(frozen=True)
class Plan:
    """How one recording is run.

    Attributes
    ----------
    options : ProcessOptions
    n_mag : int
        Magnetometer samples of the recording.
    windowed : bool
        The analysis sees windows of the recording (docs/modules.md), not all of it.
    chunk_samples : int or None
        Magnetometer samples per chunk of a recording held in memory; None: one chunk.
    prepare : tuple of Stage
        Run on the whole recording before it is chunked (a turntable's attitude).
    tilt_note : AxisTiltNote or None
        A turntable's axis tilt (or why it is not identifiable), after the estimate.

    """

    options: ProcessOptions
    n_mag: int
    windowed: bool
    chunk_samples: int | None
    prepare: tuple[Stage[Context], ...] = ()
    tilt_note: AxisTiltNote | None = None

    @property
    def keep_every(self) -> int:
        """Every k-th aligned (first pass) and restored (second pass) row kept: k."""
        return max(1, -(-self.n_mag // DECIMATED_SAMPLES)) if self.windowed else 1

    def segmentation(self) -> list[Stage[Context]]:
        """Stages on every k-th aligned sample of a long recording (before its analysis)."""
        return [SegmentMotion()]

    def step_names(self) -> list[str]:
        """Return the names of the analysis' stages in the order they run (the progress line).

        A long recording's motion is segmented in its first pass, before the analysis; what
        the first pass finds configures the stages but does not change their names.
        """
        if not self.windowed:
            return [stage_name(s) for s in self.analysis_stages()]
        stages = [*self.segmentation(), *self.analysis_stages(FirstPass(max_gap_s=1.0))]
        return [stage_name(s) for s in stages]

    def analysis_stages(self, first: FirstPass | None = None) -> list[Stage[Context]]:
        """Return the stages from Resample to the verdict (every command runs these).

        ``first``: what the first pass found in a long recording (None: the analysis sees
        the whole recording). The model is the one the data select (the estimate, then the
        diagnosis' terms) unless the options restrict it (:func:`restricted_model`); then the
        estimate stays the answer and the diagnosis measures how far the terms left out move
        the rotation (its sigma includes that).
        """
        o = self.options
        excl = tuple(o.exclude)
        stages: list[Stage[Context]] = [
            Resample(max_gap_s=o.max_gap_s if first is None else first.max_gap_s)]
        if excl:
            stages.append(Exclude(excl))
        if first is None:
            stages.append(SegmentMotion())
        if o.calibration_path is not None:
            # the calibration run's verdict is not this recording's: checked here on its own
            stages += [LoadCalibration(str(o.calibration_path)),
                       CheckApplied(calibration_source(o.calibration_path),
                                    max_gap_s=o.max_gap_s)]
        else:
            if first is not None and streams_estimate(o):
                terms = frozenset(EstimateTerm(t) for t in o.terms)
                stages.append(EstimateFromSums(terms, reference_field(o)))
            else:
                stages.append(Estimate(**estimate_kwargs(o)))
            stages.append(RequireObservable())
            if o.diagnose:
                # the final model (more effects) replaces the calibration: the field is
                # restored and measured with it
                stages.append(Diagnose(**diagnose_kwargs(o)))
            if self.tilt_note is not None:
                stages.append(self.tilt_note)
            stages.append(Judge())
        if excl:
            stages.append(NoteExclusions(
                excl, n_samples=None if first is None else first.n_excluded))
        return stages

    def sinks(self, out_dir: str | Path) -> list[Sink]:
        """Return the outputs of ``process`` into ``out_dir``, the metrics first."""
        o = self.options
        sinks: list[Sink] = [MetricsSink(out_dir), ResultsSink(out_dir),
                             CorrectedMcapSink(out_dir), SurveySink(out_dir)]
        if o.write_rerun:
            sinks.append(RerunSink(out_dir))
        if o.write_report:
            estimator = None if o.estimator is None else EstimatorKind(o.estimator).value
            sinks.append(ReportSink(out_dir, estimator=estimator,
                                    calibration_path=o.calibration_path))
        return sinks


def windows_ns(start_ns: int, end_ns: int, n_mag: int) -> np.ndarray:
    """Return a long recording's analysis windows, (W, 2) int64 ns, half-open, evenly spread.

    ``start_ns``, ``end_ns``: the recording's span; ``n_mag``: its magnetometer samples.
    """
    span = end_ns - start_ns
    share = min(1.0, DECIMATED_SAMPLES / max(n_mag, 1))
    length = span * share / DIAGNOSIS_WINDOWS
    centres = start_ns + (np.arange(DIAGNOSIS_WINDOWS) + 0.5) * span / DIAGNOSIS_WINDOWS
    lo = np.floor(centres - length / 2).astype(np.int64)
    return np.stack([lo, lo + int(np.ceil(length))], axis=1)


def make_plan(options: ProcessOptions, n_mag: int, recording: Recording | None = None) -> Plan:
    """Return the plan for a recording of ``n_mag`` magnetometer samples.

    ``recording``: the recording when it is held in memory (a turntable's attitude is made
    from its whole angle channel first).
    """
    windowed = options.scale_samples is not None and n_mag > options.scale_samples
    prepare: tuple[Stage[Context], ...] = ()
    tilt_note = None
    if recording is not None and recording.attitude is None and recording.turntable is not None:
        # fits the axis tilt when a reference field makes it identifiable (Tang 2016)
        attitude_stage, note = plan_turntable(
            recording, reference_field_enu_nT=options.reference_field_enu_nT)
        prepare = (attitude_stage,)
        tilt_note = note if options.calibration_path is None else None
    return Plan(options, n_mag, windowed, CHUNK_SAMPLES if windowed else None, prepare,
                tilt_note)


def reference_field(options: ProcessOptions) -> tuple[float, float, float] | None:
    """Return the known background field of the options (ENU, nT), as floats."""
    ref = options.reference_field_enu_nT
    return None if ref is None else (float(ref[0]), float(ref[1]), float(ref[2]))


def restricted_model(options: ProcessOptions) -> bool:
    """Whether the user chose the model (``--estimate``, another estimator, a robust loss).

    Then the estimate is the answer of every command, and its sigma includes the shift of
    the rotation that the terms the data select, but the choice leaves out, would cause.
    """
    other = (options.estimator is not None
             and EstimatorKind(options.estimator) is not EstimatorKind.ML)
    return bool(options.terms) or other or RobustLoss(options.robust) is not RobustLoss.NONE


def estimate_kwargs(options: ProcessOptions) -> dict[str, Any]:
    """Keywords of :class:`stages.estimate.Estimate` for these options."""
    kw: dict[str, Any] = {"terms": frozenset(options.terms)}
    if options.estimator is not None:
        kw["estimator"] = options.estimator
    if options.robust != "none":
        kw["robust"] = RobustLoss(options.robust)
    if options.reference_field_enu_nT is not None:
        kw["reference_field_enu_nT"] = reference_field(options)
    return kw


def diagnose_kwargs(options: ProcessOptions) -> dict[str, Any]:
    """Keywords of :class:`stages.diagnose.stage.Diagnose` for these options."""
    dkw: dict[str, Any] = {"max_gap_s": options.max_gap_s,
                           "keep_estimate": restricted_model(options)}
    if options.reference_field_enu_nT is not None:
        dkw["reference_field_enu_nT"] = reference_field(options)
    return dkw


def streams_estimate(options: ProcessOptions) -> bool:
    """Whether the sums of every sample can make the estimate asked for (ML, its terms)."""
    ml = options.estimator is None or EstimatorKind(options.estimator) is EstimatorKind.ML
    return ml and {EstimateTerm(t) for t in options.terms} <= set(EstimateFromSums.SUPPORTED_TERMS)

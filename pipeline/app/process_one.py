"""The whole pipeline on one recording: ``process_recording(path, out_dir, options=...)``.

Stages (architecture.md)::

    Ingest -> [TurntableAttitude] -> Resample -> SegmentMotion -> Estimate | LoadCalibration
           -> [Diagnose] -> Restore -> Metrics -> WriteResults -> WriteCorrectedMcap
           -> [WriteRerun] -> [Report]

Writes ``out_dir/<stem>/`` with ``calibration.json``, ``diagnosis.json`` (when diagnosed),
``metrics.json``, ``metrics.parquet``, ``<stem>.corrected.mcap``, ``<stem>.rrd`` and
``report.html`` (plus the report's PNG figures), and returns one summary row (a dict of
plain JSON values) for the campaign summary.
"""

from __future__ import annotations

import importlib
import json
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from pipeline.core import progress
from pipeline.core.atomic import safe_join, write_text_atomic
from pipeline.core.errors import NotObservableError, RecoveredDataWarning
from pipeline.core.recording import Context
from pipeline.core.stage import Pipeline
from pipeline.model.calibration import Calibration


@dataclass(frozen=True)
class ProcessOptions:
    """What to do with one recording.

    Attributes
    ----------
    estimator : stages.estimate.EstimatorKind or None
        Estimator; ``None`` means the default of :class:`stages.estimate.Estimate` (ML).
    terms : frozenset of stages.estimate.Term
        Terms estimated beside the rotation (offset, soft_iron, time_offset).
    reference_field_enu_nT : tuple of 3 float, optional
        Known background field (ENU, nT); estimated when ``None``.
    calibration_path : str, optional
        Use this calibration.json instead of estimating (survey lines restored with the
        calibration run's result).
    mag_topic, attitude_topic, turntable_topic : str, optional
        Channels to use when a recording has more than one candidate.
    diagnose : bool
        Run DIAGNOSE's stage (when it is installed and no calibration file is given).
    write_rerun : bool
        Write ``<stem>.rrd``.
    write_report : bool
        Write ``report.html`` and its PNG figures.
    max_gap_s : float
        Longest attitude gap (s) bridged by interpolation.
    scale_samples : int or None
        Recordings with more magnetometer samples than this are processed at scale: the ML
        rotation (and offset) from chunked sufficient statistics of every sample
        (:class:`StreamingEstimate`), segmentation, other estimators and diagnosis on every
        k-th sample (:data:`DECIMATED_SAMPLES` of them); restoring, metrics and the outputs
        always use every sample. ``None``: never.

    """

    estimator: Any = None
    terms: frozenset = frozenset()
    reference_field_enu_nT: tuple[float, float, float] | None = None
    calibration_path: str | None = None
    mag_topic: str | None = None
    attitude_topic: str | None = None
    turntable_topic: str | None = None
    diagnose: bool = True
    write_rerun: bool = True
    write_report: bool = True
    max_gap_s: float | None = None
    scale_samples: int | None = 600_000


#: analysis stages of a long recording see at most this many magnetometer samples
DECIMATED_SAMPLES = 150_000
#: aligned samples reduced at once by :class:`StreamingEstimate` (bounds its temporaries)
STREAM_BLOCK = 200_000


@dataclass(frozen=True)
class StreamingEstimate:
    """Stage: ML rotation (and offset) of a long recording from chunked sufficient statistics.

    :mod:`stages.estimators.streaming`: the aligned samples are reduced block by block to a
    fixed set of sums and Gauss-Newton runs on the sums, so estimation costs one pass over
    the data and no per-sample matrices.
    """

    estimate_offset: bool = False
    reference_field_enu_nT: tuple[float, float, float] | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"aligned"})
    provides: ClassVar[frozenset[str]] = frozenset({"calibration"})

    def run(self, ctx: Context) -> Context:
        """Fit ``calibration`` from ``ctx.aligned``."""
        from stages.estimators.streaming import SufficientStats, fit_stats

        al = ctx.aligned
        blocks = (
            SufficientStats.from_samples(al.q_enu_body[i : i + STREAM_BLOCK],
                                         al.mag_nT[i : i + STREAM_BLOCK],
                                         al.t_ns[i : i + STREAM_BLOCK])
            for i in range(0, len(al), STREAM_BLOCK)
        )
        st = sum(blocks, SufficientStats())
        ref = None if self.reference_field_enu_nT is None else np.asarray(
            self.reference_field_enu_nT, dtype=float)
        fit = fit_stats(st, estimate_offset=self.estimate_offset, reference_field_enu_nT=ref)
        return ctx.replace(calibration=fit.to_calibration())


@dataclass(frozen=True)
class OnDecimated:
    """Stage: run ``inner`` on every ``step``-th magnetometer sample of a long recording.

    Segmentation and diagnosis of hours of data need not see every sample (their windows
    are seconds long); the fields ``inner`` provides are taken over into the full context.
    The attitude is kept whole so the decimated samples are aligned as before.
    """

    inner: Any
    step: int

    @property
    def requires(self) -> frozenset[str]:  # type: ignore[override]
        """The inner stage's requirements."""
        return self.inner.requires

    @property
    def provides(self) -> frozenset[str]:  # type: ignore[override]
        """The inner stage's results."""
        return self.inner.provides

    def run(self, ctx: Context) -> Context:
        """Run ``inner`` on the decimated context; return ``ctx`` with its results."""
        small = decimate_context(ctx, self.step)
        out = self.inner.run(small)
        return ctx.replace(**{k: getattr(out, k) for k in self.inner.provides})


def decimate_context(ctx: Context, step: int) -> Context:
    """``ctx`` with every ``step``-th magnetometer sample (recording.mag and aligned)."""
    import dataclasses

    from pipeline.core.recording import AlignedSeries, VectorSeries

    rec, al = ctx.recording, ctx.aligned
    changes: dict[str, Any] = {}
    if rec is not None:
        m = rec.mag
        changes["recording"] = dataclasses.replace(
            rec, mag=VectorSeries(m.t_ns[::step], m.values[::step], m.frame, m.unit))
    if al is not None:
        if al.index is not None:
            keep = np.flatnonzero(al.index % step == 0)
            index = al.index[keep] // step
        else:
            keep, index = np.arange(0, len(al), step), None
        changes["aligned"] = AlignedSeries(al.t_ns[keep], al.mag_nT[keep], al.q_enu_body[keep],
                                           al.time_offset_s, index)
    return ctx.replace(**changes)


@dataclass(frozen=True)
class LoadCalibration:
    """Stage: take the calibration from a calibration.json file instead of estimating it."""

    path: str

    requires: ClassVar[frozenset[str]] = frozenset()
    provides: ClassVar[frozenset[str]] = frozenset({"calibration"})

    def run(self, ctx: Context) -> Context:
        """Load ``path``."""
        return ctx.replace(calibration=Calibration.load(self.path))


@dataclass(frozen=True)
class RequireObservable:
    """Stage: refuse an estimate that no rotation axis of the recording's motion determines.

    A platform that did not rotate gives an arbitrary rotation; every output written from it
    (and every survey line restored with it) would look like a result. The ``calibrate``
    command refuses the same case. Not used when a calibration file is given: a survey line
    that never turns is restored with the calibration run's result.
    """

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "calibration"})
    provides: ClassVar[frozenset[str]] = frozenset()

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` as it is, or raise when nothing about the rotation is observable.

        Raises
        ------
        NotObservableError
            All three rotation axes unobservable.

        """
        if len(ctx.calibration.unobservable_axes_body) >= 3:
            raise NotObservableError(
                "the platform did not rotate: nothing about the misalignment is observable",
                path=ctx.recording.path,
                hint="record rotations about at least two different axes, or restore this "
                "recording with a calibration run's result (--calibration FILE)")
        return ctx.replace()  # a new Context, as every stage returns


@dataclass(frozen=True)
class WriteResults:
    """Stage: write calibration.json (and diagnosis.json when diagnosed) into ``out_dir``."""

    out_dir: str

    requires: ClassVar[frozenset[str]] = frozenset({"calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"outputs"})

    def run(self, ctx: Context) -> Context:
        """Write the JSON results atomically."""
        out = Path(self.out_dir)
        outputs = ctx.outputs
        p = write_text_atomic(out / "calibration.json", ctx.calibration.to_json())
        outputs += (("calibration.json", str(p)),)
        if ctx.diagnosis is not None:
            d = ctx.diagnosis.to_dict() if hasattr(ctx.diagnosis, "to_dict") else ctx.diagnosis
            p = write_text_atomic(out / "diagnosis.json", json.dumps(d, indent=2))
            outputs += (("diagnosis.json", str(p)),)
        return ctx.replace(outputs=outputs)


def _optional(module: str, name: str) -> Any:
    """Return a stage class from another engineer's module, or None while it is not installed."""
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name == module:
            return None
        raise
    return getattr(mod, name, None)


def build_stages(ctx: Context, out_dir: Path, options: ProcessOptions) -> list:
    """Return the stages after ingest, chosen from what the recording holds and the options."""
    from stages.metrics import Metrics
    from stages.resample import Resample
    from stages.restore import Restore
    from stages.write_mcap import WriteCorrectedMcap

    rec = ctx.recording
    stages: list = []
    n = len(rec.mag)
    large = options.scale_samples is not None and n > options.scale_samples
    step = max(1, -(-n // DECIMATED_SAMPLES)) if large else 1

    def scaled(stage: Any) -> Any:
        return OnDecimated(stage, step) if step > 1 else stage

    tilt_note = None
    if rec.attitude is None and rec.turntable is not None:
        from stages.turntable import plan_turntable

        # fits the axis tilt when a reference field makes it identifiable (Tang 2016)
        tt_stage, tilt_note = plan_turntable(
            rec, reference_field_enu_nT=options.reference_field_enu_nT
        )
        stages.append(tt_stage)
    stages.append(Resample(max_gap_s=options.max_gap_s))
    seg_cls = _optional("stages.segment", "SegmentMotion")
    if seg_cls is not None:
        stages.append(scaled(seg_cls()))
    if options.calibration_path is not None:
        stages.append(LoadCalibration(str(options.calibration_path)))
    else:
        from stages.estimate import Estimate, EstimatorKind, Term

        kw: dict[str, Any] = {"terms": frozenset(options.terms)}
        if options.estimator is not None:
            kw["estimator"] = options.estimator
        if options.reference_field_enu_nT is not None:
            kw["reference_field_enu_nT"] = tuple(float(x) for x in options.reference_field_enu_nT)
        terms = {Term(t) for t in options.terms}
        ml = options.estimator is None or EstimatorKind(options.estimator) is EstimatorKind.ML
        if large and ml and terms <= {Term.OFFSET}:
            # every sample, in bounded memory: chunked sufficient statistics
            stages.append(StreamingEstimate(Term.OFFSET in terms,
                                            kw.get("reference_field_enu_nT")))
        else:
            stages.append(scaled(Estimate(**kw)))
        stages.append(RequireObservable())
    if options.diagnose and options.calibration_path is None:
        diag_cls = _optional("stages.diagnose.stage", "Diagnose")
        if diag_cls is not None:
            # Diagnose replaces the calibration by its final model (more effects), so the
            # field is restored and measured after it, with that model.
            dkw: dict[str, Any] = {"max_gap_s": options.max_gap_s}
            if options.reference_field_enu_nT is not None:
                dkw["reference_field_enu_nT"] = tuple(
                    float(x) for x in options.reference_field_enu_nT
                )
            stages.append(scaled(diag_cls(**dkw)))
    if tilt_note is not None and options.calibration_path is None:
        stages.append(tilt_note)  # axis_tilt (or why not) into calibration effects/warnings
    if options.calibration_path is None:
        from stages.estimate import Judge

        stages.append(Judge())  # the verdict on the final model
    stages.append(Restore(max_gap_s=options.max_gap_s))
    stages.append(Metrics(out_dir=str(out_dir), max_gap_s=options.max_gap_s))
    stages.append(WriteResults(str(out_dir)))
    stages.append(WriteCorrectedMcap(str(out_dir), max_gap_s=options.max_gap_s))
    if options.write_rerun:
        from stages.write_rerun import WriteRerun

        stages.append(WriteRerun(str(out_dir), max_gap_s=options.max_gap_s))
    if options.write_report:
        from stages.report import Report

        stages.append(Report(str(out_dir), max_gap_s=options.max_gap_s))
    return stages


def _finite_list(a: Any) -> list | None:
    if a is None:
        return None
    return [None if not np.isfinite(x) else float(x) for x in np.asarray(a, dtype=float).ravel()]


def _verdict_line(cal: Calibration) -> str:
    from stages.estimate import verdict_line

    return verdict_line(cal)


def summary_row(ctx: Context, stem: str, out_dir: Path) -> dict[str, Any]:
    """One summary row of a processed recording (plain JSON values)."""
    cal = ctx.calibration
    m = ctx.metrics
    findings: list[str] = []
    if ctx.diagnosis is not None:
        d = ctx.diagnosis.to_dict() if hasattr(ctx.diagnosis, "to_dict") else ctx.diagnosis
        findings = [f.get("effect") for f in d.get("findings", [])]
    ratios = m.ratio_pct() if m is not None else {}
    row: dict[str, Any] = {
        "stem": stem,
        "status": "ok",
        "path": str(ctx.recording.path),
        "duration_s": float(ctx.recording.duration_s),
        "n_samples": int(len(ctx.recording.mag)),
        "estimator": cal.estimator,
        "rotvec_body_mag_deg": _finite_list(cal.rotvec_body_mag_deg),
        "sigma_rotvec_deg": _finite_list(cal.sigma_rotvec_deg),
        "residual_rms_nT": float(cal.residual_rms_nT),
        "offset_nT": _finite_list(cal.offset_nT),
        "time_offset_s": cal.time_offset_s,
        "warnings": list(cal.warnings),
        "verdict": None if cal.verdict is None else cal.verdict.status.value,
        "verdict_reason": None if cal.verdict is None else cal.verdict.reason,
        "verdict_line": _verdict_line(cal),
        "findings": findings,
        "out_dir": str(out_dir),
        "paths": {k: v for k, v in ctx.outputs},
    }
    for c in ("x", "y", "z"):
        r = ratios.get(c)
        row[f"ratio_pct_{c}"] = None if r is None or not np.isfinite(r) else float(r)
    return row


def process_recording(
    path: str | Path, out_dir: str | Path, *, options: ProcessOptions | None = None
) -> dict[str, Any]:
    """Run the whole pipeline on one recording.

    Parameters
    ----------
    path : path
        The MCAP recording (never modified).
    out_dir : path
        Results go to ``out_dir/<stem>/``.
    options : ProcessOptions, optional
        What to do; defaults throughout when omitted.

    Returns
    -------
    dict
        One summary row: ``stem``, ``status``, ``rotvec_body_mag_deg``, ``sigma_rotvec_deg``,
        ``residual_rms_nT``, ``ratio_pct_x/y/z`` (fluctuation range, whole recording),
        ``findings`` (effect names), ``paths`` (output name -> path), ``timings_s`` (stage
        name -> wall seconds), ``run_warnings`` (``[category, message]`` pairs: every warning
        raised while processing, and every problem the reader repaired; they are collected
        here, not shown, so that the caller can issue them where the user sees them) and
        more.

    Raises
    ------
    MagalignError
        Bad input, estimation failure, unwritable output.

    """
    from stages.ingest import Ingest

    options = options or ProcessOptions()
    path = Path(path)
    stem = path.stem
    rec_dir = safe_join(out_dir, stem)
    rec_dir.mkdir(parents=True, exist_ok=True)
    ctx = Context(source=str(path), options=options)
    ingest = Ingest(
        mag_topic=options.mag_topic,
        attitude_topic=options.attitude_topic,
        turntable_topic=options.turntable_topic,
    )
    timings: dict[str, float] = {}
    clock = {"name": None, "t": time.perf_counter()}
    shown: list[str] = ["Ingest"]  # stage names for the progress line (known after ingest)

    def tick(name: str | None, index: int = 0, total: int = 0) -> None:
        now = time.perf_counter()
        if clock["name"] is not None:
            timings[clock["name"]] = timings.get(clock["name"], 0.0) + now - clock["t"]
        clock["name"], clock["t"] = name, now
        if name is not None:
            i = index if name == "Ingest" else index + 1
            progress.stage(shown[i] if i < len(shown) else name, i, len(shown), shown)

    # Warnings are collected, not shown: this runs in a worker process whose stderr is not
    # the user's terminal (and has Python's two-line warning format); the command that
    # started the worker issues them once from the row (pipeline.app.commands.process).
    with warnings.catch_warnings(record=True) as caught, \
            progress.use_sink(progress.current() or progress.sink_from_env(stem)):
        ctx = Pipeline([ingest]).run(ctx, progress=tick)
        rest = Pipeline(build_stages(ctx, rec_dir, options),
                        initial=ctx.provided() | {"source"})
        shown[1:] = [progress_name(st) for st in rest.stages]
        ctx = rest.run(ctx, progress=tick)
    tick(None)
    row = summary_row(ctx, stem, rec_dir)
    row["timings_s"] = {k: round(v, 3) for k, v in timings.items()}
    row["run_warnings"] = run_warnings(str(path), caught, ctx.recording.problems)
    return row


def progress_name(stage: Any) -> str:
    """Return the name a stage goes by on the progress line (the inner stage of ``OnDecimated``)."""
    inner = getattr(stage, "inner", None)
    return type(inner if inner is not None else stage).__name__


def run_warnings(path: str, caught: list[warnings.WarningMessage],
                 problems: tuple) -> list[list[str]]:
    """Return the warnings of one run as ``[category name, message]`` pairs, each once.

    Parameters
    ----------
    path : str
        The recording.
    caught : list of warnings.WarningMessage
        What was warned while it was processed (the reader warns the damage it found in
        the file).
    problems : tuple of pipeline.core.recording.Problem
        ``Recording.problems``: also what the reader repaired in the data without warning
        (dropped NaN samples, sorted stamps, ...), which the user must hear too.

    Returns
    -------
    list of [str, str]
        JSON-able, in the order they arose; the problems as ``RecoveredDataWarning``.

    """
    from pipeline.io.mcap_read import problem_warnings

    out: list[list[str]] = []
    seen: set[str] = set()
    for w in caught:
        msg = str(w.message)
        if msg not in seen:
            seen.add(msg)
            out.append([w.category.__name__, msg])
    for msg in problem_warnings(path, problems, seen):
        if msg not in seen:
            seen.add(msg)
            out.append([RecoveredDataWarning.__name__, msg])
    return out

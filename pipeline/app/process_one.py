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
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from pipeline.core import progress
from pipeline.core.atomic import safe_join
from pipeline.core.errors import RecoveredDataWarning
from pipeline.core.recording import Context
from pipeline.core.stage import Pipeline
from pipeline.model.calibration import Calibration
from stages.decimate import OnDecimated
from stages.load_calibration import LoadCalibration
from stages.require_observable import RequireObservable
from stages.streaming_estimate import StreamingEstimate
from stages.write_results import WriteResults


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
    robust : str
        Robust loss of the estimate: ``none``, ``huber`` or ``cauchy``.
    exclude : tuple of stages.exclude.ExcludeWindow
        Stretches left out of the fit and the verdict (``--exclude``); restored like the rest.
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
    robust: str = "none"
    exclude: tuple = ()


#: analysis stages of a long recording see at most this many magnetometer samples
DECIMATED_SAMPLES = 150_000


def _optional(module: str, name: str) -> Any:
    """Return a stage class from another engineer's module, or None while it is not installed."""
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name == module:
            return None
        raise
    return getattr(mod, name, None)


def analysis_stages(ctx: Context, options: ProcessOptions) -> list:
    """Return the stages from Resample to the verdict (``calibrate``, ``diagnose``, ``process``).

    All three commands run these, so one recording and one set of options give one answer.

    The model is the one the data select (the estimate, then the diagnosis' terms) unless the
    options restrict it (:func:`restricted_model`); then the estimate stays the answer and the
    diagnosis measures how far the terms left out move the rotation (its sigma includes that).
    """
    from stages.resample import Resample

    rec = ctx.need_recording()
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
    if options.exclude:
        from stages.exclude import Exclude

        stages.append(Exclude(tuple(options.exclude)))
    seg_cls = _optional("stages.segment", "SegmentMotion")
    if seg_cls is not None:
        stages.append(scaled(seg_cls()))
    if options.calibration_path is not None:
        stages.append(LoadCalibration(str(options.calibration_path)))
        from stages.check_applied import CheckApplied, calibration_source

        # the calibration run's verdict is not this recording's: checked here on its own
        stages.append(CheckApplied(calibration_source(options.calibration_path),
                                   max_gap_s=options.max_gap_s))
    else:
        from stages.estimate import Estimate, Term

        kw = estimate_kwargs(options)
        if large and streams_estimate(options):
            # every sample, in bounded memory: chunked sufficient statistics
            terms = {Term(t) for t in options.terms}
            stages.append(StreamingEstimate(Term.OFFSET in terms,
                                            kw.get("reference_field_enu_nT"),
                                            frozenset(terms)))
        else:
            stages.append(scaled(Estimate(**kw)))
        stages.append(RequireObservable())
    if options.diagnose and options.calibration_path is None:
        diag_cls = _optional("stages.diagnose.stage", "Diagnose")
        if diag_cls is not None:
            # Diagnose replaces the calibration by its final model (more effects), so the
            # field is restored and measured after it, with that model.
            stages.append(scaled(diag_cls(**diagnose_kwargs(options))))
    if tilt_note is not None and options.calibration_path is None:
        stages.append(tilt_note)  # axis_tilt (or why not) into calibration effects/warnings
    if options.calibration_path is None:
        from stages.estimate import Judge

        stages.append(Judge())  # the verdict on the final model
    if options.exclude:
        from stages.exclude import NoteExclusions

        stages.append(NoteExclusions(tuple(options.exclude)))
    return stages


def restricted_model(options: ProcessOptions) -> bool:
    """Whether the user chose the model (``--estimate``, another estimator, a robust loss).

    Then the estimate is the answer of every command, and its sigma includes the shift of
    the rotation that the terms the data select, but the choice leaves out, would cause.
    """
    from stages.estimate import EstimatorKind, RobustLoss

    other = (options.estimator is not None
             and EstimatorKind(options.estimator) is not EstimatorKind("ml"))
    return bool(options.terms) or other or RobustLoss(options.robust) is not RobustLoss.NONE


def analyse_recording(path: str | Path, options: ProcessOptions | None = None) -> Context:
    """Read one recording and run :func:`analysis_stages` on it; returns the Context.

    ``calibrate`` and ``diagnose`` call this; ``process`` runs the same stages followed by
    restore and the outputs (:func:`build_stages`). Each stage is announced on the progress
    sink as it starts; what the reader repaired is warned (``RecoveredDataWarning``).
    """
    from pipeline.io.mcap_read import read_recording_warning

    options = options or ProcessOptions()
    progress.stage("Ingest", 0, 1, ["Ingest"])
    rec = read_recording_warning(path, mag_topic=options.mag_topic,
                                 attitude_topic=options.attitude_topic,
                                 turntable_topic=options.turntable_topic)
    return analyse(Context(source=str(path), recording=rec, options=options), options)


def analyse(ctx: Context, options: ProcessOptions) -> Context:
    """Run :func:`analysis_stages` on a context that holds a recording (any span of one)."""
    rest = Pipeline(analysis_stages(ctx, options), initial=ctx.provided() | {"source"})
    names = ["Ingest"] + [progress_name(st) for st in rest.stages]

    def tick(name: str, index: int, total: int) -> None:
        progress.stage(names[index + 1], index + 1, len(names), names)

    return rest.run(ctx, progress=tick)


def build_stages(ctx: Context, out_dir: Path, options: ProcessOptions) -> list:
    """Return the stages after ingest: :func:`analysis_stages`, then restore and the outputs."""
    from stages.metrics import Metrics
    from stages.restore import Restore
    from stages.write_mcap import WriteCorrectedMcap

    stages = analysis_stages(ctx, options)
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


def estimate_kwargs(options: ProcessOptions) -> dict[str, Any]:
    """Keywords of :class:`stages.estimate.Estimate` for these options."""
    kw: dict[str, Any] = {"terms": frozenset(options.terms)}
    if options.estimator is not None:
        kw["estimator"] = options.estimator
    if options.robust != "none":
        from stages.estimate import RobustLoss

        kw["robust"] = RobustLoss(options.robust)
    if options.reference_field_enu_nT is not None:
        kw["reference_field_enu_nT"] = tuple(float(x) for x in options.reference_field_enu_nT)
    return kw


def diagnose_kwargs(options: ProcessOptions) -> dict[str, Any]:
    """Keywords of :class:`stages.diagnose.stage.Diagnose` for these options."""
    dkw: dict[str, Any] = {"max_gap_s": options.max_gap_s,
                           "keep_estimate": restricted_model(options)}
    if options.reference_field_enu_nT is not None:
        dkw["reference_field_enu_nT"] = tuple(float(x) for x in options.reference_field_enu_nT)
    return dkw


def streams_estimate(options: ProcessOptions) -> bool:
    """Whether the streaming estimator can make the estimate asked for (ML, its terms)."""
    from stages.estimate import EstimatorKind, Term

    ml = options.estimator is None or EstimatorKind(options.estimator) is EstimatorKind("ml")
    return ml and {Term(t) for t in options.terms} <= set(StreamingEstimate.SUPPORTED_TERMS)


def _finite_list(a: Any) -> list | None:
    if a is None:
        return None
    return [None if not np.isfinite(x) else float(x) for x in np.asarray(a, dtype=float).ravel()]


def _verdict_line(cal: Calibration) -> str:
    from stages.estimate import verdict_line

    return verdict_line(cal)


def summary_row(ctx: Context, stem: str, out_dir: Path) -> dict[str, Any]:
    """One summary row of a processed recording (plain JSON values)."""
    cal = ctx.need_calibration()
    rec = ctx.need_recording()
    m = ctx.metrics
    findings: list[str] = []
    if ctx.diagnosis is not None:
        d = cast(dict[str, Any], ctx.diagnosis.to_dict() if hasattr(ctx.diagnosis, "to_dict")
                 else ctx.diagnosis)
        findings = [f.get("effect") for f in d.get("findings", [])]
    ratios = m.ratio_pct() if m is not None else {}
    row: dict[str, Any] = {
        "stem": stem,
        "status": "ok",
        "path": str(rec.path),
        "duration_s": float(m.whole.end_s) if m is not None else float(rec.duration_s),
        "n_samples": int(m.n_samples) if m is not None else int(len(rec.mag)),
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
    clock: dict[str, Any] = {"name": None, "t": time.perf_counter()}
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
        from pipeline.app.process_stream import plan_stream, process_stream

        plan = plan_stream(path, options)
        if plan is not None:  # long: two passes over the file, bounded memory
            ctx = process_stream(plan, path, rec_dir, options, tick, shown)
        else:
            ctx = Pipeline([ingest]).run(ctx, progress=tick)
            rest = Pipeline(build_stages(ctx, rec_dir, options),
                            initial=ctx.provided() | {"source"})
            shown[1:] = [progress_name(st) for st in rest.stages]
            ctx = rest.run(ctx, progress=tick)
    tick(None)
    row = summary_row(ctx, stem, rec_dir)
    row["timings_s"] = {k: round(v, 3) for k, v in timings.items()}
    row["run_warnings"] = run_warnings(str(path), caught, ctx.need_recording().problems)
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

"""The runner: every command's one way through a recording.

More in docs/modules.md, ``pipeline.run.runner``.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import time
import warnings
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core import progress
from pipeline.core.atomic import safe_join
from pipeline.core.errors import InputError, MagalignError, RecoveredDataWarning, damage_behind
from pipeline.core.memory import release_free_memory
from pipeline.core.recording import (
    AlignedSeries,
    AttitudeSeries,
    PositionSeries,
    Problem,
    Recording,
    Segment,
    VectorSeries,
)
from pipeline.core.stage import Pipeline, stage_name
from pipeline.core.verdict import verdict_line
from pipeline.core.vocabulary import EstimateTerm
from pipeline.core.warm import warm_in_background
from pipeline.io.mcap_read import RecordingChunk, problem_warnings
from pipeline.model.attitude import AttitudeInterpolator, auto_max_gap_s, estimate_cubic_weight
from pipeline.model.calibration import Calibration
from pipeline.run.options import ProcessOptions
from pipeline.run.passes import PASS_WINDOW_S, PassFinder
from pipeline.run.plan import FirstPass, Plan, make_plan, streams_estimate, windows_ns
from pipeline.run.source import FileSource, MemorySource, Source, open_source
from stages.check_applied import applied_verdict
from stages.context import Context
from stages.estimators.streaming import SampleSums, StreamAccumulator
from stages.exclude import excluded_mask
from stages.restore import (
    ChunkedAttitude,
    ChunkedRestore,
    RestoreResult,
    RestoreTotals,
    model_key_of,
)
from stages.sinks import MetricsSink, RunEnd, RunStart, Sink

#: attitude kept beyond each analysis window (s): its interpolation at the window's edges
WINDOW_MARGIN_S = 1.0
#: the final model's residual over every sample may exceed its residual on the analysed
#: samples by this factor before the user is warned
UNSEEN_RMS_RATIO = 1.25


# ------------------------------------------------------------------------------- steps
class Steps:
    """The run's steps on the progress line, and the wall time of each.

    Parameters
    ----------
    expected : sequence of str
        The steps expected after reading the file (:func:`expected_steps`): announced from
        the start, so that the count a step shows (``aligning (2/7)``) keeps its total
        through the run rather than growing as the plan becomes known.

    """

    def __init__(self, expected: Sequence[str] = ()) -> None:
        self.names: list[str] = ["Ingest", *(n for n in expected if n != "Ingest")]
        self.timings: dict[str, float] = {}
        self._current: str | None = None
        self._t = time.perf_counter()

    def _next(self) -> int:
        """Index of the first step not started yet."""
        return 0 if self._current is None else self.names.index(self._current) + 1

    def start(self, name: str | None) -> None:
        """Start step ``name`` (None: the run is over)."""
        now = time.perf_counter()
        if self._current is not None:
            self.timings[self._current] = self.timings.get(self._current, 0.0) + now - self._t
        if name is not None and name not in self.names:
            self.names.insert(self._next(), name)
        self._current, self._t = name, now
        if name is not None:
            progress.stage(name, self.names.index(name), len(self.names), self.names)

    def expect(self, names: list[str]) -> None:
        """Announce the steps that run next, in order (the progress line's count and time left).

        The steps expected up to the last of ``names`` are replaced by ``names``: the plan of
        the recording read (a long recording's first pass, a turntable's attitude) may differ
        from the one expected. The steps expected after it (the outputs) stay.
        """
        head = self.names[:self._next()]
        todo = [n for n in names if n not in head]
        later = self.names[len(head):]
        known = [i for i, n in enumerate(later) if n in todo]
        if known:
            later = later[known[-1] + 1:]
        self.names = head + todo + [n for n in later if n not in todo]

    def pipeline(self, pipe: Pipeline[Context], ctx: Context) -> Context:
        """Run ``pipe`` on ``ctx`` with each stage as a step."""
        self.expect([stage_name(s) for s in pipe.stages])
        return pipe.run(ctx, progress=lambda name, i, n: self.start(name))


def expected_steps(options: ProcessOptions, rec_dir: Path | None = None) -> list[str]:
    """Return the steps a run is expected to take after reading its recording.

    Those of a recording held in memory without a turntable (:func:`make_plan`), then, with
    ``rec_dir`` (``process``), restoring and each output. Only the stages' names are taken:
    nothing is read or written.
    """
    plan = make_plan(options, 0)
    names = [stage_name(s) for s in plan.analysis_stages()]
    if rec_dir is not None:
        names += ["Restore", *(s.name for s in plan.sinks(rec_dir))]
    return names


# ------------------------------------------------------------------------- first pass
@dataclasses.dataclass(frozen=True)
class AttitudeRule:
    """How the recording's attitude is interpolated in every chunk (its first chunk's).

    Attributes
    ----------
    max_gap_s : float
        Longest gap bridged, s.
    cubic_weight : float
        ``lam`` of (A7) (pipeline/model/attitude.py).
    step_s : float
        The attitude's spacing, s.

    """

    max_gap_s: float
    cubic_weight: float
    step_s: float

    @classmethod
    def of(cls, attitude: AttitudeSeries, max_gap_s: float | None) -> AttitudeRule:
        """Return the rule of an attitude series (and the options' gap, when they give one)."""
        gap = float(max_gap_s) if max_gap_s is not None else auto_max_gap_s(attitude.t_ns)
        dt = np.diff(np.unique(attitude.t_ns))
        step = float(np.median(dt)) * 1e-9 if len(dt) else 0.01
        return cls(gap, estimate_cubic_weight(attitude.t_ns, attitude.q_enu_body), step)


class _Kept:
    """What the first pass keeps of a long recording: its windows, every k-th aligned row."""

    def __init__(self, windows: np.ndarray, step: int) -> None:
        self.windows = windows
        self.step = step
        self.mag_t: list[np.ndarray] = []
        self.mag_v: list[np.ndarray] = []
        self.att_t: list[np.ndarray] = []
        self.att_q: list[np.ndarray] = []
        self.pos: list[PositionSeries] = []
        # every step-th position of the whole recording: the report's map of the path
        self.pos_thin: list[PositionSeries] = []
        self.n_pos = 0
        self.al: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.n_aligned = 0
        self.t_first_ns: int | None = None

    def _inside(self, t: np.ndarray, margin_ns: int = 0) -> np.ndarray:
        w = self.windows
        k = np.searchsorted(w[:, 0] - margin_ns, t, "right") - 1
        ok = k >= 0
        ok[ok] = t[ok] < w[k[ok], 1] + margin_ns
        return ok

    def chunk(self, ch: RecordingChunk) -> None:
        t = ch.mag.t_ns
        if len(t):
            t_min = int(t.min())
            self.t_first_ns = t_min if self.t_first_ns is None else min(self.t_first_ns, t_min)
        m = self._inside(t)
        if m.any():
            self.mag_t.append(t[m])
            self.mag_v.append(ch.mag.values[m])
        if ch.attitude is not None and len(ch.attitude):
            a = self._inside(ch.attitude.t_ns, int(WINDOW_MARGIN_S * 1e9))
            if a.any():
                self.att_t.append(ch.attitude.t_ns[a])
                self.att_q.append(ch.attitude.q_enu_body[a])
        if ch.position is not None and len(ch.position):
            first = (-self.n_pos) % self.step
            self.pos_thin.append(dataclasses.replace(
                ch.position, t_ns=ch.position.t_ns[first::self.step].copy(),
                p_m=ch.position.p_m[first::self.step].copy()))
            self.n_pos += len(ch.position)
            p = self._inside(ch.position.t_ns, int(WINDOW_MARGIN_S * 1e9))
            if p.any():
                self.pos.append(dataclasses.replace(ch.position, t_ns=ch.position.t_ns[p],
                                                    p_m=ch.position.p_m[p]))

    def add_windows(self, other: _Kept) -> None:
        """Take the samples ``other`` kept in its windows (disjoint from these) as well.

        The attitude and positions both kept about neighbouring windows (their margins) are
        kept once: ``other``'s rows already kept here are dropped.
        """
        margin = int(WINDOW_MARGIN_S * 1e9)
        self.mag_t += other.mag_t
        self.mag_v += other.mag_v
        for t, q in zip(other.att_t, other.att_q, strict=True):
            new = ~self._inside(t, margin)
            self.att_t.append(t[new])
            self.att_q.append(q[new])
        for p in other.pos:
            new = ~self._inside(p.t_ns, margin)
            self.pos.append(dataclasses.replace(p, t_ns=p.t_ns[new], p_m=p.p_m[new]))
        w = np.concatenate([self.windows, other.windows])
        self.windows = w[np.argsort(w[:, 0], kind="stable")]

    def aligned(self, q: np.ndarray, y: np.ndarray, t: np.ndarray) -> None:
        first = (-self.n_aligned) % self.step
        # copies: views would keep every block alive
        self.al.append((q[first::self.step].copy(), y[first::self.step].copy(),
                        t[first::self.step].copy()))
        self.n_aligned += len(t)

    def aligned_series(self) -> AlignedSeries:
        if not self.al:
            return AlignedSeries(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)))
        q, y, t = (np.concatenate(x) for x in zip(*self.al, strict=True))
        return AlignedSeries(t, y, q)

    def thin_positions(self, header: Recording) -> PositionSeries | None:
        """Every step-th position of the recording (the report's map), or None."""
        if header.position is None or not self.pos_thin:
            return None
        t = np.concatenate([p.t_ns for p in self.pos_thin])
        o = np.argsort(t, kind="stable")
        return dataclasses.replace(self.pos_thin[0], t_ns=t[o], p_m=np.concatenate(
            [p.p_m for p in self.pos_thin])[o], max_gap_s=None)

    def window_recording(self, header: Recording) -> Recording:
        def cat(parts: list[np.ndarray], shape: tuple[int, ...], dtype: Any) -> np.ndarray:
            return np.concatenate(parts) if parts else np.zeros(shape, dtype)

        mt, mv = cat(self.mag_t, (0,), np.int64), cat(self.mag_v, (0, 3), float)
        at, aq = cat(self.att_t, (0,), np.int64), cat(self.att_q, (0, 4), float)
        o = np.argsort(mt, kind="stable")
        oa = np.argsort(at, kind="stable")
        position = None
        if header.position is not None and self.pos:
            pt = np.concatenate([p.t_ns for p in self.pos])
            pp = np.concatenate([p.p_m for p in self.pos])
            op = np.argsort(pt, kind="stable")
            # the whole series' gap rule: the windows' positions must not bridge the
            # stretches between windows
            position = dataclasses.replace(self.pos[0], t_ns=pt[op], p_m=pp[op],
                                           max_gap_s=self.pos[0].gap_rule_s())
        return dataclasses.replace(
            header, mag=VectorSeries(mt[o], mv[o], header.mag.frame, header.mag.unit),
            attitude=AttitudeSeries(at[oa], aq[oa]), position=position,
            first_ns=self.t_first_ns)


@dataclasses.dataclass(frozen=True)
class Reduced:
    """What the first pass made of a long recording.

    Attributes
    ----------
    first : FirstPass
        What its analysis stages are built with.
    t0_ns : int
        The recording's first magnetometer stamp.
    rule : AttitudeRule
    windows_ns : ndarray (W, 2)
        The analysis windows, in time order: those spread over the recording and those where
        its field's magnitude stood out (:mod:`pipeline.run.passes`).
    n_pass_windows : int
        How many of them are of the second kind.
    recording : Recording
        The windows' samples (the header's channels).
    thin_aligned : AlignedSeries
        Every k-th aligned sample of the whole recording (the segmentation's).
    thin_positions : PositionSeries or None
        Every k-th position (the report's map).
    sums : SampleSums or None
        The sums of every aligned sample (None when no estimate is made from them).

    """

    first: FirstPass
    t0_ns: int
    rule: AttitudeRule
    windows_ns: np.ndarray
    n_pass_windows: int
    recording: Recording
    thin_aligned: AlignedSeries
    thin_positions: PositionSeries | None
    sums: SampleSums | None


def _settled(rows: tuple[np.ndarray, np.ndarray, AttitudeInterpolator] | None
             ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``(q_enu_body, mag_nT, t_ns)`` of the settled rows with a usable attitude."""
    if rows is None:
        return
    t, y, interp = rows
    at = interp.at(t, 0.0)
    ok = at.valid
    if ok.any():
        yield at.q_enu_body[ok], y[ok], t[ok]


def first_pass(source: Source, plan: Plan) -> Reduced:
    """Read a long recording's chunks once and reduce them (docs/modules.md)."""
    options = plan.options
    kept = _Kept(windows_ns(source.start_ns, source.end_ns, source.n_mag), plan.keep_every)
    chunks = source.chunks()
    first = next(chunks, None)
    if first is None:
        raise InputError("the recording holds no magnetometer sample", path=source.header.path)
    att0 = first.attitude if first.attitude is not None else source.header.attitude
    if att0 is None:
        raise InputError("the recording has no attitude", path=source.header.path)
    rule = AttitudeRule.of(att0, options.max_gap_s)
    excl = tuple(options.exclude)
    t0_excl: int | None = None
    n_excl = 0
    terms = {EstimateTerm(t) for t in options.terms}
    streamed = options.calibration_path is None and streams_estimate(options)
    # the sums of each half of the recording (split-half check of the sigmas) add up to the
    # whole's; soft iron and time offset: the expanded sums of every sample
    halves = [StreamAccumulator(max_gap_s=rule.max_gap_s, with_tau=False) for _ in range(2)]
    terms_acc = (StreamAccumulator(max_gap_s=rule.max_gap_s)
                 if streamed and terms - {EstimateTerm.OFFSET} else None)
    split_ns: int | None = None
    aligner = ChunkedAttitude(max_gap_s=rule.max_gap_s, cubic_weight=rule.cubic_weight)
    finder = PassFinder()

    def reduce(q: np.ndarray, y: np.ndarray, t: np.ndarray) -> None:
        nonlocal split_ns
        if excl and t0_excl is not None:
            keep = ~excluded_mask(t, excl, t0_excl)
            q, y, t = q[keep], y[keep], t[keep]
        if terms_acc is not None:
            terms_acc.add(q, y, t)  # its own rotation sums included
        elif streamed:
            cut = min(max(source.n_mag // 2 - kept.n_aligned, 0), len(t))
            if 0 < cut < len(t) or (cut == 0 and split_ns is None and len(t)):
                split_ns = int(t[cut])
            if cut:
                halves[0].add(q[:cut], y[:cut], t[:cut])
            if cut < len(t):
                halves[1].add(q[cut:], y[cut:], t[cut:])
        kept.aligned(q, y, t)

    for ch in itertools.chain([first], chunks):
        kept.chunk(ch)
        finder.add(ch.mag.t_ns, ch.mag.values)
        if excl and kept.t_first_ns is not None:
            if t0_excl is None:  # the first range's first stamp: the recording's
                t0_excl = int(kept.t_first_ns)
            n_excl += int(np.count_nonzero(excluded_mask(ch.mag.t_ns, excl, t0_excl)))
        att = ch.attitude
        for q, y, t in _settled(aligner.add(ch.mag.t_ns, ch.mag.values,
                                            None if att is None else att.t_ns,
                                            None if att is None else att.q_enu_body)):
            reduce(q, y, t)
    for q, y, t in _settled(aligner.finish()):
        reduce(q, y, t)
    t0 = int(kept.t_first_ns if kept.t_first_ns is not None else source.start_ns)
    sums = None
    if terms_acc is not None:
        sums = SampleSums(terms=terms_acc.result())
    elif streamed:
        split_s = 0.0 if split_ns is None else (split_ns - t0) * 1e-9
        sums = SampleSums(halves=(halves[0].result(), halves[1].result()), split_s=split_s)
    passes = finder.windows(kept.windows)
    if len(passes):
        # the candidates are known once every sample was judged: their samples are read again
        more = _Kept(passes, plan.keep_every)
        for ch in source.again():
            more.chunk(ch)
        kept.add_windows(more)
    return Reduced(FirstPass(rule.max_gap_s, n_excl),
                   t0, rule, kept.windows, len(passes), kept.window_recording(source.header),
                   kept.aligned_series(), kept.thin_positions(source.header), sums)


# --------------------------------------------------------------------------- analysis
@dataclasses.dataclass(frozen=True)
class Analysed:
    """The analysis of a recording: its context, and what the second pass needs.

    Attributes
    ----------
    ctx : Context
        ``calibration``, ``diagnosis``; ``recording``: what the analysis saw.
    plan : Plan
    source : Source
    segments : tuple of Segment or None
        The segments of the whole recording.
    reduced : Reduced or None
        A long recording's first pass.

    """

    ctx: Context
    plan: Plan
    source: Source
    segments: tuple[Segment, ...] | None
    reduced: Reduced | None


def _prepared(source: Source, options: ProcessOptions, steps: Steps) -> tuple[Source, Plan]:
    """Return the plan of ``source``, a recording in memory prepared (a turntable's attitude)."""
    if isinstance(source, FileSource):
        return source, make_plan(options, source.n_mag)
    rec = source.recording
    plan = make_plan(options, source.n_mag, rec)
    if plan.prepare:
        ctx = Context(source=rec.path, recording=rec)
        rec = steps.pipeline(Pipeline(list(plan.prepare), initial=ctx.provided()), ctx
                             ).need_recording()
    return MemorySource(rec, plan.chunk_samples), plan


def analyse_source(source: Source, options: ProcessOptions, steps: Steps) -> Analysed:
    """Run the first pass (a long recording) and the analysis stages on ``source``."""
    source, plan = _prepared(source, options, steps)
    steps.expect(plan.step_names())
    if not plan.windowed:
        assert isinstance(source, MemorySource)
        rec = source.recording
        ctx = Context(source=rec.path, recording=rec)
        pipe = Pipeline(plan.analysis_stages(), initial=ctx.provided())
        ctx = steps.pipeline(pipe, ctx)
        return Analysed(ctx, plan, source, ctx.segments, None)
    reduced = first_pass(source, plan)
    release_free_memory()
    seg_ctx = Context(aligned=reduced.thin_aligned)
    segments = steps.pipeline(Pipeline(plan.segmentation(), initial=seg_ctx.provided()),
                              seg_ctx).segments
    # the analysis sees the segments its windows overlap (thousands on a 10-hour recording
    # otherwise, each a mask over the window samples)
    w = reduced.windows_ns
    win_segments = None if segments is None else tuple(
        sg for sg in segments
        if bool(np.any((sg.start_ns < w[:, 1]) & (sg.end_ns > w[:, 0]))))
    ctx = Context(source=source.header.path, recording=reduced.recording,
                  segments=win_segments, sums=reduced.sums)
    pipe = Pipeline(plan.analysis_stages(reduced.first), initial=ctx.provided())
    ctx = steps.pipeline(pipe, ctx)
    cal = ctx.need_calibration()
    n_win = len(ctx.need_recording().mag)
    if options.calibration_path is None and n_win < source.n_mag:
        k = reduced.n_pass_windows
        spread = w[np.argsort(w[:, 1] - w[:, 0])[k:]] if k else w
        where = (f"{len(spread)} windows of {(spread[0, 1] - spread[0, 0]) * 1e-9:.0f} s spread "
                 "over the recording"
                 + (f" and {k} of at most {PASS_WINDOW_S:.0f} s where the field's magnitude "
                    "stood out" if k else "")
                 + f" ({n_win} of {source.n_mag} magnetometer samples)")
        if ctx.sums is None:
            fitted = f"the model was fitted on {where}"
        elif options.diagnose:
            fitted = ("the rotation and the terms asked for were estimated from every sample, "
                      f"then the diagnosis fitted the final model on {where}")
        else:
            fitted = "the model was estimated from every sample"
        note = (f"long recording processed in chunks: {fitted}; restored, measured and "
                "written: every sample")
        # the report says how many samples the analysis saw and why the fit used fewer
        seen = {"n": int(n_win), "of": int(source.n_mag), "windows": int(len(w))}
        ctx = ctx.replace(calibration=cal.replace(
            warnings=cal.warnings + (note,), checks={**cal.checks, "analysed_samples": seen}))
    return Analysed(ctx, plan, source, segments, reduced)


def analyse(recording: Recording, options: ProcessOptions | None = None) -> Context:
    """Analyse a recording held in memory (any span of one); return the final context."""
    return analyse_source(MemorySource(recording), options or ProcessOptions(), Steps()).ctx


def analyse_recording(path: str | Path, options: ProcessOptions | None = None) -> Context:
    """Read one recording and analyse it (the ``calibrate`` and ``diagnose`` commands).

    Each step is announced on the progress sink as it starts; what the reader repaired is
    warned (``RecoveredDataWarning``).
    """
    options = options or ProcessOptions()
    steps = Steps(expected_steps(options))
    steps.start("Ingest")
    source = open_source(path, options, warn=True)
    analysis = analyse_source(source, options, steps)
    steps.start(None)
    return analysis.ctx


# ------------------------------------------------------------------------- second pass
@dataclasses.dataclass(frozen=True)
class Processed:
    """What ``process`` made of one recording (the summary row's source).

    Attributes
    ----------
    recording : Recording
        As the outputs show it (:class:`stages.sinks.RunEnd`).
    calibration : Calibration
    diagnosis : Diagnosis or None
    metrics : MetricsResult
    outputs : tuple of (name, path)
    problems : tuple of Problem
        What the reader repaired.

    """

    recording: Recording
    calibration: Calibration
    diagnosis: Any
    metrics: Any
    outputs: tuple[tuple[str, str], ...]
    problems: tuple[Problem, ...]


def process(source: Source, rec_dir: Path, options: ProcessOptions, steps: Steps) -> Processed:
    """Analyse ``source`` and restore every sample into the outputs (docs/modules.md)."""
    # rerun's SDK, matplotlib and the grid's libraries (slow to import) imported on the other
    # core while the first pass and the analysis run
    warm = []
    if options.write_rerun:
        os.environ.setdefault("RUST_LOG", "off")  # as stages.write_rerun sets it
        warm.append("rerun")
    if options.write_report:
        warm.append("pipeline.core.style:pyplot")
    if getattr(source.header, "position", None) is not None:
        # the anomaly grid's libraries and the kernels numba compiles in every process
        warm.append("stages.write_survey:compile_grid")
    warm_in_background(*warm)
    if isinstance(source, FileSource):
        source.spill_to(rec_dir)
    return restore_into_sinks(analyse_source(source, options, steps), rec_dir, steps)


def restore_into_sinks(analysis: Analysed, rec_dir: Path, steps: Steps) -> Processed:
    """Restore every sample of an analysed recording into its plan's sinks (second pass)."""
    source, plan, reduced = analysis.source, analysis.plan, analysis.reduced
    options = plan.options
    ctx = analysis.ctx
    cal = ctx.need_calibration()
    header = source.header
    if reduced is not None:
        rule, t0 = reduced.rule, reduced.t0_ns
    else:
        assert isinstance(source, MemorySource)
        att = source.recording.attitude
        if att is None or not len(att):
            raise InputError("the recording has no attitude to restore the magnetometer with",
                             path=header.path)
        rule, t0 = AttitudeRule.of(att, options.max_gap_s), source.start_ns
    steps.start("Restore")
    release_free_memory()
    sinks = plan.sinks(rec_dir)
    steps.expect([s.name for s in sinks])
    restorer = ChunkedRestore(cal, t0_ns=t0, max_gap_s=rule.max_gap_s,
                              cubic_weight=rule.cubic_weight, step_s=rule.step_s,
                              model_key=model_key_of(cal, options.max_gap_s),
                              positions=header.position is not None)
    start = RunStart(header, cal, analysis.segments, t0, source.passthrough())
    k = plan.keep_every
    kept: list[RestoreResult] = []
    totals = RestoreTotals()
    # the final model's residual per chunk: where the samples the analysis did not see
    # disagree with it (:func:`unseen_check`)
    per_chunk: list[tuple[int, int, RestoreTotals]] = []
    n_seen = 0
    opened: list[Sink] = []
    # Each chunk's outputs are written on a helper thread while the next chunk is restored
    # (numpy, zstd and rerun release the interpreter lock), one at a time and in order; the
    # helper first opens the sinks (rerun builds its blueprint's store meanwhile).
    with ThreadPoolExecutor(max_workers=1) as pool:
        try:
            def open_all() -> None:
                for s in sinks:
                    s.open(start)
                    opened.append(s)

            def consume(rs: RestoreResult | None) -> None:
                nonlocal totals, n_seen
                if rs is None or not len(rs.t_ns):
                    return
                part = RestoreTotals.of(rs)
                per_chunk.append((int(rs.t_ns[0]), int(rs.t_ns[-1]), part))
                totals = totals + part
                for s in sinks:
                    s.add(rs)
                kept.append(rs if k == 1 else rs.rows(slice((-n_seen) % k, None, k)))
                n_seen += len(rs.t_ns)

            pending: Future[None] = pool.submit(open_all)
            chunks = source.replay() if reduced is not None else source.chunks()
            for chunk, last in _chunks_with_last(chunks):
                att = chunk.attitude
                rs = restorer.add(chunk.mag.t_ns, chunk.mag.values,
                                  None if att is None else att.t_ns,
                                  None if att is None else att.q_enu_body,
                                  chunk.position, last=last)
                pending.result()
                pending = pool.submit(consume, rs)
            rs = restorer.finish()
            pending.result()
            consume(rs)
            if not kept:
                raise InputError("no magnetometer sample of the recording could be restored",
                                 path=header.path, hint="check that the magnetometer and "
                                 "attitude overlap in time")
            sample = kept[0] if len(kept) == 1 else RestoreResult.concat(kept)
            if options.calibration_path is not None:
                res_all = totals.residual_rms_nT
                cal = cal.replace(residual_rms_nT=res_all, verdict=applied_verdict(cal, res_all))
            if reduced is not None:
                ref_rms = analysed_rms(ctx)
                unseen = None if ref_rms is None else unseen_check(per_chunk, totals, ref_rms,
                                                                    t0)
                if unseen is not None:
                    cal = cal.replace(warnings=cal.warnings + (unseen,))
            positions = (reduced.thin_positions if reduced is not None else header.position)
            shown = dataclasses.replace(
                header, mag=VectorSeries(sample.t_ns, sample.raw_mag_nT, header.mag.frame,
                                         header.mag.unit),
                attitude=None, position=positions)
            end = RunEnd(shown, cal, ctx.diagnosis, analysis.segments, sample, totals)
            prepared = [pool.submit(s.prepare, end) for s in sinks]
            outputs: tuple[tuple[str, str], ...] = ()
            for s, p in zip(sinks, prepared, strict=True):
                steps.start(s.name)
                p.result()
                outputs += s.close(end)
                opened.remove(s)
                if isinstance(s, MetricsSink):
                    end = dataclasses.replace(end, metrics=s.result)
        except BaseException as exc:
            # each output drops its temporary file; what it makes of the error (a full disk:
            # an OutputError naming the folder) is what the user hears
            said: MagalignError | None = None
            for s in opened:
                try:
                    s.discard(exc)
                except MagalignError as err:
                    said = said or err
            if said is not None and said is not exc:
                raise said from exc
            raise
    return Processed(shown, cal, ctx.diagnosis, end.metrics, outputs, header.problems)


def _chunks_with_last(chunks: Iterator[RecordingChunk]
                      ) -> Iterator[tuple[RecordingChunk, bool]]:
    """Each chunk, and whether it is the last."""
    prev = next(chunks, None)
    for ch in chunks:
        assert prev is not None
        yield prev, False
        prev = ch
    if prev is not None:
        yield prev, True


def analysed_rms(ctx: Context) -> float | None:
    """Return the final model's residual RMS (nT) on the samples the analysis saw, or None."""
    d = ctx.diagnosis
    if d is not None:
        v = (d.final or {}).get("residual_rms_nT")
        if v is not None and np.isfinite(v):
            return float(v)
    cal = ctx.calibration
    if cal is not None and np.isfinite(cal.residual_rms_nT) and cal.residual_rms_nT > 0:
        return float(cal.residual_rms_nT)
    return None


def unseen_check(per_chunk: list[tuple[int, int, RestoreTotals]], totals: RestoreTotals,
                 analysed_rms_nT: float, t0_ns: int) -> str | None:
    """Return a warning when every sample fits the final model worse than the analysed ones.

    The analysis of a long recording sees windows of it; the second pass restores every
    sample with the final model. When the residual RMS over every sample exceeds the
    analysed samples' by more than :data:`UNSEEN_RMS_RATIO`, something between the windows
    (a disturbance, a step, a change of the platform) was left out of the model: the
    warning says so and names the stretch (a chunk of the recording) where the residual is
    largest.

    Parameters
    ----------
    per_chunk : list of (first stamp ns, last stamp ns, RestoreTotals)
        The restored chunks in order.
    totals : RestoreTotals
        Over every sample.
    analysed_rms_nT : float
        The final model's residual RMS on the analysed samples (per component, nT).
    t0_ns : int
        First magnetometer stamp.

    """
    rms = totals.residual_rms_nT
    if not np.isfinite(rms) or rms <= UNSEEN_RMS_RATIO * analysed_rms_nT:
        return None
    worst = max(per_chunk, key=lambda c: c[2].residual_rms_nT if c[2].n_valid else -1.0)
    a, b = (worst[0] - t0_ns) * 1e-9, (worst[1] - t0_ns) * 1e-9
    return (f"the final model leaves {rms:.3g} nT rms over every sample against "
            f"{analysed_rms_nT:.3g} nT on the samples it was fitted and diagnosed on: the "
            "recording holds physics between the analysed windows that the model lacks "
            f"(largest: {worst[2].residual_rms_nT:.3g} nT rms from {a:.0f} s to {b:.0f} s); "
            "look at the residual there, or process that stretch on its own")


# --------------------------------------------------------------------------- one file
def _finite_list(a: Any) -> list | None:
    if a is None:
        return None
    return [None if not np.isfinite(x) else float(x) for x in np.asarray(a, dtype=float).ravel()]


def summary_row(done: Processed, stem: str, out_dir: Path) -> dict[str, Any]:
    """One summary row of a processed recording (plain JSON values)."""
    cal = done.calibration
    rec = done.recording
    m = done.metrics
    findings: list[str] = []
    if done.diagnosis is not None:
        findings = [f.get("effect") for f in done.diagnosis.to_dict().get("findings", [])]
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
        "verdict_line": verdict_line(cal),
        "findings": findings,
        "out_dir": str(out_dir),
        "paths": dict(done.outputs),
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
        ``findings`` (effect names), ``paths`` (output name -> path), ``timings_s`` (step
        name -> wall seconds), ``run_warnings`` (``[category, message]`` pairs: every warning
        raised while processing, and every problem the reader repaired; they are collected
        here, not shown, so that the caller can issue them where the user sees them) and
        more.

    Raises
    ------
    MagalignError
        Bad input, estimation failure, unwritable output.

    """
    options = options or ProcessOptions()
    path = Path(path)
    stem = path.stem
    rec_dir = safe_join(out_dir, stem)
    rec_dir.mkdir(parents=True, exist_ok=True)
    steps = Steps(expected_steps(options, rec_dir))
    # Warnings are collected, not shown: this runs in a worker process whose stderr is not
    # the user's terminal (and has Python's two-line warning format); the command that
    # started the worker issues them once from the row (pipeline.app.commands.process).
    with warnings.catch_warnings(record=True) as caught, \
            progress.use_sink(progress.current() or progress.sink_from_env(stem)):
        try:
            steps.start("Ingest")
            source = open_source(path, options)
            done = process(source, rec_dir, options, steps)
            steps.start(None)
        except MagalignError as exc:
            # the warnings stay here: what damage the reader met goes into the one line
            note = damage_behind(caught, exc.path or str(path))
            if note:
                exc.naming(str(path))
                exc.message += note
                exc.args = (exc.one_line(),)
            raise
    row = summary_row(done, stem, rec_dir)
    row["timings_s"] = {k: round(v, 3) for k, v in steps.timings.items()}
    row["run_warnings"] = run_warnings(str(path), caught, done.problems)
    return row


def run_warnings(path: str, caught: list[warnings.WarningMessage],
                 problems: tuple[Problem, ...]) -> list[list[str]]:
    """Return the warnings of one run as ``[category name, message]`` pairs, each once.

    Parameters
    ----------
    path : str
        The recording.
    caught : list of warnings.WarningMessage
        What was warned while it was processed (the reader warns the damage it found in
        the file).
    problems : tuple of Problem
        ``Recording.problems``: also what the reader repaired in the data without warning
        (dropped NaN samples, sorted stamps, ...), which the user must hear too.

    Returns
    -------
    list of [str, str]
        JSON-able, in the order they arose; the problems as ``RecoveredDataWarning``.

    """
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

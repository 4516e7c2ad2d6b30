"""``process`` of a long recording in memory that does not grow with its length.

A recording with more magnetometer samples than ``ProcessOptions.scale_samples`` whose file
is an intact indexed MCAP is processed in two passes over its samples, never holding them
whole (the file is decoded once; its samples are spilled to an anonymous file beside the
outputs, 72 bytes a sample pair, and replayed by pass 2):

1. **Read** (range by range, :func:`pipeline.io.mcap_read.iter_recording_chunks`): every
   sample, brought onto the magnetometer stamps, is reduced to the streaming estimator's
   sums (:mod:`stages.estimators.streaming`: the ML rotation, and offset, from every
   sample); every k-th aligned sample is kept for the segmentation (at most
   :data:`DECIMATED_SAMPLES`); and :data:`DIAGNOSIS_WINDOWS` windows spread evenly over the
   recording are kept whole, at the full rate of both sensors (about
   :data:`DECIMATED_SAMPLES` magnetometer samples in all), for the estimators that need
   the samples themselves and for the diagnosis: its effects (a time offset, eddy
   currents, a sample-and-hold, the attitude's interpolation error) live at the sensors'
   own rates, which a decimated series would hide, and windows spread over the whole
   recording keep its slow terms (drifts) interpolated, never extrapolated.
2. **Analyse**: segmentation, estimation, diagnosis and the verdict, as in memory, on
   those samples.
3. **Restore and write** (the spilled ranges again): :class:`stages.restore.ChunkedRestore`
   restores every sample with the final model (the same attitude as a whole-recording
   interpolator, with the blend weight and gap rule of the recording's first range); each
   range goes to the metrics (:class:`stages.metrics.MetricsAccumulator`), the corrected
   MCAP (:class:`stages.write_mcap.CorrectedMcapStream`, the input's chunks copied as they
   are) and the rerun recording (:class:`stages.write_rerun.RrdStream`), and every k-th
   row is kept for the report's figures and the rerun 3D views. Counts, the residual RMS
   and every metric are over every sample. The final model's residual over every sample is
   compared with its residual on the analysed windows (:func:`unseen_check`): physics
   between the windows that the model lacks is reported, with the stretch where it is.

Positions (a ``NavSatFix`` channel, or those the attitude carries) go with the samples: the
diagnosis windows keep theirs, so the spatial terms of the field (``field_gradient``,
``local_source``, ``field_map``) are fitted there, and pass 2 restores each row with the
position interpolated as over the whole series (:class:`stages.restore.ChunkedPositions`).

What is not streamed (such recordings take the in-memory path, whatever their length): a
damaged or unindexed file (the reader must recover what it can from the whole file) and a
turntable recording (the axis-tilt fit needs the whole rotation). Ingest's whole-recording
checks (duplicated stamps, clock jumps, gaps) are made range by range here, so a stamp
repeated across two ranges is not reported.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.errors import InputError, OutputError
from pipeline.core.memory import release_free_memory
from pipeline.core.recording import (
    AlignedSeries,
    AttitudeSeries,
    Context,
    PositionSeries,
    Recording,
    VectorSeries,
)
from pipeline.core.warm import warm_in_background

#: analysis stages see at most this many magnetometer samples (segmentation: every k-th;
#: diagnosis: this many in whole windows)
DECIMATED_SAMPLES = 150_000
#: windows of full-rate data the diagnosis sees, spread evenly over the recording
DIAGNOSIS_WINDOWS = 12
#: messages per range read from the file (memory: about 100 bytes a message)
RANGE_MESSAGES = 200_000
#: attitude kept beyond each diagnosis window (s): its interpolation at the window's edges
WINDOW_MARGIN_S = 1.0


@dataclasses.dataclass(frozen=True)
class StreamPlan:
    """Why and how a recording is processed in chunks (:func:`plan_stream`)."""

    header: Recording
    passthrough: Any  # pipeline.io.mcap_read.PassThrough: the input's chunks, for pass 2
    n_mag: int
    start_ns: int
    end_ns: int


def plan_stream(path: str | Path, options: Any) -> StreamPlan | None:
    """Return the plan for processing ``path`` in chunks, or None for the in-memory path.

    Chunks when the options allow it (``scale_samples``), the file holds more magnetometer
    messages than ``scale_samples``, is intact and indexed (its chunks can be copied as they
    are), and its attitude source is not a turntable.
    """
    from pipeline.io.mcap_header import read_recording_header
    from pipeline.io.mcap_read import pass_through

    if options.scale_samples is None or options.turntable_topic is not None:
        return None
    header = read_recording_header(path, mag_topic=options.mag_topic,
                                   attitude_topic=options.attitude_topic)
    mag = next((c for c in header.channels if c.topic == header.mag_topic), None)
    if mag is None or mag.count <= options.scale_samples or header.attitude is None:
        return None
    pt = pass_through(path)
    if pt is None or not pt.chunks:
        return None
    return StreamPlan(header, pt, int(mag.count), min(c.start_ns for c in pt.chunks),
                      max(c.end_ns for c in pt.chunks))


def windows_ns(plan: StreamPlan) -> np.ndarray:
    """Return the diagnosis windows, (W, 2) int64 ns, half-open, spread over the recording."""
    span = plan.end_ns - plan.start_ns
    share = min(1.0, DECIMATED_SAMPLES / max(plan.n_mag, 1))
    length = span * share / DIAGNOSIS_WINDOWS
    centres = plan.start_ns + (np.arange(DIAGNOSIS_WINDOWS) + 0.5) * span / DIAGNOSIS_WINDOWS
    lo = np.floor(centres - length / 2).astype(np.int64)
    return np.stack([lo, lo + int(np.ceil(length))], axis=1)


class _Collector:
    """The samples of pass 1 kept for the analysis (windows; every k-th aligned row)."""

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

    def chunk(self, ch: Any) -> None:
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
            attitude=AttitudeSeries(at[oa], aq[oa]), position=position)


@dataclasses.dataclass
class _Counted:
    """The recording's first magnetometer stamp and the samples ``--exclude`` leaves out."""

    t0: int | None = None
    n: int = 0


class _Replay:
    """The decoded samples of pass 1, spilled to an anonymous file for pass 2.

    Reading them back is a copy of 72 bytes a sample pair; decoding the MCAP again (CDR,
    zstd) costs ten times more. The file (next to the outputs) goes away with the object.
    """

    def __init__(self, folder: Path) -> None:
        import tempfile

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

    def write(self, ch: Any) -> None:
        att, pos = ch.attitude, ch.position
        m = 0 if att is None else len(att.t_ns)
        k = 0 if pos is None else len(pos.t_ns)
        try:
            np.array([len(ch.mag.t_ns), m, k], dtype=np.int64).tofile(self._fh)
            for a, dt in ((ch.mag.t_ns, np.int64), (ch.mag.values, np.float64)):
                np.ascontiguousarray(a, dtype=dt).tofile(self._fh)
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

    def chunks(self) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray | None,
                                       np.ndarray | None, PositionSeries | None]]:
        """Yield ``(mag_t_ns, mag_nT, att_t_ns, q_enu_body, position)`` of each chunk."""
        fh = self._fh
        fh.flush()
        fh.seek(0)
        for _ in range(self.n_chunks):
            n, m, k = (int(x) for x in np.fromfile(fh, np.int64, 3))
            mt = np.fromfile(fh, np.int64, n)
            mv = np.fromfile(fh, np.float64, 3 * n).reshape(n, 3)
            at = aq = None
            if m:
                at = np.fromfile(fh, np.int64, m)
                aq = np.fromfile(fh, np.float64, 4 * m).reshape(m, 4)
            pos = None
            if k:
                pt = np.fromfile(fh, np.int64, k)
                pp = np.fromfile(fh, np.float64, 3 * k).reshape(k, 3)
                assert self.position is not None  # set with the first positions written
                pos = dataclasses.replace(self.position, t_ns=pt, p_m=pp)
            yield mt, mv, at, aq, pos
        fh.close()


def _chunks(path: str | Path, options: Any) -> Iterator[Any]:
    from pipeline.io.mcap_read import iter_recording_chunks

    return iter_recording_chunks(path, max_messages=RANGE_MESSAGES, mag_topic=options.mag_topic,
                                 attitude_topic=options.attitude_topic)


def process_stream(plan: StreamPlan, path: str | Path, rec_dir: Path, options: Any,
                   tick: Callable[..., None], shown: list[str]) -> Context:
    """Run the pipeline on a long recording in two passes (module docstring).

    Parameters
    ----------
    plan : StreamPlan
        From :func:`plan_stream`.
    path : path
        The recording (never modified).
    rec_dir : Path
        Output folder of this recording.
    options : ProcessOptions
        What to do (as for the in-memory path).
    tick : callable
        ``tick(stage name, index, total)`` at the start of each step (progress and timings).
    shown : list of str
        Filled with the step names (the progress line's stages).

    Returns
    -------
    Context
        ``calibration``, ``diagnosis``, ``segments``, ``metrics``, ``outputs``; ``restored``
        holds every k-th restored row with the counts and residual RMS of every sample
        (``RestoreResult.totals``); ``recording`` is the header with those rows' readings.

    """
    from pipeline.model.attitude import auto_max_gap_s, estimate_cubic_weight
    from stages.estimators.streaming import StreamAccumulator, fit_stats, iter_aligned_chunks
    from stages.metrics import MetricsAccumulator
    from stages.restore import ChunkedRestore, RestoreResult, RestoreTotals, model_key_of
    from stages.write_mcap import CorrectedMcapStream, corrected_path
    from stages.write_results import WriteResults

    steps = ["Ingest", "SegmentMotion", "Estimate", "Diagnose", "Judge",
             "Restore+outputs", "WriteResults", "Report"]
    if not options.diagnose or options.calibration_path is not None:
        steps.remove("Diagnose")
    if options.calibration_path is not None:
        steps.remove("Judge")
    if not options.write_report:
        steps.remove("Report")
    shown[:] = steps

    def step(name: str) -> None:
        # process_one's tick counts the stages after Ingest from 0 (they follow it)
        i = steps.index(name)
        tick(name, i if i == 0 else i - 1, len(steps))

    # rerun's SDK (about a second) and matplotlib (about half a second) imported on the
    # other core during pass 1, which waits on reading more than on computing
    warm = []
    if options.write_rerun:
        os.environ.setdefault("RUST_LOG", "off")  # as stages.write_rerun sets it
        warm.append("rerun")
    if options.write_report:
        warm += ["pipeline.core.style:pyplot", "stages.report"]
    warm_in_background(*warm)

    # ---------------------------------------------------------------- pass 1: read
    step("Ingest")
    release_free_memory()  # what scanning the file's indexes freed
    k = max(1, -(-plan.n_mag // DECIMATED_SAMPLES))
    col = _Collector(windows_ns(plan), k)
    chunks = _chunks(path, options)
    first = next(chunks)
    att0 = first.attitude if first.attitude is not None else plan.header.attitude
    assert att0 is not None  # plan_stream took only recordings with an attitude
    gap_s = (float(options.max_gap_s) if options.max_gap_s is not None
             else auto_max_gap_s(att0.t_ns))
    lam = estimate_cubic_weight(att0.t_ns, att0.q_enu_body)  # (A7) of the first range
    # the attitude's spacing, s: the first range's stands for the recording's
    att_dt = np.diff(np.unique(att0.t_ns))
    att_step_s = float(np.median(att_dt)) * 1e-9 if len(att_dt) else 0.01

    replay = _Replay(rec_dir)

    excl = tuple(options.exclude)
    counted = _Counted()  # --exclude: the recording's first stamp, samples left out

    def tapped() -> Iterator[Any]:
        for ch in itertools.chain([first], chunks):
            col.chunk(ch)
            replay.write(ch)
            if excl and col.t_first_ns is not None:
                from stages.exclude import excluded_mask

                if counted.t0 is None:  # the first range's first stamp: the recording's
                    counted.t0 = int(col.t_first_ns)
                counted.n += int(np.count_nonzero(excluded_mask(ch.mag.t_ns, excl, counted.t0)))
            yield ch

    # the sums of each half of the recording (split-half check of the sigmas) add up to
    # the whole's
    # rotation only: each half's sums per time block (block sandwich); the whole's are theirs
    halves = [StreamAccumulator(max_gap_s=gap_s, with_tau=False) for _ in range(2)]
    split_ns: int | None = None
    from pipeline.app.process_one import diagnose_kwargs, estimate_kwargs, streams_estimate
    from stages.estimate import Term

    terms = {Term(t) for t in options.terms}
    streamed = options.calibration_path is None and streams_estimate(options)
    # soft iron and time offset: the expanded sums of every sample (one pass, fixed size)
    terms_acc = (StreamAccumulator(max_gap_s=gap_s) if streamed and terms - {Term.OFFSET}
                 else None)
    for q, y, t in iter_aligned_chunks(tapped(), max_gap_s=gap_s, cubic_weight=lam):
        if excl and counted.t0 is not None:
            from stages.exclude import excluded_mask

            keep = ~excluded_mask(t, excl, counted.t0)
            q, y, t = q[keep], y[keep], t[keep]
        if terms_acc is not None:
            terms_acc.add(q, y, t)  # its own rotation sums included
        else:
            cut = min(max(plan.n_mag // 2 - col.n_aligned, 0), len(t))
            if 0 < cut < len(t) or (cut == 0 and split_ns is None and len(t)):
                split_ns = int(t[cut])
            if cut:
                halves[0].add(q[:cut], y[:cut], t[:cut])
            if cut < len(t):
                halves[1].add(q[cut:], y[cut:], t[cut:])
        col.aligned(q, y, t)
    win = Context(source=str(path), recording=col.window_recording(plan.header),
                  options=options)

    # ---------------------------------------------------------------- analyse
    release_free_memory()
    step("SegmentMotion")
    segments = None
    try:
        from stages.segment import SegmentMotion
    except ModuleNotFoundError:  # pragma: no cover - the stage is part of the project
        SegmentMotion = None  # type: ignore[assignment,misc]  # noqa: N806
    if SegmentMotion is not None:
        segments = SegmentMotion().run(Context(aligned=col.aligned_series())).segments
    step("Estimate")
    from stages.resample import Resample

    # the analysis sees the segments its windows overlap (thousands on a 10-hour recording
    # otherwise, each a mask over the window samples)
    w_ns = col.windows
    win_segments = None if segments is None else tuple(
        sg for sg in segments
        if bool(np.any((sg.start_ns < w_ns[:, 1]) & (sg.end_ns > w_ns[:, 0]))))
    win = Resample(max_gap_s=gap_s).run(win).replace(segments=win_segments)
    if excl:
        from stages.exclude import Exclude

        win = Exclude(excl, t0_ns=counted.t0).run(win)
    if options.calibration_path is not None:
        from stages.check_applied import CheckApplied, calibration_source
        from stages.load_calibration import LoadCalibration

        win = LoadCalibration(str(options.calibration_path)).run(win)
        # the line's noise and rotation from the windows; its verdict from every sample's
        # residual after pass 2
        win = CheckApplied(calibration_source(options.calibration_path),
                           max_gap_s=options.max_gap_s).run(win)
    else:
        from stages.estimate import Estimate
        from stages.require_observable import RequireObservable

        ref = options.reference_field_enu_nT
        kw_fit: dict[str, Any] = {
            "estimate_offset": Term.OFFSET in terms,
            "reference_field_enu_nT": None if ref is None else np.asarray(ref, float),
            "block_sandwich": True}
        if streamed and terms_acc is None:
            # every sample, from the sums of pass 1; checked by its halves
            half_stats = [h.result() for h in halves]
            cal0 = fit_stats(half_stats[0] + half_stats[1], **kw_fit).to_calibration()
            split_s = 0.0 if split_ns is None else (split_ns - (col.t_first_ns or 0)) * 1e-9
            win = win.replace(calibration=split_halves(cal0, half_stats, kw_fit, split_s))
        elif terms_acc is not None:
            # soft iron and time offset from every sample too (its sigmas: the block
            # sandwich of the expanded sums)
            fit = fit_stats(terms_acc.result(), estimate_soft_iron=Term.SOFT_IRON in terms,
                            estimate_time_offset=Term.TIME_OFFSET in terms, **kw_fit)
            win = win.replace(calibration=fit.to_calibration())
        else:
            win = Estimate(**estimate_kwargs(options)).run(win)
        win = RequireObservable().run(win)
        if options.diagnose:
            step("Diagnose")
            from stages.diagnose.stage import Diagnose

            win = Diagnose(**diagnose_kwargs(options)).run(win)
        step("Judge")
        from stages.estimate import Judge

        win = Judge().run(win)
    cal = win.need_calibration()
    if excl:
        from stages.exclude import noted

        cal = noted(cal, excl, counted.t0 if counted.t0 is not None else plan.start_ns,
                    counted.n)
    n_win = len(win.need_recording().mag)
    if options.calibration_path is None and n_win < plan.n_mag:
        w = col.windows
        where = (f"{len(w)} windows of {(w[0, 1] - w[0, 0]) * 1e-9:.0f} s spread over the "
                 f"recording ({n_win} of {plan.n_mag} magnetometer samples)")
        if not streamed:
            fitted = f"the model was fitted on {where}"
        elif options.diagnose:
            fitted = ("the rotation and the terms asked for were estimated from every sample, "
                      f"then the diagnosis fitted the final model on {where}")
        else:
            fitted = "the model was estimated from every sample"
        note = (f"long recording processed in chunks: {fitted}; restored, measured and "
                "written: every sample")
        cal = cal.replace(warnings=cal.warnings + (note,))

    # ---------------------------------------------------------------- pass 2: restore, write
    step("Restore+outputs")
    release_free_memory()
    t0 = int(col.t_first_ns if col.t_first_ns is not None else plan.start_ns)
    restorer = ChunkedRestore(cal, t0_ns=t0, max_gap_s=gap_s, cubic_weight=lam,
                              step_s=att_step_s,
                              model_key=model_key_of(cal, options.max_gap_s),
                              positions=plan.header.position is not None)
    acc = MetricsAccumulator(segments, t0, spill_dir=rec_dir)
    totals = RestoreTotals()
    kept: list[Any] = []
    n_seen = 0
    outputs: tuple[tuple[str, str], ...] = ()
    mcap_dest = corrected_path(rec_dir, path)
    from concurrent.futures import Future, ThreadPoolExecutor
    from contextlib import ExitStack

    # Each range's outputs are written on a helper thread while the next range is restored
    # (numpy, zstd and rerun release the interpreter lock): one at a time, in order (2 h:
    # about 0.4 s of 10.6 on a quiet machine). The helper also opens the rerun recording
    # first (rerun builds the blueprint's store: about 0.3 s) while the first range is
    # restored. The exit stack closes the outputs after the helper is done.
    with ExitStack() as stack, ThreadPoolExecutor(max_workers=1) as pool:
        mc = stack.enter_context(CorrectedMcapStream(plan.header, cal, mcap_dest,
                                                     plan.passthrough))
        rrd = None
        pending: Future[Any] | None = None
        if options.write_rerun:
            from stages.write_rerun import RrdStream, rrd_path

            rrd_dest = rrd_path(rec_dir, path)
            rrd = RrdStream(plan.header, cal, rrd_dest)
            # opened by the helper before it takes any range (one worker, tasks in order)
            pending = pool.submit(stack.enter_context, rrd)

        # the final model's residual per chunk: where the samples the analysis did not see
        # disagree with it (:func:`unseen_check`)
        per_chunk: list[tuple[int, int, Any]] = []

        def consume(rs: Any) -> None:
            nonlocal totals, n_seen
            if rs is None or not len(rs.t_ns):
                return
            part = RestoreTotals.of(rs)
            per_chunk.append((int(rs.t_ns[0]), int(rs.t_ns[-1]), part))
            totals = totals + part
            acc.add(rs)
            mc.add(rs)
            if rrd is not None:
                rrd.add(rs)
            kept.append(rs.rows(slice((-n_seen) % k, None, k)))
            n_seen += len(rs.t_ns)

        for mt, mv, at, aq, pos in replay.chunks():
            rs = restorer.add(mt, mv, at, aq, pos)
            if pending is not None:
                pending.result()
            pending = pool.submit(consume, rs)
        rs = restorer.finish()
        if pending is not None:
            pending.result()
        consume(rs)
        if not kept:
            raise InputError("no magnetometer sample of the recording could be restored",
                             path=str(path), hint="check that the magnetometer and attitude "
                             "overlap in time")
        sample = RestoreResult.concat(kept, totals)
        if options.calibration_path is not None:
            from stages.check_applied import applied_verdict

            res_all = totals.residual_rms_nT
            cal = cal.replace(residual_rms_nT=res_all, verdict=applied_verdict(cal, res_all))
            mc.cal_text = cal.to_json()  # the corrected MCAP carries the same calibration
        ref_rms = _analysed_rms(win)
        if ref_rms is not None:
            unseen = unseen_check(per_chunk, totals, ref_rms, t0)
            if unseen is not None:
                cal = cal.replace(warnings=cal.warnings + (unseen,))
                mc.cal_text = cal.to_json()  # the corrected MCAP carries the same calibration
        report_rec = dataclasses.replace(
            plan.header, mag=VectorSeries(sample.t_ns, sample.raw_mag_nT,
                                          plan.header.mag.frame, plan.header.mag.unit),
            attitude=None, position=col.thin_positions(plan.header))
        figures: Future[dict[str, bytes]] | None = None
        if options.write_report:
            # the report's figures need the final model and the kept rows only: drawn on
            # the helper while rerun and the corrected MCAP are closed and the metrics
            # finished (matplotlib is used by this thread alone)
            from stages.report import make_figures

            figures = pool.submit(make_figures, report_rec, cal, segments,
                                  max_gap_s=options.max_gap_s, restored=sample,
                                  diagnosis=win.diagnosis)
        if rrd is not None:
            rrd.finish(sample, segments=segments, diagnosis=win.diagnosis)
        stack.close()  # flush rerun, finish the corrected MCAP (the helper is idle or drawing)
        outputs += (("corrected_mcap", str(mcap_dest)),)
        if options.write_rerun:
            outputs += (("rrd", str(rrd_dest)),)
        metrics = acc.finish()
        j, pq = metrics.write(rec_dir, (str(path),))
        outputs = (("metrics.json", str(j)), ("metrics.parquet", str(pq))) + outputs
        ctx = Context(source=str(path), recording=report_rec, calibration=cal,
                      segments=segments, restored=sample, metrics=metrics,
                      diagnosis=win.diagnosis, outputs=outputs, options=options)
        step("WriteResults")
        ctx = WriteResults(str(rec_dir)).run(ctx)
        if figures is not None:
            step("Report")
            from stages.report import write_report

            # the Report stage's work, with the figures drawn above
            report = write_report(str(rec_dir), ctx.need_recording(), ctx.calibration,
                                  ctx.metrics, ctx.diagnosis, ctx.segments,
                                  max_gap_s=options.max_gap_s, restored=sample,
                                  options=options, figures=figures.result())
            ctx = ctx.replace(outputs=ctx.outputs + (("report.html", str(report)),))
    return ctx


def split_halves(cal: Any, halves: list[Any], kw_fit: dict[str, Any], split_s: float) -> Any:
    """Return the streaming fit ``cal`` checked against the fits of its two halves.

    As the in-memory estimator does (:func:`stages.estimators.checks.apply_split`): when the
    halves of the recording disagree beyond their sigmas, the disagreement goes into the
    rotation's sigmas (and into the verdict's doubts when it more than doubles them), and
    the check is recorded in ``checks["split"]`` (``split_s``: where the halves meet, s
    from the first sample).
    """
    from pipeline.core.errors import EstimationError
    from stages.estimators.checks import SplitCheck, apply_split
    from stages.estimators.streaming import fit_stats

    if min(h.n for h in halves) < 200:
        return cal
    try:
        a, b = (fit_stats(h, **kw_fit).to_calibration() for h in halves)
    except (EstimationError, np.linalg.LinAlgError):
        return cal
    if (a.unobservable_axes_body or b.unobservable_axes_body) and not cal.unobservable_axes_body:
        return cal
    split = SplitCheck.compare(a, b, split_s)
    cal = cal.replace(checks={**cal.checks, "split": split.to_dict()})
    return apply_split(cal, split)


#: the final model's residual over every sample may exceed its residual on the analysed
#: samples by this factor before the user is warned
UNSEEN_RMS_RATIO = 1.25


def _analysed_rms(win: Context) -> float | None:
    """Return the final model's residual RMS (nT) on the samples the analysis saw, or None."""
    d: Any = win.diagnosis
    if d is not None:
        dd: dict[str, Any] = d.to_dict() if hasattr(d, "to_dict") else dict(d)
        v = (dd.get("final") or {}).get("residual_rms_nT")
        if v is not None and np.isfinite(v):
            return float(v)
    cal = win.calibration
    if cal is not None and np.isfinite(cal.residual_rms_nT) and cal.residual_rms_nT > 0:
        return float(cal.residual_rms_nT)
    return None


def unseen_check(per_chunk: list[tuple[int, int, Any]], totals: Any, analysed_rms_nT: float,
                 t0_ns: int) -> str | None:
    """Return a warning when every sample fits the final model worse than the analysed ones.

    The analysis of a long recording sees windows of it; pass 2 restores every sample with
    the final model. When the residual RMS over every sample exceeds the analysed samples'
    by more than :data:`UNSEEN_RMS_RATIO`, something between the windows (a disturbance, a
    step, a change of the platform) was left out of the model: the warning says so and names
    the stretch (a chunk of the recording) where the residual is largest.

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

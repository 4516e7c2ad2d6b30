"""Diagnose: find the physics the fitted model left out, name it, model it, verify it.

Starting from the baseline model (misalignment ``R_body_mag`` and field ``B_enu`` only), every
candidate effect of :mod:`stages.diagnose.model` is tested with a score (Lagrange multiplier) test
at the current fit: the gradient and the information of the added parameters at zero, with
the parameters already in the model profiled out (Schur complement), no refit. The strongest
candidate is refitted and kept only if it raises the Laplace evidence (the sample count
discounted for residual correlation, :func:`~stages.diagnose.statistics.occam`) **and**
lowers the error on held-out time blocks; then the loop repeats until nothing qualifies.
Effects local in time (``disturbance``, ``hard_iron_step``) are located first by a scan of
the robust residual norm; their windows become candidate terms.
Terms the motion cannot determine go to ``not_identifiable`` with the reason.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, cast

import numpy as np

from pipeline.core.geometry import matrix_to_quat, quat_to_rotvec
from pipeline.core.recording import AlignedSeries, Recording
from pipeline.core.vocabulary import EffectKind
from pipeline.core.warm import warm_in_background
from pipeline.model import parallel
from pipeline.model.calibration import Calibration
from pipeline.model.effects import EFFECTS, IRON_PRIOR, kin_words
from pipeline.model.sample_hold import (
    WARNING_PREFIX,
    Handling,
    SampleHold,
    detect_sample_hold,
)
from pipeline.model.solve import one_blas_thread
from stages.context import Context
from stages.diagnose.catalogue import explanation
from stages.diagnose.fit import FitResult, fit
from stages.diagnose.model import (
    F64,
    AttitudeTrack,
    FitData,
    ModelState,
    Term,
    drift_span,
    evaluate,
    held_directions,
    term_params,
    term_sigma,
)
from stages.diagnose.partial import held_words
from stages.diagnose.result import DiagnoseConfig, Diagnosis, Finding
from stages.diagnose.search import MAX_LAG_S, diagnose_data, gradient_note, scan_windows
from stages.diagnose.statistics import (
    INFORMATION_CUT,
    effective_samples,
    fold_errors,
    inflation,
    param_covariance,
    sigma_for,
)
from stages.estimate import WHITE_SIGMA, carry_checks
from stages.estimators.base import solve_many_truncated
from stages.estimators.checks import (
    SplitCheck,
    apply_split,
    info_halves,
    sandwich_cov,
    split_inflation,
    split_limit,
    split_statistic,
    undetermined_directions,
)
from stages.restore import restore_samples


def fit_data_from(
    recording: Recording,
    aligned: AlignedSeries,
    *,
    reference_field_enu_nT: Sequence[float] | np.ndarray | None = None,
    max_samples: int | None = None,
    full_rate_s: Sequence[tuple[float, float]] = (),
) -> FitData:
    """Build the fitting data: stamps in s from the first magnetometer sample.

    The attitude track is the recording's attitude channel (so a time offset re-interpolates
    it); without one (turntable), the aligned attitude shifted back by the ``tau`` it was
    interpolated with. A recording longer than ``max_samples`` is decimated evenly, except
    inside the half-open windows ``full_rate_s`` (s), where every sample is kept: an event
    there is briefer than the decimated data resolve (:func:`brief_events`).
    """
    t0 = recording.origin_ns() if len(recording.mag) else int(aligned.t_ns[0])
    t_s = (np.asarray(aligned.t_ns, dtype=np.int64) - t0) * 1e-9
    if recording.attitude is not None and len(recording.attitude) >= 2:
        ta = (np.asarray(recording.attitude.t_ns, dtype=np.int64) - t0) * 1e-9
        # THE interpolator, as calibrate and restore: the same recording and model
        # give the same prediction
        track = AttitudeTrack(cast(F64, ta),
                              np.asarray(recording.attitude.q_enu_body, dtype=np.float64))
    else:
        track = AttitudeTrack(cast(F64, t_s - aligned.time_offset_s),
                              np.asarray(aligned.q_enu_body, dtype=np.float64))
    y = np.asarray(aligned.mag_nT, dtype=float)
    # a sample whose sensing time t - tau falls outside the attitude track cannot be
    # predicted (the track is held at its ends): for lags up to MAX_LAG_S the samples that
    # close to the track's ends are left out (a lag of 100 ms otherwise shows as a step in
    # the first 0.1 s)
    edge = (t_s >= track.t_s[0] + MAX_LAG_S) & (t_s <= track.t_s[-1] - MAX_LAG_S)
    if np.count_nonzero(edge) >= 0.9 * len(t_s):
        t_s, y = t_s[edge], y[edge]
        aligned_t_ns = np.asarray(aligned.t_ns)[edge]
    else:
        aligned_t_ns = np.asarray(aligned.t_ns)
    pos: dict[str, Any] = {}
    p = _positions_at(recording, aligned_t_ns)
    if p is not None:
        ok = np.isfinite(p).all(axis=1)
        t_s, y, p = t_s[ok], y[ok], p[ok]
        pos = {"p_m": p, "p_ref_m": p.mean(axis=0),
               "position_frame": recording.position.frame.value}  # type: ignore[union-attr]
    n_avail, stride = len(t_s), 1
    if max_samples is not None and len(t_s) > max_samples:
        stride = int(np.ceil(len(t_s) / max_samples))
        keep = np.zeros(len(t_s), dtype=bool)
        keep[::stride] = True
        for a, b in full_rate_s:
            keep |= (t_s >= a) & (t_s < b)
        t_s, y = t_s[keep], y[keep]
        if pos:
            pos["p_m"] = pos["p_m"][keep]
    B = None if reference_field_enu_nT is None else np.asarray(reference_field_enu_nT, float)
    origin = getattr(recording.position, "origin", None) if pos else None
    if origin is not None:
        pos["position_origin"] = origin.to_dict()
    return FitData(cast(F64, t_s), y, track, B_known_enu_nT=B, stride=stride,
                   n_available=n_avail, **pos)


def resolved_s(data: FitData, cfg: DiagnoseConfig) -> float:
    """Shortest event the search's scan resolves in ``data``, s.

    The scan (:func:`~stages.diagnose.search.scan_windows`) smooths over ``scan_smooth_s``
    and at least three samples: on data decimated to a coarser spacing, an event shorter
    than three samples is averaged with noise and lost.
    """
    dt = float(np.median(np.diff(data.t_s))) if len(data) > 1 else 0.0
    return max(cfg.scan_smooth_s, 3.0 * dt)


def brief_events(recording: Recording, aligned: AlignedSeries, data: FitData,
                 state: ModelState, cfg: DiagnoseConfig,
                 reference_field_enu_nT: Sequence[float] | np.ndarray | None = None,
                 ) -> tuple[tuple[float, float], ...]:
    """Windows of events briefer than the decimated ``data`` resolve, found in every sample.

    A recording decimated to the sample budget keeps every ``stride``-th sample: an object
    passed for a second in a two-hour survey leaves one or two of them, which no scan tells
    from noise. The model ``state`` the search selected on ``data`` predicts every sample;
    what its residual holds on time scales shorter than the scan resolves in ``data``
    (:func:`resolved_s`; the residual less its moving mean over that span: what the
    decimated data still follow is the search's own) is scanned at full rate by the same
    detector (:func:`~stages.diagnose.search.scan_windows`, its false-alarm rate shared over
    every sample). Each window it opens, padded as the search pads a transient, is
    returned. Only where the decimation coarsens the scan beyond its own smoothing
    (``scan_smooth_s``: three decimated samples span more) is this needed: finer data
    resolve what the scan was built to see, and are left as they are. The selected model,
    not the baseline: a baseline that lacks a magnet of tens of microtesla is wrong in its
    rotation too, and its residual then follows every quick turn.

    Returns
    -------
    tuple of (start_s, end_s)
        Half-open, s from the first magnetometer sample; empty when ``data`` is not decimated.

    """
    shortest_s = resolved_s(data, cfg)
    if data.stride <= 1 or shortest_s <= cfg.scan_smooth_s:
        return ()  # the decimated data resolve what the scan was built to see
    full = fit_data_from(recording, aligned, reference_field_enu_nT=reference_field_enu_nT)
    r = full.y_nT - evaluate(state, full, jacobian=False).y_nT
    t = full.t_s
    span = max(3, int(round(shortest_s / float(np.median(np.diff(t))))))
    if len(r) < 4 * span:
        return ()
    c = np.concatenate([np.zeros((1, 3)), np.cumsum(r, axis=0)])
    i = np.arange(len(r))
    lo, hi = np.clip(i - span // 2, 0, len(r)), np.clip(i + span // 2 + 1, 0, len(r))
    brief = r - (c[hi] - c[lo]) / (hi - lo)[:, None]
    out = []
    for a, b in scan_windows(brief, t, cfg):
        pad = max(0.5, 0.25 * (b - a))
        out.append((max(float(t[0]), a - pad), min(float(t[-1]) + 1e-6, b + pad)))
    return tuple(out)


#: Positions are used only when at least this fraction of the samples has one.
MIN_POSITION_COVERAGE = 0.5


def _positions_at(recording: Recording, t_ns: np.ndarray) -> np.ndarray | None:
    """Positions at the magnetometer stamps (N, 3), m, NaN where unknown; None when unused.

    Samples without a position (lost markers: NaN rows, or gaps longer than 0.1 s) are
    left out of the diagnosis, for every model alike so that the evidence and held-out errors
    compare the same samples. When fewer than :data:`MIN_POSITION_COVERAGE` of the samples
    have a position, the positions are not used at all (``field_gradient`` is then not
    identifiable: no positions).
    """
    if recording.position is None or len(t_ns) == 0:
        return None
    p = recording.position.at(np.asarray(t_ns, dtype=np.int64))
    if np.mean(np.isfinite(p).all(axis=1)) < MIN_POSITION_COVERAGE:
        return None
    return p


def _heldout_split(state: ModelState, train: FitData, test: FitData, cfg: DiagnoseConfig,
                   t0_s: float, block_of: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Held-out RMS (nT) when the model is fitted on ``train`` and predicts ``test``.

    :func:`~stages.diagnose.statistics.fold_errors` over the time blocks of
    :func:`heldout_rms`, counted from ``t0_s`` (with the first sample of the diagnosis data
    the folds are exactly those of :func:`heldout_rms`); the samples fitted and the samples
    predicted may differ: the repeats of a sample-and-hold sensor are predicted although
    only the first copies are fitted.

    Returns the RMS and the squared error of each test sample (summed over its components),
    so that two handlings can be compared block by block (``block_of``: the test samples'
    block numbers, default from their own stamps).
    """
    f_tr = np.floor((train.t_s - t0_s) / cfg.block_s).astype(np.int64) % cfg.n_folds
    blk = (np.floor((test.t_s - t0_s) / cfg.block_s).astype(np.int64) if block_of is None
           else np.asarray(block_of, dtype=np.int64))
    f_te = blk % cfg.n_folds
    sq, cnt = 0.0, 0
    per = np.full(len(test), np.nan)
    for te, e in fold_errors(state, train, test, f_tr, f_te, cfg.n_folds):
        sq += float(np.sum(e * e))
        cnt += e.size
        per[te] = np.sum(e * e, axis=1)
    return float(np.sqrt(sq / max(cnt, 1))), per


def _blocks_better(sq_old: np.ndarray, sq_new: np.ndarray, block: np.ndarray) -> bool:
    """Tell whether the new handling lowers the held-out error block by block, beyond chance.

    Paired over the held-out blocks (one second each): the mean of the per-block changes of
    the squared error must exceed twice its standard error. A change of a few tenths of a
    percent that some blocks gain and others lose is not evidence.
    """
    ok = np.isfinite(sq_old) & np.isfinite(sq_new)
    if ok.sum() < 10:
        return False
    _, inv = np.unique(block[ok], return_inverse=True)
    d = np.bincount(inv, weights=sq_old[ok] - sq_new[ok])
    if len(d) < 5:
        return False
    return bool(np.mean(d) > 2.0 * np.std(d, ddof=1) / np.sqrt(len(d)))


def sample_hold_finding(
    diag: Diagnosis,
    res: FitResult,
    data: FitData,
    recording: Recording,
    aligned: AlignedSeries,
    sh: SampleHold,
    cfg: DiagnoseConfig,
    *,
    reference_field_enu_nT: Any = None,
) -> tuple[Diagnosis, FitResult, FitData, Handling] | None:
    """Add the ``sample_hold`` finding: the final model refitted on the handled data.

    Up to three handlings are compared on the same messages (the diagnosis samples, repeats
    included) by their held-out RMS: (a) ``first_stamp``: the repeats are left out of the fit
    and every message is predicted at the stamp of the first copy of its conversion; (b)
    ``native_grid``: as (a), with the conversions re-stamped on the sensor's native grid
    (``SampleHold.t_sensed_ns``); (c) ``anchored``: as (a), with the conversions at their
    anchor-rule sensing times (``SampleHold.t_anchored_ns``: a reading held over three
    messages sensed at its middle one, the conversions between such readings evenly spaced),
    each tried only where its times differ from those before it. The best one is kept;
    without it (the messages fitted and predicted at their own stamps) is the final model of
    ``diag``. The finding is added when the handling lowers the held-out error by
    ``heldout_margin`` (as every finding) and the fall holds over the held-out blocks
    (:func:`_blocks_better`); its evidence is the change of the in-sample and held-out RMS
    over the same messages.

    Returns
    -------
    (Diagnosis, FitResult, FitData, Handling) or None
        The diagnosis with the finding appended, the fit on the handled data, that data and
        the handling kept; None when the handling does not help.

    """
    mag_t = np.asarray(recording.mag.t_ns, dtype=np.int64)
    t0 = recording.origin_ns()
    idx = np.clip(np.searchsorted(mag_t, t0 + np.round(data.t_s * 1e9).astype(np.int64)), 0,
                  len(mag_t) - 1)
    first_idx = np.maximum.accumulate(np.where(sh.first, np.arange(len(mag_t)), 0))
    al_idx = (np.arange(len(aligned)) if aligned.index is None
              else np.asarray(aligned.index, dtype=np.int64))
    keep = sh.first[al_idx]
    variants: dict[Handling, np.ndarray] = {"first_stamp": mag_t[first_idx]}
    # a handling that gives the same times as one before it is not fitted again: the native
    # grid falls back to the first copies' stamps on an irregular grid, the anchor rule
    # without anchors
    others: tuple[tuple[Handling, np.ndarray], ...] = (("native_grid", sh.t_sensed_ns),
                                                        ("anchored", sh.t_anchored_ns))
    for handling, t_h in others:
        t_h = np.asarray(t_h, dtype=np.int64)
        if not any(np.array_equal(t_h, v) for v in variants.values()):
            variants[handling] = t_h
    block = np.floor((data.t_s - float(data.t_s[0])) / cfg.block_s).astype(np.int64)
    best = None
    for name, t_new in variants.items():
        al_new = AlignedSeries(t_new[al_idx][keep], aligned.mag_nT[keep],
                               aligned.q_enu_body[keep], aligned.time_offset_s, al_idx[keep])
        train = fit_data_from(recording, al_new, reference_field_enu_nT=reference_field_enu_nT,
                              max_samples=cfg.max_samples)
        test = dataclasses.replace(data, t_s=cast(F64, (t_new[idx] - t0) * 1e-9))
        if len(train) < 30:
            continue
        cv, sq = _heldout_split(res.state, train, test, cfg, float(data.t_s[0]), block)
        if best is None or cv < best[0]:
            best = (cv, name, train, test, sq)
    # the same blocks as the handled variants and as diag.final's held-out error
    cv_old, sq_old = _heldout_split(res.state, data, data, cfg, float(data.t_s[0]), block)
    # the rule of every other finding (the held-out error falls by heldout_margin), and the
    # fall holds block by block: the repeats are a fact of the sensor, the finding says that
    # handling them changes the fit
    if best is None or not best[0] < cv_old * (1.0 - cfg.heldout_margin) \
            or not _blocks_better(sq_old, best[4], block):
        return None
    cv_new, name, train, test, _ = best
    res_h = fit(res.state, train)
    r_new = test.y_nT - evaluate(res_h.state, test, jacobian=False).y_nT
    rss_new = float(np.sum(r_new * r_new))
    n_eff = effective_samples(res, data)
    s2 = res.rss / res.residual_nT.size
    span = float(mag_t[-1] - mag_t[0]) * 1e-9
    p = sh.params()
    expl = EFFECTS[EffectKind.SAMPLE_HOLD].physics + "; signature: " + EFFECTS[
        EffectKind.SAMPLE_HOLD].signature + ". " + sh.explanation(handling=name) + (
        f" Compared on the same messages, the held-out error goes from {cv_old:.1f} to "
        f"{cv_new:.1f} nT. Read the sensor at its native rate (or publish only new "
        "conversions, stamped when they were sensed)")
    fd = Finding(
        effect=EffectKind.SAMPLE_HOLD.value,
        params=p,
        sigma={"native_rate_hz": 1.0 / max(span, 1e-9),
               "repeated_fraction": float(np.sqrt(p["repeated_fraction"] * (
                   1 - p["repeated_fraction"]) / len(mag_t)))},
        evidence={
            # no parameter is added: the in-sample RSS over the messages cannot rise or fall
            # by fitting, so the statistic and the evidence's change are those of the held-out error
            "statistic": float((cv_old**2 - cv_new**2) * n_eff / s2),
            "delta_bic": float(n_eff * np.log(max(cv_new, 1e-30) ** 2 / max(cv_old, 1e-30) ** 2)),
            "rms_before_nT": res.rms_nT,
            "rms_after_nT": float(np.sqrt(rss_new / max(r_new.size, 1))),
            "heldout_rms_before_nT": cv_old,
            "heldout_rms_after_nT": float(cv_new),
        },
        where={"windows_s": [[0.0, float(data.t_s[-1])]], "axes": ["x", "y", "z"],
               "frame": "mag"},
        explanation=expl,
    )
    final = {
        "effects": list(diag.final["effects"]) + [fd.effect],
        "residual_rms_nT": fd.evidence["rms_after_nT"],
        "heldout_rms_nT": float(cv_new),
    }
    return (dataclasses.replace(diag, findings=diag.findings + (fd,), final=final), res_h,
            train, name)


def with_final_values(diag: Diagnosis, before: FitResult, before_data: FitData,
                      after: FitResult, after_data: FitData) -> Diagnosis:
    """Return ``diag`` whose findings quote the values of the ``after`` fit.

    The search names each term and states its values at its own final fit (``before`` on
    ``before_data``); a later refit of the same terms (the sample-and-hold handling) moves
    them. The calibration holds the refit's values, so each finding's ``params`` and the
    numbers in its explanation are taken from it too: a reader then sees one value of each
    quantity in every output. The sigmas are the final covariance's (:func:`with_sigmas`),
    set once the halves have been compared. The evidence (how much each term lowered the
    residual, step by step) stays as measured. Findings without a term of their own (the
    sample-and-hold finding) are kept as they are.
    """
    terms = after.state.terms
    if len(terms) != len(before.state.terms):
        return diag
    not_ident = {e: r for e, r in diag.not_identifiable}
    note_old = gradient_note(before, before_data, not_ident)
    note_new = gradient_note(after, after_data, not_ident)
    out = list(diag.findings)
    for i, term in enumerate(terms):
        if i >= len(out) or out[i].effect != term.kind.value:
            return diag  # not the search's order: leave the findings as measured
        fd = out[i]
        p_new = term_params(term, after.state.values[i], after.state, after_data)
        text = fd.explanation
        head_old = explanation(term.kind, fd.params, before_data.duration_s, note=note_old)
        if text.startswith(head_old):
            text = (explanation(term.kind, p_new, after_data.duration_s, note=note_new)
                    + text[len(head_old):])
        if term.partial:
            held_old = held_words(before, i, before_data)
            if held_old and held_old in text:
                text = text.replace(held_old, held_words(after, i, after_data))
        out[i] = dataclasses.replace(fd, params=p_new, explanation=text)
    return dataclasses.replace(diag, findings=tuple(out))


def with_kin_words(diag: Diagnosis) -> Diagnosis:
    """Return ``diag`` whose findings say what each says about the others of its effect.

    Run once on the final findings (:func:`pipeline.model.effects.kin_words`): several
    dipoles that the data do not resolve as separate objects are one object.
    """
    fs = diag.findings
    words = kin_words([f.effect for f in fs], [f.params for f in fs])
    return dataclasses.replace(diag, findings=tuple(
        dataclasses.replace(f, explanation=f.explanation + w) if w else f
        for f, w in zip(fs, words, strict=True)))


def with_sigmas(diag: Diagnosis, res: FitResult, data: FitData, cov: np.ndarray) -> Diagnosis:
    """Return ``diag`` whose findings state the sigmas of ``cov`` (those of ``res``'s terms).

    Findings without a term of their own, or not in the model's order, keep theirs.
    """
    out = list(diag.findings)
    for i, term in enumerate(res.state.terms):
        if i < len(out) and out[i].effect == term.kind.value:
            out[i] = dataclasses.replace(out[i], sigma=sigma_for(res, i, cov, data))
    return dataclasses.replace(diag, findings=tuple(out))


def _sample_hold_stated(cal: Calibration, sh: SampleHold | None, handled: bool) -> Calibration:
    """Return ``cal`` stating the repeats as the final model treats them.

    The estimate detects the repeats on the samples it fitted and leaves them out; the
    diagnosis detects them on every message, and its final model leaves them out only when
    that (or timing them at the sensor's rate) predicts held-out data better, the
    ``sample_hold`` finding (``handled``). The calibration's ``sample_hold`` and its warning
    quote the diagnosis' native rate and fraction, so that one figure stands in every output,
    and say what the final model did, not what the estimate did.
    """
    others = tuple(w for w in cal.warnings if not w.startswith(WARNING_PREFIX))
    if sh is None:  # the messages of the whole recording hold no repeats
        return cal.replace(sample_hold=None, warnings=others)
    return cal.replace(sample_hold=sh.params(), warnings=others + (sh.warning(handled),))


def _model_values(term: Term, value: np.ndarray, data: FitData) -> dict[str, Any]:
    """Return the fitted values of a term that its CONVENTIONS params cannot reproduce.

    The CONVENTIONS params of these terms (``peak_nT``, ``peak_to_peak_nT``) describe them
    but cannot reproduce them; the calibration also carries the fitted values so that
    :meth:`pipeline.model.calibration.Calibration.predict` includes them (the residual of the
    final model is then the same number everywhere).
    """
    if term.kind is EffectKind.DISTURBANCE:
        knots = term.knots()
        v = np.asarray(value, dtype=float).reshape(-1, 3)
        out, i = [], 0
        for kn in knots:
            out.append(v[i:i + len(kn)].tolist())
            i += len(kn)
        return {"knots_s": [k.tolist() for k in knots], "knot_field_nT": out}
    if term.kind is EffectKind.HARD_IRON_STEP and term.ramps_s:
        # the transitions while the magnet moved: their modes (restore evaluates them with
        # the same basis, pipeline.model.forward.ramp_profile)
        return {"ramps_s": [[float(a), float(b)] for a, b in term.ramps_s],
                "ramp_modes_nT": np.asarray(value[3:], dtype=float).reshape(-1, 3).tolist(),
                "ramp_mode_step_s": term.knot_step_s}
    if term.kind is EffectKind.FIELD_DRIFT:
        return {"legendre_nT": np.asarray(value, dtype=float).reshape(-1, 3).tolist(),
                "span_s": drift_span(data)}
    if term.kind is EffectKind.HEADING_DRIFT:
        return {"legendre_rad": np.asarray(value, dtype=float).reshape(-1).tolist(),
                "span_s": drift_span(data)}
    if term.kind is EffectKind.LOCAL_SOURCE:
        # the bearing of the position frame the source was fitted in (not a CONVENTIONS
        # param: the model needs it to place the source in ENU)
        psi = float(value[6]) if term.fit_yaw else term.yaw_rad
        return {"frame_yaw_deg": float(np.degrees(psi))}
    if term.kind is EffectKind.FIELD_GRADIENT:
        # the same for the gradient (the lever arm turns the sensor's offset in ENU)
        return {"frame_yaw_deg": float(np.degrees(term.yaw_rad))}
    if term.kind is EffectKind.FIELD_MAP:
        # the weights' basis: the modes per axis of the box (``n_basis`` is their product)
        # and the bearing of the position frame the box is in
        return {"n_per_axis": [int(x) for x in term.n_axis],
                "frame_yaw_deg": float(np.degrees(term.yaw_rad))}
    return {}


def with_undetermined_iron(cal: Calibration, res: FitResult, data: FitData,
                           kinds: Sequence[str]) -> Calibration:
    """Return ``cal`` whose rotation sigmas cover iron the motion cannot determine.

    A recording that does not turn the sensor enough leaves the offset or the soft-iron
    matrix confounded with the field and the rotation, so the fit leaves them out (``kinds``,
    not in the model) or holds the combinations it cannot determine (a partial term of the
    model, :meth:`~stages.diagnose.model.Term.restricted`); a real one then biases R by an
    amount the noise sigma does not show. In the linearised model the bias of leaving out
    ``theta`` is ``K theta`` with ``K = -(J'WJ)^-1 J'W J_theta`` (the regression of the
    left-out columns on the fitted ones, at the final state: a left-out term's columns, a
    partial term's held ones ``J_full U``); over a prior of typical size (:data:`IRON_PRIOR`
    per parameter or held combination, ``Sigma``) its covariance is ``K Sigma K'``. Each
    rotation sigma becomes ``sqrt(sigma^2 + (K Sigma K')_ii)`` and a doubt says so.
    """
    st = res.state
    P0 = res.info.shape[0]
    held = [t for t in st.terms if t.partial and t.kind.value in IRON_PRIOR]
    kinds = list(kinds)
    if not kinds and not held:
        return cal
    for k in kinds:
        st = st.with_term(Term(EffectKind(k)))
    ev = evaluate(st, data, jacobian=True)
    if ev.J is None:
        return cal
    w = None if ev.sqrt_w is None else ev.sqrt_w[:, None, None]
    J = ev.J if w is None else ev.J * w
    J = J.reshape(-1, J.shape[-1])
    left = J[:, P0:]
    prior = [np.full(Term(EffectKind(k)).n_params(), IRON_PRIOR[k]) for k in kinds]
    if ev.J_held is not None:
        Jh = ev.J_held if w is None else ev.J_held * w
        left = np.concatenate([left, Jh.reshape(-1, Jh.shape[-1])], axis=1)
        prior += [np.full(t.full_size() - t.n_params(), IRON_PRIOR[t.kind.value])
                  for t in st.terms if t.partial]
    H = res.info.copy()  # what the fit itself used (its ridge included)
    cross = J[:, :P0].T @ left
    if data.B_known_enu_nT is not None:  # the field is given: not a fitted column
        H[3:6, :] = 0.0
        H[:, 3:6] = 0.0
        H[3:6, 3:6] = np.eye(3)
        cross[3:6, :] = 0.0
    K = -solve_many_truncated(H, cross, INFORMATION_CUT)
    sd = np.concatenate(prior)
    sig_b = np.degrees(np.sqrt(np.clip(np.einsum("ij,j,ij->i", K[:3], sd**2, K[:3]),
                                       0, None)))
    sig = np.asarray(cal.sigma_rotvec_deg, float)
    wider = np.where(np.isfinite(sig), np.hypot(sig, sig_b), sig)
    terms = [k for k in IRON_PRIOR if k in kinds or any(t.kind.value == k for t in held)]
    # the verdict's words match the start ("hard iron or soft iron"); a held part is named
    # after it
    names = " or ".join(x.replace("_", " ") for x in terms)
    part = "; ".join(f"of the {t.kind.value.replace('_', ' ')} the fit holds "
                     f"{t.undetermined().shape[1]} combination(s) it cannot determine"
                     for t in held)
    sizes = ", ".join(f"{IRON_PRIOR[k]:g}{' nT' if k == 'hard_iron' else ''} {k.replace('_', ' ')}"
                      for k in terms)
    doubt = (f"the motion cannot determine {names}"
             + (": the fit leaves it out" if kinds else "") + (f" ({part})" if part else "")
             + f"; the sigmas include what one of typical size ({sizes}) would do to the "
             f"misalignment (up to {float(np.max(sig_b)):.2f} deg)")
    out: dict[str, Any] = {"terms": terms, "prior": {k: IRON_PRIOR[k] for k in terms},
                           "sigma_rotvec_bias_deg": sig_b.tolist()}
    if held:
        # the combinations a partial term holds (mag-frame unit vectors for the offset,
        # unit symmetric matrices for D), so a reader knows which part of the term in the
        # calibration is a reference and not a measurement
        out["held"] = {t.kind.value: held_directions(t) for t in held}
    return cal.replace(sigma_rotvec_deg=wider, checks={
        **cal.checks, "undetermined_iron": out,
        "doubts": list(cal.checks.get("doubts", ())) + [doubt]})


def calibration_from(res: FitResult, data: FitData, findings: tuple[Finding, ...],
                     cov: np.ndarray | None = None) -> Calibration:
    """Return the final model as a Calibration; terms beyond D, o, tau go to ``effects``.

    ``cov``: the parameter covariance its sigmas come from (default the fit's own).
    """
    st = res.state
    if cov is None:
        cov = param_covariance(res, data)
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    sig_rot = np.degrees(sd[0:3])
    D = st.D() if st.value(EffectKind.SOFT_IRON) is not None else None
    o = st.value(EffectKind.HARD_IRON)
    tau = st.value(EffectKind.TIME_OFFSET)
    extra: dict[str, Any] = {}
    sig: dict[str, Any] = {}
    for i, t in enumerate(st.terms):
        blk = slice(st.offsets()[i], st.offsets()[i] + t.n_params())
        if t.kind is EffectKind.HARD_IRON:
            # a partial offset's held component carries its prior's sigma (held_covariance)
            sig["offset"] = np.asarray(term_sigma(t, cov[blk, blk], st, data)["offset_nT"])
        elif t.kind is EffectKind.SOFT_IRON:
            sig["D"] = np.asarray(term_sigma(t, cov[blk, blk], st, data)["D"])
        elif t.kind is EffectKind.TIME_OFFSET:
            sig["tau"] = float(sd[blk][0])
        else:
            params = term_params(t, st.values[i], st, data)
            params.update(_model_values(t, st.values[i], data))
            extra.setdefault(t.kind.value, []).append(params)
    effects = {k: (v[0] if len(v) == 1 else v) for k, v in extra.items()}
    return Calibration(
        R_body_mag=st.R_body_mag,
        sigma_rotvec_deg=sig_rot,
        B_enu_nT=st.B_enu_nT,
        estimator="diagnose",
        residual_rms_nT=res.rms_nT,
        n_samples=len(data),
        D=D,
        offset_nT=o,
        time_offset_s=None if tau is None else float(tau[0]),
        sigma_D=sig.get("D"),
        sigma_offset_nT=sig.get("offset"),
        sigma_time_offset_s=sig.get("tau"),
        sigma_B_enu_nT=None if data.B_known_enu_nT is not None else sd[3:6],
        effects=effects,
    )


@dataclass(frozen=True)
class Halves:
    """The final model refitted on two contiguous halves of equal rotation information.

    Attributes
    ----------
    t_split_s : float
        Where the second half begins, s from the first sample.
    fits : tuple of (FitResult, FitData)
        Each half's fit and its samples.

    """

    t_split_s: float
    fits: tuple[tuple[FitResult, FitData], tuple[FitResult, FitData]]


def fit_halves(res: FitResult, data: FitData) -> Halves | None:
    """Refit the final model on two contiguous halves of equal rotation information.

    None when the recording or a half is too small. A term that the motion barely
    determines, or physics the final model still leaves out, shows up as halves that
    disagree.
    """
    if len(data) < 200:
        return None
    ev = evaluate(res.state, data)
    Jr = ev.jac[:, :, 0:3]
    first = info_halves(np.einsum("nip,nip->n", Jr, Jr))
    fits = []
    for m in (first, ~first):
        sub = data.subset(m)
        if len(sub) < 50:
            return None
        fits.append((fit(res.state, sub), sub))
    t_split = float(data.t_s[np.flatnonzero(~first)[0]] - data.t_s[0])
    return Halves(t_split, (fits[0], fits[1]))


def covered_covariance(res: FitResult, data: FitData, halves: Halves | None) -> np.ndarray:
    """Return the parameter covariance with each term's block covering what the halves show.

    The rotation's rule (:func:`stages.estimators.checks.apply_split`), applied to every
    term in the directions of its parameters that both halves measure
    (:func:`shared_directions`): there the difference ``d`` of the term's values between
    the two halves is tested at the halves' stated false-alarm rate
    (:func:`stages.estimators.checks.split_limit`), and where it fails, ``d d^T / 2`` of
    the whole difference is added to the term's block
    (:func:`stages.estimators.checks.split_inflation`: each half's bias spreads by about
    ``|d| / sqrt(2)`` along ``d``), so that along ``d`` the stated sigma is at least
    ``|d| / sqrt(2)``. The statistic is the smaller of ``d' E^+ d`` under what the fits
    expect of ``d``: ``4 C`` from the whole recording's covariance ``C`` of the block
    (halves of equal information each have twice its variance) and ``C_a + C_b`` from the
    halves' own (left out where a half's covariance is not finite); its degrees of freedom
    are the rank of ``E`` in those directions. A term with held combinations (its values
    have more entries than its free parameters) keeps its covariance. The rotation's own
    halves check is :func:`final_split`.
    """
    cov = param_covariance(res, data)
    if halves is None:
        return cov
    (ra, sa), (rb, sb) = halves.fits
    ca, cb = param_covariance(ra, sa), param_covariance(rb, sb)
    shared = shared_directions(res, halves)
    added = np.zeros_like(cov)
    for i, t in enumerate(res.state.terms):
        o, k = res.state.offsets()[i], t.n_params()
        d = np.asarray(ra.state.values[i], float) - np.asarray(rb.state.values[i], float)
        P = shared[i]
        if d.size != k or k == 0 or not P.any():
            continue
        blk = slice(o, o + k)
        ds = P @ d
        tests = []
        for e in (4.0 * cov[blk, blk], ca[blk, blk] + cb[blk, blk]):
            if not np.all(np.isfinite(e)):
                continue
            e = P @ e @ P.T
            dof = int(np.linalg.matrix_rank(e, hermitian=True))
            if dof:
                tests.append(float(ds @ np.linalg.pinv(e, hermitian=True) @ ds)
                             / split_limit(dof))
        if tests and min(tests) > 1.0:
            # shown to disagree where both measure the term: what moved it between the
            # halves is not confined to those directions, and the whole difference goes in
            added[blk, blk] = split_inflation(d)
    return cov + added


#: Least share of a direction's information each half must hold for the halves to be
#: compared along it. A half with a tenth of it still measures that combination (to about
#: three times the whole recording's sigma); below that the half's value is its prior's, or
#: a wrong place that a distant view allows, not a second measurement: in a ground survey,
#: sources passed in one half only left 0.1-2.4 % of their information to the other, which
#: moved them by 3-7 m under a linearised sigma of 0.4 m; a disturbance whose window ends
#: 0.5 s into the second half left it its last knots only.
MIN_HALF_SHARE = 0.1


def shared_directions(res: FitResult, halves: Halves) -> list[np.ndarray]:
    """Projector onto the combinations of each term's parameters that both halves measure.

    Both halves are evaluated at the whole recording's solution (a half's own fit may have
    wandered where the half says little), giving the informations ``I_a`` and ``I_b``
    (``J^T W J``) of each term's block. The generalised eigenvectors ``v`` of
    ``I_a v = lam (I_a + I_b) v`` split the block into directions that half ``a`` holds
    the share ``lam`` of, half ``b`` the rest; those with both shares at least
    :data:`MIN_HALF_SHARE` are compared. Returns, per term, the ``(k, k)`` projector
    ``V V^T (I_a + I_b)`` onto them along the others (zero: nothing to compare).
    """
    info = []
    for _, sub in halves.fits:
        ev = evaluate(res.state, sub)
        J = ev.jac if ev.sqrt_w is None else ev.jac * ev.sqrt_w[:, None, None]
        J = J.reshape(-1, J.shape[-1])
        info.append(J.T @ J)
    out = []
    for i, t in enumerate(res.state.terms):
        o, k = res.state.offsets()[i], t.n_params()
        blk = slice(o, o + k)
        Ia, M = info[0][blk, blk], info[0][blk, blk] + info[1][blk, blk]
        m, U = np.linalg.eigh(M) if k else (np.zeros(0), np.zeros((0, 0)))
        live = m > 1e-12 * (float(m.max()) if m.size else 0.0)
        if not live.any():
            out.append(np.zeros((k, k)))
            continue
        W = U[:, live] / np.sqrt(m[live])  # whitens M: W^T M W = I
        lam, Q = np.linalg.eigh(W.T @ Ia @ W)
        both = (lam >= MIN_HALF_SHARE) & (lam <= 1.0 - MIN_HALF_SHARE)
        V = W @ Q[:, both]
        out.append(V @ V.T @ M)
    return out


def final_split(res: FitResult, halves: Halves | None, excluded: np.ndarray | None = None):
    """Compare the rotations of the final model's two halves (:func:`fit_halves`).

    Returns a :class:`stages.estimators.checks.SplitCheck` (the halves' rotations, their
    difference and its chi-square under the covariance of the difference), or None without
    halves. Each half's rotation covariance is its block sandwich
    (:func:`half_rotation_cov`), as the estimator's halves are; ``excluded``: directions the
    recording does not determine, not compared.
    """
    if halves is None:
        return None
    out = [(r.state.R_body_mag, half_rotation_cov(r, sub)) for r, sub in halves.fits]
    (Ra, ca), (Rb, cb) = out

    def rv(R: np.ndarray) -> np.ndarray:
        return quat_to_rotvec(matrix_to_quat(R))

    d = rv(Ra @ Rb.T)
    chi2, dof = split_statistic(d, ca + cb, excluded)
    return SplitCheck(np.degrees(rv(Ra)), np.degrees(rv(Rb)), np.degrees(d), chi2,
                      halves.t_split_s, dof)


def half_rotation_cov(r: FitResult, sub: FitData) -> np.ndarray:
    """Rotation covariance (rad^2, 3x3) of a fit to one half: the block sandwich.

    ``param_covariance`` inflates the white covariance by one factor measured on the
    residual's block means; what the rotation feels is the correlation of its scores
    ``J_i^T r_i`` (attitude noise interpolated between attitude samples is correlated
    across components and in time, and the Jacobian weighs it by the motion). The block
    (batch-means) sandwich of the estimator (:func:`stages.estimators.checks.sandwich_cov`)
    measures that, never below the white covariance.
    """
    white = param_covariance(r, sub)
    P = r.info.shape[0]
    dof = max(r.residual_nT.size - P, 1)
    s2 = r.rss / dof
    scale = s2 * inflation(r.residual_nT, sub.t_s)
    if not np.isfinite(scale) or scale <= 0:
        return np.asarray(white[0:3, 0:3], float)
    H_pinv = white / scale
    ev = evaluate(r.state, sub)
    J = ev.jac if ev.sqrt_w is None else ev.jac * ev.sqrt_w[:, None, None]
    if sub.B_known_enu_nT is not None:
        J = J.copy()
        J[:, :, 3:6] = 0.0
    t_ns = np.round((sub.t_s - sub.t_s[0]) * 1e9).astype(np.int64)
    cov, _ = sandwich_cov(J, None, np.ones(len(sub)), r.residual_nT, t_ns, H_pinv,
                          s2 * H_pinv)
    return np.asarray(cov[0:3, 0:3], float)


@dataclass(frozen=True)
class Diagnose:
    """Stage: find, name, model and verify what the calibration model leaves out.

    Parameters
    ----------
    config : DiagnoseConfig
    reference_field_enu_nT : tuple of 3 floats, optional
        Known background field (ENU, nT); the field is then not estimated (and ``axis_tilt``
        becomes identifiable on a turntable).
    max_gap_s : float or None
        Attitude gap rule of the final model's residual over the whole recording (as the
        Restore stage); None: the automatic rule.
    keep_estimate : bool
        The user chose the model (``--estimate``, another estimator): the estimate in
        ``ctx.calibration`` stays the answer. Its rotation sigma is widened by the shift of
        ``R_body_mag`` between it and the diagnosis' final model when that model holds terms
        the estimate left out (:func:`left_out_shift`), and the verdict says so.

    The final residual (``diagnosis.final.residual_rms_nT`` and the final calibration's
    ``residual_rms_nT``) is that of the final model over every sample of the recording with
    a usable attitude (:func:`stages.restore.restore_samples`): the number the restored
    ``<mag>/residual`` channel, the residual figure and the report show.

    """

    config: DiagnoseConfig = field(default_factory=DiagnoseConfig)
    reference_field_enu_nT: tuple[float, float, float] | None = None
    max_gap_s: float | None = None
    keep_estimate: bool = False

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "aligned", "calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"diagnosis", "calibration"})

    def run(self, ctx: Context) -> Context:
        """Diagnose ``ctx.recording``; the final model replaces ``ctx.calibration``."""
        # hundreds of fits of a few hundred parameters: their factorizations run on one BLAS
        # thread (pipeline.model.solve.one_blas_thread), and the fits that do not depend on
        # each other side by side on the cores the process may use (pipeline.model.parallel)
        with parallel.side_by_side(), one_blas_thread():
            return self._run(ctx)

    def _run(self, ctx: Context) -> Context:
        """:meth:`run` itself."""
        rec, al = ctx.need_recording(), ctx.need_aligned()
        data = fit_data_from(
            rec, al, reference_field_enu_nT=self.reference_field_enu_nT,
            max_samples=self.config.max_samples,
        )
        # the compiled loops load on a helper thread: the attitude's first, which the first
        # fit waits for; the sources' are ready by the time the search tries a source
        if data.compiled:
            warm_in_background("pipeline.model.attitude_kernels:warm",
                               "pipeline.model.dipole_kernels:warm")
        init = None
        cal = ctx.calibration
        if cal is not None:
            init = ModelState(np.asarray(cal.R_body_mag), np.asarray(cal.B_enu_nT))
        turntable = rec.turntable is not None
        diag, res = diagnose_data(data, init, self.config, turntable=turntable)
        brief = brief_events(rec, al, data, res.state, self.config,
                             reference_field_enu_nT=self.reference_field_enu_nT)
        if brief:
            # the search again, on data that hold every sample of those events
            data = fit_data_from(rec, al, reference_field_enu_nT=self.reference_field_enu_nT,
                                 max_samples=self.config.max_samples, full_rate_s=brief)
            diag, res = diagnose_data(data, init, self.config, turntable=turntable)
        data = dataclasses.replace(data, noise_model=res.noise_model)
        sh = detect_sample_hold(rec.mag.t_ns, rec.mag.values)
        extra: dict[str, Any] = {}
        if sh is not None:
            out = sample_hold_finding(diag, res, data, rec, al, sh, self.config,
                                      reference_field_enu_nT=self.reference_field_enu_nT)
            if out is not None:
                before, before_data = res, data
                diag, res, data, handling = out
                diag = with_final_values(diag, before, before_data, res, data)
                # the restore times the conversions as the fit that chose the handling did
                extra["sample_hold"] = {**diag.findings[-1].params, "handling": handling}
        # every sigma a user reads covers what the recording's halves show
        halves = fit_halves(res, data)
        cov = covered_covariance(res, data, halves)
        diag = with_kin_words(with_sigmas(diag, res, data, cov))
        final = calibration_from(res, data, diag.findings, cov)
        if extra:
            final = dataclasses.replace(final, effects={**(final.effects or {}), **extra})

        split = final_split(res, halves, undetermined_directions(final, cal))
        if cal is not None:

            # one halves check decides, that of the model which is the answer: when the
            # final model's halves were compared, their check (apply_split below) is the one
            # the sigma and the verdict carry, whether it passes or not. The estimate's,
            # measured without the terms the data asked for (lab_02: 54 deg without its
            # magnet, 0.4 deg with it), says nothing about the final model's rotation; with
            # no findings the final model is the estimate's, and testing it twice would
            # double the check's false-alarm rate. Without a final split the findings, if
            # any, stand for the physics that made the estimate's halves disagree.
            explained = split is not None or bool(diag.findings)
            final = carry_checks(cal, final, explained=explained)
        # the verdict weighs the stated sigma against what the final model's motion gives
        final = with_white_sigma(final, res, data)
        if sh is not None or final.sample_hold is not None:
            final = _sample_hold_stated(final, sh, handled="sample_hold" in extra)
        if split is not None:
            final = final.replace(checks={**final.checks, "split_final": split.to_dict()})
            final = apply_split(final, split, " under the final model")
        iron = [e for e, _ in diag.not_identifiable if e in ("hard_iron", "soft_iron")]
        iron = [e for e in iron if res.state.value(EffectKind(e)) is None]
        partial = any(t.partial and t.kind.value in IRON_PRIOR for t in res.state.terms)
        if (iron or partial) and len(final.unobservable_axes_body) == 0:
            final = with_undetermined_iron(final, res, data, iron)
        fit_samples: dict[str, Any] = {"n": len(data), "stride": int(data.stride),
                                       "of": int(data.n_available or len(data))}
        if "sample_hold" in extra:
            fit_samples["note"] = ", sample-and-hold repeats left out"
        final = final.replace(checks={**final.checks, "fit_samples": fit_samples})
        restored = None
        if rec.attitude is not None and len(rec.attitude) >= 2:

            restored = restore_samples(rec, final, max_gap_s=self.max_gap_s)
            rms = restored.residual_rms_nT
            if np.isfinite(rms):
                final = final.replace(residual_rms_nT=rms)
                diag = dataclasses.replace(diag, final={**diag.final, "residual_rms_nT": rms})
        if self.keep_estimate and cal is not None:
            # the user's model is the answer; the restore of the diagnosis' model is not its
            return ctx.replace(diagnosis=diag, calibration=left_out_shift(cal, final, diag))
        return ctx.replace(diagnosis=diag, calibration=final)


def white_rotation_sigma_deg(res: FitResult, data: FitData) -> np.ndarray:
    """Return the rotation's white-noise sigma (deg, body x, y, z) of the fit ``res``.

    ``s^2 (J'J)^-1`` without the residual-correlation inflation of
    :func:`~stages.diagnose.statistics.param_covariance`: what the motion determines when
    every sample is independent, the geometry of the turns under the fit's own noise.
    """
    cov = param_covariance(res, data) / inflation(res.residual_nT, data.t_s)
    return np.degrees(np.sqrt(np.clip(np.diag(cov)[0:3], 0.0, None)))


def with_white_sigma(final: Calibration, res: FitResult, data: FitData) -> Calibration:
    """Return ``final`` stating its own white-noise rotation sigma.

    Check ``sigma_rotvec_white_deg``, deg about body x, y, z. The estimate's, carried by
    :func:`stages.estimate.carry_checks`, was measured on another model (one without the
    diagnosis' terms, whose residual holds them) and other samples; the verdict compares
    the final model's stated sigma with what its motion alone determines
    (:func:`white_rotation_sigma_deg` of ``res`` on ``data``).
    """
    white = white_rotation_sigma_deg(res, data)
    return final.replace(checks={**final.checks, WHITE_SIGMA: white.tolist()})


#: calibration terms of the estimate and the diagnosis effects they stand for
_ESTIMATE_TERMS = {"hard_iron": "offset_nT", "soft_iron": "D", "time_offset": "time_offset_s"}


def left_out_shift(estimate: Calibration, final: Calibration, diag: Diagnosis) -> Calibration:
    """Return the user's ``estimate`` with the bias of the terms it leaves out in its sigma.

    A term the data select but a fit leaves out biases its rotation; the noise sigma does not
    see it. The diagnosis' final model holds every term the data select; the rotation vector
    of ``R_final R_estimate.T`` (body frame, deg) is that bias, measured. Each axis' sigma
    becomes ``sqrt(sigma^2 + shift^2)`` and a doubt names the terms and the shift (the
    verdict is then at most QUESTIONABLE). Nothing changes when the final model holds no term
    the estimate lacks.
    """
    left_out = [f.effect for f in diag.findings
                if f.effect not in _ESTIMATE_TERMS
                or getattr(estimate, _ESTIMATE_TERMS[f.effect]) is None]
    left_out = list(dict.fromkeys(left_out))
    if not left_out:
        return estimate
    dR = np.asarray(final.R_body_mag) @ np.asarray(estimate.R_body_mag).T
    shift = np.degrees(quat_to_rotvec(matrix_to_quat(dR)))
    sig = np.asarray(estimate.sigma_rotvec_deg, float)
    widened = np.sqrt(sig**2 + shift**2)
    names = ", ".join(x.replace("_", " ") for x in left_out)
    doubt = (f"the model was restricted: the data also ask for {names}, which move the "
             f"misalignment by {float(np.linalg.norm(shift)):.2f} deg; the sigmas include "
             "that shift (run without --estimate for the model the data select)")
    checks = {**estimate.checks,
              "left_out": {"effects": left_out, "shift_rotvec_deg": shift.tolist(),
                           "sigma_rotvec_noise_deg": sig.tolist()},
              "doubts": list(estimate.checks.get("doubts", ())) + [doubt]}
    return estimate.replace(sigma_rotvec_deg=widened, checks=checks)

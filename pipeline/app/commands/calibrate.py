"""``magalign calibrate REC.mcap --out DIR``: estimate the misalignment, write calibration.json.

Options (CONVENTIONS): ``--estimator ml|li2020|ellipsoid|dpi``, ``--reference-field E,N,U``,
``--igrf LAT,LON,ALT_M,DATE``, ``--estimate offset,soft_iron,time_offset``, ``--mag TOPIC``,
``--attitude TOPIC``, ``--robust huber|cauchy``.
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
from pathlib import Path

import numpy as np

from pipeline.app.commands._options import (
    ESTIMATE_HELP,
    add_exclude_option,
    add_field_options,
    add_topic_options,
    check_out_folder,
    exclude_from_args,
    field_from_args,
)
from pipeline.core import progress
from pipeline.core.atomic import atomic_path
from pipeline.core.errors import NotObservableError, RefusedError, UsageError
from pipeline.core.style import num
from pipeline.core.verdict import Status, plain_words, verdict_line
from pipeline.core.vocabulary import EstimateTerm, EstimatorKind
from pipeline.run.options import ProcessOptions
from pipeline.run.runner import analyse_recording
from stages.estimators.registry import DESCRIPTIONS, ESTIMATORS

log = logging.getLogger("magalign")


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("calibrate", help="estimate the magnetometer misalignment",
                       description="Estimate the misalignment between the magnetometer and "
                       "the attitude source of one recording; writes DIR/calibration.json.")
    p.add_argument("recording", help="MCAP recording")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (gets calibration.json)")
    p.add_argument(
        "--estimator",
        default="ml",
        choices=list(ESTIMATORS),
        help="estimation method (default ml): "
        + "; ".join(f"{k}: {v}" for k, v in DESCRIPTIONS.items()),
    )
    add_field_options(p)
    p.add_argument(
        "--estimate",
        default="",
        metavar="TERMS",
        help=ESTIMATE_HELP,
    )
    p.add_argument(
        "--robust",
        default="none",
        choices=["none", "huber", "cauchy"],
        help="robust loss against outliers (default none)",
    )
    add_topic_options(p)
    add_exclude_option(p)
    p.set_defaults(func=run)


#: Kept for callers of the former name (the option parsing lives in ``_options``).
reference_from_args = field_from_args


def run(args: argparse.Namespace) -> int:
    """Analyse as ``process`` does, write DIR/calibration.json and print a summary.

    The stages are :meth:`pipeline.run.plan.Plan.analysis_stages`, the same as ``diagnose``
    and ``process``: one recording and one set of options give one answer. Without
    ``--estimate`` (and with the default estimator) the answer is the model the data select;
    with it, the chosen model, its sigma widened by what the terms it leaves out do to R.
    """
    check_out_folder(args.out)  # before the analysis, not after it
    try:
        terms = frozenset(EstimateTerm(t.strip()) for t in args.estimate.split(",") if t.strip())
    except ValueError as exc:
        raise UsageError(
            f"--estimate takes offset, soft_iron, time_offset; got {args.estimate!r}"
        ) from exc
    ref = reference_from_args(args)
    options = ProcessOptions(
        estimator=EstimatorKind(args.estimator), terms=terms,
        reference_field_enu_nT=None if ref is None else (float(ref[0]), float(ref[1]),
                                                         float(ref[2])),
        mag_topic=args.mag, attitude_topic=args.attitude, robust=args.robust,
        exclude=exclude_from_args(args))
    display = progress.ProgressDisplay(1, "magalign calibrate",
                                       enabled=progress.enabled_for(sys.stderr))
    sink = progress.DirectSink(Path(args.recording).stem, display.update)
    with display, progress.use_sink(sink):
        ctx = analyse_recording(args.recording, options)
    cal = ctx.need_calibration()
    log.info("%s: %s", Path(args.recording).stem, progress.timings_text(sink.state.timings))
    if len(cal.unobservable_axes_body) >= 3:
        # A calibration.json whose rotation is arbitrary must not be written: a later run
        # (or a survey line restored with it) would take it for a result.
        raise NotObservableError(
            "the platform did not rotate: nothing about the misalignment is observable",
            path=args.recording, hint="record rotations about at least two different axes")
    if cal.verdict is not None and cal.verdict.status is Status.REFUSED:
        # Same reason: a refused fit is not written where a later run would find it.
        raise RefusedError(f"calibration refused: {refusal_reason(cal)}", path=args.recording)
    out = Path(args.out) / "calibration.json"
    with atomic_path(out, inputs=(args.recording,)) as tmp:
        tmp.write_text(cal.to_json() + "\n")
    print(summary(cal))
    print(f"wrote {out}")
    return 0


#: the verdict's pointer to the doubts it does not state, for the outputs that carry them
_MORE = re.compile(r"\s*\((\d+) more doubts? in the report\.\)\s*$")


def refusal_reason(cal) -> str:
    """Return a refused calibration's reason with its other doubts said, not pointed at.

    The verdict states one cause and counts the others "in the report"; ``calibrate``
    writes no report (nor, when it refuses, a calibration.json), so its one line names them.
    """
    assert cal.verdict is not None
    reason = cal.verdict.reason
    m = _MORE.search(reason)
    if m is None:
        return reason
    reason = reason[: m.start()]
    said = reason.lower()
    others: list[str] = []
    for check in [*cal.checks.get("refusals", ()), *cal.checks.get("doubts", ())]:
        cause = plain_words(str(check))[0]
        if cause and cause.lower() not in said and cause not in others:
            others.append(cause)
    if not others:
        return reason
    return reason + " Also: " + "; ".join(others) + "."


def summary(cal) -> str:
    """Format a few lines: rotation vector with sigmas, residual RMS, terms, warnings."""
    rv = cal.rotvec_body_mag_deg
    sg = cal.sigma_rotvec_deg
    lines = [
        f"estimator {cal.estimator}, {cal.n_samples} samples, residual RMS "
        f"{num(cal.residual_rms_nT, '.3f')} nT",
        "rotation vector body<-mag [deg]: "
        + ", ".join(
            f"{num(v, '+.4f')} +- {num(s, '.4f') if np.isfinite(s) else 'inf'}"
            for v, s in zip(rv, sg, strict=True)
        ),
        "B_enu [nT]: " + ", ".join(num(b, ".1f") for b in cal.B_enu_nT),
    ]
    if cal.rotvec_from_nominal_deg is not None:
        lines.append(
            "from nominal [deg]: " + ", ".join(num(v, "+.4f") for v in cal.rotvec_from_nominal_deg)
        )
    if cal.offset_nT is not None:
        lines.append("offset [nT]: " + ", ".join(num(v, ".2f") for v in cal.offset_nT))
    if cal.time_offset_s is not None:
        lines.append(
            f"time offset: {num(cal.time_offset_s * 1e3, '.3f')} ms +- "
            f"{num((cal.sigma_time_offset_s or 0) * 1e3, '.3f')} ms"
        )
    lines += [f"warning: {w}" for w in cal.warnings]
    lines += [f"not estimated: {d['term']}: {d['reason']}" for d in cal.not_estimated]
    if cal.n_eff is not None:
        lines.append(f"effective independent samples behind the sigmas: {num(cal.n_eff, '.0f')} of "
                     f"{cal.n_samples} (correlated residuals)")

    lines.append(verdict_line(cal))
    if cal.verdict is not None:
        lines.append(cal.verdict.reason)  # the status ends the line above
    return "\n".join(lines)

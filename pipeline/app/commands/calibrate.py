"""``magalign calibrate REC.mcap --out DIR``: estimate the misalignment, write calibration.json.

Options (CONVENTIONS): ``--estimator ml|li2020|ellipsoid|dpi``, ``--reference-field E,N,U``,
``--igrf LAT,LON,ALT_M,DATE``, ``--estimate offset,soft_iron,time_offset``, ``--mag TOPIC``,
``--attitude TOPIC``, ``--robust huber|cauchy``.
"""

from __future__ import annotations

import argparse
import logging
import re
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
from pipeline.core.style import GLUE, minus, num, terminal_width, wrap
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
    display = progress.display_for(1, "magalign calibrate")
    sink = progress.DirectSink(Path(args.recording).stem, display.update)
    with display, progress.use_sink(sink):
        ctx = analyse_recording(args.recording, options)
        display.run_done(sink.state.name)
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


def _pm(values, sigmas, spec: str) -> str:
    """Return ``+1.23 ± 0.04, ...``: each value with its sigma (``inf``: not determined)."""
    sig = [None] * len(values) if sigmas is None else list(sigmas)
    # a value and its sigma stay on one line when the text is wrapped
    return ", ".join(num(v, spec) + ("" if s is None else
                                     f"{GLUE}\u00b1{GLUE}" + (num(s, spec.lstrip("+"))
                                                            if np.isfinite(s) else "inf"))
                     for v, s in zip(values, sig, strict=True))


def _count(n: float) -> str:
    """Return a count with a space between thousands (11 999), as the report writes it.

    The space is one :func:`~pipeline.core.style.wrap` does not break at: a count is one
    number on one line.
    """
    return f"{int(round(float(n))):,}".replace(",", GLUE)


def model_words(cal) -> str:
    """Say in words what the calibration's model holds, for a person (no stage names)."""
    terms = ["misalignment", "background field"]
    if cal.offset_nT is not None:
        terms.append("offset (hard iron)")
    if cal.D is not None:
        terms.append("soft iron")
    if cal.time_offset_s is not None:
        terms.append("time offset")
    terms += [k.replace("_", " ") for k in (cal.effects or {})]
    how = ("the model the diagnosis selected" if cal.estimator == "diagnose"
           else f"the {cal.estimator} estimator")
    return f"fitted with {how}: " + ", ".join(terms)


def event_words(cal) -> list[str]:
    """Say the field offsets the final model holds for part of the recording (a magnet).

    One line per event of an effect with windows and a field offset (``hard_iron_step``):
    its size (the offset's magnitude, nT) and when it acted, in the final model's values.
    """
    out = []
    for kind, value in (cal.effects or {}).items():
        for p in value if isinstance(value, list) else [value]:
            if not isinstance(p, dict) or p.get("offset_nT") is None or not p.get("windows_s"):
                continue
            size = float(np.linalg.norm(np.asarray(p["offset_nT"], float)))
            when = ", ".join(f"{a:.1f}-{b:.1f}{GLUE}s" for a, b in p["windows_s"])
            out.append(f"found: a {kind.replace('_', ' ')} of "
                       f"{_count(size)} nT at {when} (a magnet or "
                       "magnetic object near the sensor)")
    return out


def summary(cal, width: int | None = None) -> str:
    """Format the result in words: the model, the values with their sigmas, the verdict.

    The values carry the digits of the report's calibration table (one value everywhere);
    every line is wrapped to ``width`` columns (the terminal's, 80 when unknown) between
    words, so that no number is cut.
    """
    rv = cal.rotvec_body_mag_deg
    sg = cal.sigma_rotvec_deg
    texts = [
        model_words(cal) + f"; {_count(cal.n_samples)} samples, residual "
        f"{num(cal.residual_rms_nT, '.1f')} nT RMS",
        "misalignment as a rotation vector (deg, body x, y, z): " + _pm(rv, sg, "+.3f"),
        "background field (nT, east, north, up): " + _pm(cal.B_enu_nT, cal.sigma_B_enu_nT,
                                                         ".1f"),
    ]
    if cal.rotvec_from_nominal_deg is not None:
        texts.append("from the nominal mounting (deg, body x, y, z): "
                     + _pm(cal.rotvec_from_nominal_deg, None, "+.3f"))
    if cal.offset_nT is not None:
        texts.append("offset (nT, magnetometer x, y, z): "
                     + _pm(cal.offset_nT, cal.sigma_offset_nT, ".1f"))
    if cal.time_offset_s is not None:
        sig = cal.sigma_time_offset_s
        texts.append(f"time offset: {num(cal.time_offset_s * 1e3, '+.2f')}"
                     + ("" if sig is None else f" \u00b1 {num(sig * 1e3, '.2f')}") + " ms")
    texts += event_words(cal)
    texts += [f"warning: {w}" for w in cal.warnings]
    texts += [f"not estimated: {d['term'].replace('_', ' ')}: {d['reason']}"
              for d in cal.not_estimated]
    if cal.n_eff is not None:
        texts.append(f"the sigmas rest on {_count(cal.n_eff)} independent samples of "
                     f"{_count(cal.n_samples)} (the residuals are correlated in time)")
    w = terminal_width() if width is None else width
    lines: list[str] = []
    for t in texts:
        lines += wrap(minus(t), "", "    ", w)
    lines += wrap(minus(verdict_line(cal)), "", "    ", w)
    if cal.verdict is not None:  # the status ends the line above
        # calibrate writes no report: the doubts the reason counts are said here
        lines += wrap(minus(refusal_reason(cal)), "  why: ", "       ", w)
    return "\n".join(lines)

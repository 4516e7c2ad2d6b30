"""``magalign diagnose REC.mcap --out DIR``: find, name, model and verify what the model leaves out.

Writes ``DIR/diagnosis.json`` and ``DIR/calibration.json`` (the final model, CONVENTIONS) and
prints the findings table.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from pipeline.app.commands._options import (
    add_exclude_option,
    add_field_options,
    add_topic_options,
    check_out_folder,
    exclude_from_args,
    field_from_args,
)
from pipeline.app.commands.calibrate import refusal_reason
from pipeline.core import progress
from pipeline.core.atomic import write_text_atomic
from pipeline.core.style import minus, terminal_width, unsigned_zeros_in, wrap
from pipeline.core.verdict import verdict_line
from pipeline.run.options import ProcessOptions
from pipeline.run.runner import analyse_recording

log = logging.getLogger("magalign")


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("diagnose", help="find and model the physics the calibration left out",
                       description="Find, name, model and verify what the calibration model "
                       "leaves out; writes DIR/diagnosis.json and DIR/calibration.json.")
    p.add_argument("recording", help="MCAP recording")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    add_topic_options(p)
    add_field_options(p)
    add_exclude_option(p)
    p.set_defaults(func=run)


def diagnose_file(path: str | Path, *, mag_topic: str | None = None,
                  attitude_topic: str | None = None,
                  reference_field_enu_nT: tuple[float, float, float] | None = None,
                  exclude: tuple = ()):
    """Analyse one recording as ``process`` and ``calibrate`` do; returns the final Context.

    The stages are :meth:`pipeline.run.plan.Plan.analysis_stages` (estimate, diagnosis,
    verdict): the calibration written is the one ``process`` restores with.
    """
    options = ProcessOptions(reference_field_enu_nT=reference_field_enu_nT,
                             mag_topic=mag_topic, attitude_topic=attitude_topic,
                             exclude=tuple(exclude))
    return analyse_recording(path, options)


def run(args: argparse.Namespace) -> int:
    """Diagnose and write the outputs; returns the exit status."""
    check_out_folder(args.out)  # before the analysis, not after it
    ref = field_from_args(args)
    exclude = exclude_from_args(args)
    display = progress.display_for(1, "magalign diagnose")
    sink = progress.DirectSink(Path(args.recording).stem, display.update)
    with display, progress.use_sink(sink):
        ctx = diagnose_file(args.recording, mag_topic=args.mag, attitude_topic=args.attitude,
                            reference_field_enu_nT=None if ref is None
                            else (float(ref[0]), float(ref[1]), float(ref[2])),
                            exclude=exclude)
        display.run_done(sink.state.name)
        cal = ctx.need_calibration()
    log.info("%s: %s", Path(args.recording).stem, progress.timings_text(sink.state.timings))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "diagnosis.json",
                      json.dumps(unsigned_zeros_in(ctx.diagnosis.to_dict()), indent=2,
                                 allow_nan=False))
    write_text_atomic(out / "calibration.json", cal.to_json())
    width = terminal_width()
    print(ctx.diagnosis.table(width))
    lines = wrap(minus(verdict_line(cal)), "", "    ", width)
    if cal.verdict is not None:
        # diagnose writes no report: the doubts the reason counts are said here
        lines += wrap(minus(refusal_reason(cal)), "  why: ", "       ", width)
    print("\n".join(lines))
    print("the explanation of each finding is in diagnosis.json:")
    print(f"wrote {out / 'diagnosis.json'}")
    print(f"wrote {out / 'calibration.json'}")
    return 0

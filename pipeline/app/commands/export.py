"""``magalign export CALIBRATION.json --format ardupilot|magcal|ros-tf|yaml``: other tools' terms.

Prints to stdout; ``docs/exports.md`` describes each format. The file carries the verdict
as comments and only the terms that were estimated. A calibration whose verdict is REFUSED
is not exported (exit status 2), nor one the format cannot carry without a value nobody
estimated; a QUESTIONABLE one is, with a warning on stderr besides the file's own comments.
"""

from __future__ import annotations

import argparse
import sys
import warnings

from pipeline.app.exports import FORMATS, export_text
from pipeline.core.errors import QuestionableCalibrationWarning
from pipeline.core.verdict import Status
from pipeline.model.calibration import Calibration


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("export", help="print a calibration in another tool's terms",
                       description="Print a calibration.json in another tool's terms: "
                       "ArduPilot compass parameters, MATLAB magcal A and b, a ROS 2 static "
                       "transform command, or plain YAML. The output starts with comments "
                       "giving the verdict and holds only the terms that were estimated; a "
                       "refused calibration is not exported.")
    p.add_argument("calibration", metavar="CALIBRATION.json",
                   help="calibration.json written by magalign calibrate, diagnose or process")
    p.add_argument("--format", required=True, choices=FORMATS,
                   help="ardupilot, magcal, ros-tf or yaml")
    p.add_argument("--body-frame", default="base_link", metavar="FRAME",
                   help="ros-tf: parent frame id, the attitude source's body (default "
                   "base_link)")
    p.add_argument("--mag-frame", default="mag", metavar="FRAME",
                   help="ros-tf: child frame id, the magnetometer (default mag)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Load, export (which refuses what must not be exported), print."""
    path = args.calibration
    cal = Calibration.load(path)
    text = export_text(cal, args.format, path, body_frame=args.body_frame,
                       mag_frame=args.mag_frame)
    if cal.verdict is not None and cal.verdict.status is Status.QUESTIONABLE:
        # the reason is in the exported text; stderr only flags it for whoever runs this
        warnings.warn(f"{path}: QUESTIONABLE; the reason is in the output's comments",
                      QuestionableCalibrationWarning, stacklevel=2)
    sys.stdout.write(text)
    return 0

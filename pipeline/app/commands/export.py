"""``magalign export CALIBRATION.json --format ardupilot|magcal|ros-tf|yaml``: other tools' terms.

Prints to stdout; ``docs/exports.md`` describes each format. A calibration whose verdict is
REFUSED is not exported (exit status 2); a QUESTIONABLE one is, with a warning on stderr.
"""

from __future__ import annotations

import argparse
import sys
import warnings

from pipeline.core.errors import InputError, QuestionableCalibrationWarning


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    from pipeline.app.exports import FORMATS

    p = sub.add_parser("export", help="print a calibration in another tool's terms",
                       description="Print a calibration.json in another tool's terms: "
                       "ArduPilot compass parameters, MATLAB magcal A and b, a ROS 2 static "
                       "transform command, or plain YAML.")
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
    """Load, check the verdict, print the chosen format."""
    from pipeline.app.exports import check_exportable, to_ardupilot, to_magcal, to_ros_tf, to_yaml
    from pipeline.core.verdict import Status
    from pipeline.model.calibration import Calibration

    path = args.calibration
    cal = Calibration.load(path)
    if cal.verdict is not None and cal.verdict.status is Status.REFUSED:
        raise InputError(f"the calibration was refused ({cal.verdict.reason}); it is not "
                         "exported", path=path, hint="record the motion the reason asks for "
                         "and calibrate again")
    check_exportable(cal, path)
    if cal.verdict is not None and cal.verdict.status is Status.QUESTIONABLE:
        warnings.warn(f"{path}: the calibration is QUESTIONABLE ({cal.verdict.reason}); "
                      "exported anyway", QuestionableCalibrationWarning, stacklevel=2)
    src = f"from {path}"
    if args.format == "ardupilot":
        text = to_ardupilot(cal, src)
    elif args.format == "magcal":
        text = to_magcal(cal, src)
    elif args.format == "ros-tf":
        text = to_ros_tf(cal, args.body_frame, args.mag_frame)
    else:
        text = to_yaml(cal, src)
    sys.stdout.write(text)
    return 0

"""Options shared by several subcommands: one spelling, metavar and help text each.

``--mag TOPIC`` / ``--attitude TOPIC`` choose channels; ``--reference-field E,N,U`` /
``--igrf LAT,LON,ALT_M,DATE`` give the background field (CONVENTIONS, "Command line").
:func:`check_mcap_file` refuses a file that is not an MCAP recording before a command
creates any output.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pipeline.core.errors import UsageError
from pipeline.core.vocabulary import ExcludeWindow
from pipeline.io.mcap_format import MAGIC
from pipeline.io.mcap_scan import check_magic, open_error  # the reader's own words
from pipeline.model.igrf import igrf_enu_nT

#: The first 8 bytes of every MCAP file (https://mcap.dev/spec).

MAG_HELP = ("magnetometer topic; needed only when the recording has more than one "
            "magnetometer channel")
ATTITUDE_HELP = ("attitude topic; needed only when the recording has more than one "
                 "attitude channel")
REFERENCE_FIELD_HELP = ("known background field in nT, east, north, up; it is then not "
                        "estimated")
ESTIMATE_HELP = ("comma-separated terms to estimate beside the rotation: offset (the "
                 "constant offset in the magnetometer's frame, nT: sensor bias and hard "
                 "iron; diagnose reports it as hard_iron), soft_iron (scale, soft iron and "
                 "non-orthogonality), time_offset (magnetometer stamps late or early)")
EXCLUDE_HELP = ("leave this stretch out of the fit and the verdict (repeatable): START:END in "
                "seconds from the first magnetometer sample (12.5:30) or UTC "
                "(2026-11-20T10:03:00Z:2026-11-20T10:04:30Z); it is still restored")
IGRF_HELP = ("background field from the IGRF model at this place and date: latitude and "
             "longitude in degrees, altitude in metres, date as YYYY-MM-DD")


def add_topic_options(p: argparse.ArgumentParser) -> None:
    """Add ``--mag TOPIC`` and ``--attitude TOPIC`` (defaults None: found by message type)."""
    p.add_argument("--mag", default=None, metavar="TOPIC", help=MAG_HELP)
    p.add_argument("--attitude", default=None, metavar="TOPIC", help=ATTITUDE_HELP)


def add_field_options(p: argparse.ArgumentParser) -> None:
    """Add ``--reference-field E,N,U`` and ``--igrf LAT,LON,ALT_M,DATE`` (exclusive)."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--reference-field", default=None, metavar="E,N,U",
                   help=REFERENCE_FIELD_HELP)
    g.add_argument("--igrf", default=None, metavar="LAT,LON,ALT_M,DATE", help=IGRF_HELP)


def _floats(text: str, n: int, what: str) -> list[float]:
    """Parse ``n`` comma-separated finite numbers, or raise UsageError naming the option."""
    parts = [p.strip() for p in text.split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError as exc:
        raise UsageError(f"{what} must be {n} comma-separated numbers, got {text!r}") from exc
    if len(vals) != n or not all(np.isfinite(vals)):
        raise UsageError(f"{what} must be {n} comma-separated finite numbers, got {text!r}")
    return vals


def field_from_args(args: argparse.Namespace) -> np.ndarray | None:
    """Return the background field (ENU, nT) asked for on the command line, or None.

    Parameters
    ----------
    args : argparse.Namespace
        With ``reference_field`` and/or ``igrf`` (either may be missing or None).

    Returns
    -------
    ndarray, shape (3,), or None
        ``--reference-field`` as given, or the IGRF field at ``--igrf``'s place and date;
        None when neither was given (the field is estimated).

    Raises
    ------
    UsageError
        A malformed option.
    ConfigError
        An IGRF date or place outside the model.

    """
    if getattr(args, "reference_field", None):
        return np.array(_floats(args.reference_field, 3, "--reference-field"))
    if getattr(args, "igrf", None):
        parts = args.igrf.split(",")
        if len(parts) != 4:
            raise UsageError(f"--igrf must be LAT,LON,ALT_M,DATE, got {args.igrf!r}")
        lat, lon, alt = _floats(",".join(parts[:3]), 3, "--igrf LAT,LON,ALT_M")

        return np.asarray(igrf_enu_nT(lat, lon, alt, parts[3].strip()), float).reshape(3)
    return None


def check_mcap_file(path: str | Path) -> None:
    """Refuse, before any output is made, a path that is not an MCAP file.

    Only the first bytes are read (the full reader says the same, later and at more cost).

    Raises
    ------
    InputError
        No such file, a folder, or unreadable.
    NotMcapError
        Empty, or not starting with the MCAP magic bytes.

    """
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(len(MAGIC))
    except OSError as exc:
        raise open_error(p, exc) from None
    check_magic(head, p)


def check_out_folder(path: str | Path) -> None:
    """Refuse, before any work, an ``--out`` folder that is an existing file."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UsageError("exists and is not a folder (--out takes a folder)", path=p)


def check_out_file(path: str | Path) -> None:
    """Refuse, before any work, an ``--out`` file name that is an existing folder."""
    p = Path(path)
    if p.is_dir():
        raise UsageError("is a folder (--out takes a file name, such as REC.mcap)", path=p)
    if p.parent.exists() and not p.parent.is_dir():
        raise UsageError("is not a folder, so no file can be written in it", path=p.parent)


def add_exclude_option(p: argparse.ArgumentParser) -> None:
    """Add ``--exclude START:END`` (repeatable; default none)."""
    p.add_argument("--exclude", action="append", default=None, metavar="START:END",
                   help=EXCLUDE_HELP)


def exclude_from_args(args: argparse.Namespace) -> tuple[ExcludeWindow, ...]:
    """Return the ``--exclude`` windows, or raise UsageError naming the malformed one."""
    out = []
    for text in getattr(args, "exclude", None) or ():
        try:
            out.append(ExcludeWindow.parse(text))
        except ValueError as exc:
            raise UsageError(f"--exclude {exc}") from None
    return tuple(out)
